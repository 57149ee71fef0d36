"""Rerun viewer layouts (blueprints) for training runs and multi-camera rigs.

Entity paths used across gaia_app (see docs/rerun.md):
  /metrics/<key>      scalars on the `step` timeline (`train/loss` -> /metrics/train/loss)
  /hparams, /config   static Markdown documents
  /<stage>/<name>     media from RerunMediaCallback (`val/reconstruction`)
  /log                text logs
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import rerun.blueprint as rrb


def _media_view(path: str) -> rrb.View:
    """A 2D view of one image/video entity, titled by its path."""
    path = "/" + path.strip("/")
    return rrb.Spatial2DView(origin=path, name=path.lstrip("/"))


def training_blueprint(
    media_paths: Sequence[str] = (),
    metrics_origin: str = "/metrics",
    grid_columns: int = 3,
) -> rrb.Blueprint:
    """Metrics on the left; media grid, hyperparameters and text logs on the right.

    media_paths: entity paths of images/videos/token maps to show in the grid. When empty the
        viewer adds views for unlisted entities by itself (auto_views), so media still appear.
    """
    docs = rrb.Tabs(
        rrb.TextDocumentView(origin="/hparams", name="hparams"),
        rrb.TextDocumentView(origin="/config", name="config"),
        rrb.TextLogView(origin="/", name="log"),
    )
    right: list[rrb.Container | rrb.View] = [docs]
    if media_paths:
        grid = rrb.Grid(*[_media_view(p) for p in media_paths], grid_columns=grid_columns)
        right.insert(0, grid)
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.TimeSeriesView(origin=metrics_origin, name="metrics"),
            rrb.Vertical(*right, row_shares=[3, 1] if media_paths else None),
            column_shares=[2, 3],
        ),
        auto_views=not media_paths,
        collapse_panels=True,
    )


def rig_view(
    camera_names: Sequence[str],
    rig_origin: str = "/world/rig",
    world_origin: str = "/world",
    scalars_origin: str = "/actions",
    text_origin: str = "/text",
    grid_columns: int = 3,
    name: str | None = None,
) -> rrb.Vertical:
    """One clip of a rig: a 2D view per camera in a grid, the 3D world, actions and text (see rig_blueprint)."""
    cams = [rrb.Spatial2DView(origin=f"{rig_origin}/{c}", name=c) for c in camera_names]
    return rrb.Vertical(
        rrb.Grid(*cams, grid_columns=grid_columns),
        rrb.Horizontal(
            rrb.Spatial3DView(origin=world_origin, name="world"),
            rrb.TimeSeriesView(origin=scalars_origin, name="actions"),
            rrb.TextLogView(origin=text_origin, name="text"),
        ),
        row_shares=[3, 2],
        name=name,
    )


def rig_blueprint(camera_names: Sequence[str], **view_options: Any) -> rrb.Blueprint:
    """Multi-camera rollout: one 2D view per camera in a grid, the 3D world, actions and text.

    camera_names: entity names under `rig_origin` (`front` -> /world/rig/front), in display order.
    Frames live on the `frame` timeline; each camera entity carries its Pinhole and extrinsics,
    so the 3D view shows the frusta and the 2D views show images with projected boxes.
    view_options: rig_view's origins and grid_columns.
    """
    return rrb.Blueprint(rig_view(camera_names, **view_options), collapse_panels=True)


def rig_tabs_blueprint(camera_names: Sequence[str], roots: Sequence[str], grid_columns: int = 3) -> rrb.Blueprint:
    """Several clips of one rig logged by viz/world.log_world under `roots` (e.g. the real clip and each generated
    sample): a tab per root, each a camera grid over its 3D world (frusta, agent boxes), actions and text."""
    tabs = [rig_view(camera_names, f"{root}/ego/rig", root, f"{root}/actions", f"{root}/text", grid_columns,
                     name=root.strip("/")) for root in roots]
    return rrb.Blueprint(rrb.Tabs(*tabs), collapse_panels=True)


def rollout_blueprint(num_futures: int, has_real: bool, has_actions: bool, has_guidance: bool) -> rrb.Blueprint:
    """A `generate.py` rollout (entity paths of gaia_app/tasks/rollout.py): the real clip and every future side
    by side, their token maps below, then perplexity, commanded actions, guidance scale and the prompt/phase log.
    """
    videos = ([rrb.Spatial2DView(origin="/real", name="real")] if has_real else []) + [
        rrb.Spatial2DView(origin=f"/future_{k}/video", name=f"future {k}") for k in range(num_futures)]
    tokens = [rrb.Spatial2DView(origin=f"/future_{k}/tokens", name=f"tokens {k}") for k in range(num_futures)]
    series: list[rrb.View] = [rrb.TimeSeriesView(
        origin="/", contents=[f"/future_{k}/perplexity" for k in range(num_futures)], name="perplexity")]
    if has_actions:
        series.append(rrb.TimeSeriesView(origin="/actions", name="actions"))
    if has_guidance:
        series.append(rrb.TimeSeriesView(origin="/guidance", name="guidance"))
    series.append(rrb.TextLogView(origin="/", name="prompt / phase"))
    return rrb.Blueprint(
        rrb.Vertical(rrb.Horizontal(*videos), rrb.Horizontal(*tokens), rrb.Horizontal(*series),
                     row_shares=[3, 2, 2]),
        collapse_panels=True,
    )


def showcase_blueprint(commands: Sequence[str], prompts: Sequence[str]) -> rrb.Blueprint:
    """`generate.py mode=showcase` (entity paths of gaia_app/tasks/showcase.py): the real continuation (raw and through
    the tokenizer) and one future per command side by side, the prompt rollouts below, then the commanded speed and
    curvature of every future."""
    steered = [rrb.Spatial2DView(origin="/commands/real", name="real continuation"),
               rrb.Spatial2DView(origin="/commands/real_tokenized", name="real, through the tokenizer")] + [
        rrb.Spatial2DView(origin=f"/commands/{name}", name=name) for name in commands]
    prompted = [rrb.Spatial2DView(origin=f"/prompts/{name}", name=name) for name in prompts]
    series = [rrb.TimeSeriesView(origin="/actions/speed", name="commanded speed (m/s)"),
              rrb.TimeSeriesView(origin="/actions/curvature", name="commanded curvature (1/m)")]
    return rrb.Blueprint(
        rrb.Vertical(rrb.Horizontal(*steered), rrb.Horizontal(*prompted), rrb.Horizontal(*series),
                     row_shares=[3, 3, 2]),
        collapse_panels=True,
    )
