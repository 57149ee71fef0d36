"""A GAIA-2 generation mode from a `generate.py model=gaia2` config: the clip of `context` (encoded), the user's
commands and added agents on its generated frames, and the pipeline call of `mode` (scratch, rollout, inpaint, edit;
GAIA-2 report, inference). `generate.py` and the GAIA-2 benchmarks both start here."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from gaia_app.data.clip import ClipError
from gaia_app.data.latent_cache import LatentClip, find_latent_clips, read_latent_clip
from gaia_app.pipelines.gaia1_inputs import folder_clip, future_actions
from gaia_app.pipelines.gaia2 import Gaia2Output, Gaia2Pipeline, check_metadata, with_labels
from gaia_app.pipelines.gaia2_edits import InpaintRegion, cut_steps, with_added_agents


def latent_steps(cfg: DictConfig) -> int:
    """Latent steps of the clip that the mode uses."""
    g = cfg.model
    if g.steps < 1 or not 0 < g.context_steps < g.steps:
        raise ValueError(f"model.steps={g.steps}, model.context_steps={g.context_steps}: "
                         "need 0 < context_steps < steps")
    if cfg.mode == "rollout":
        if g.chunks < 1:
            raise ValueError(f"model.chunks={g.chunks}: expected at least 1")
        return g.context_steps + g.chunks * (g.steps - g.context_steps)
    return g.steps


def source_clip(cfg: DictConfig, pipeline: Gaia2Pipeline, steps: int) -> LatentClip:
    """The clip of `cfg.context`, encoded, with at least `steps` latent steps."""
    c, frames = cfg.context, steps * pipeline.temporal
    if c.source == "latents":
        if not c.folder:
            raise ValueError("context.source=latents needs context.folder=<a latent cache split or clip folder>")
        folders = [Path(c.folder)] if (Path(c.folder) / "mean.npy").is_file() else find_latent_clips(c.folder)
        if not 0 <= c.index < len(folders):
            raise ClipError(f"context.index={c.index}: {c.folder} holds {len(folders)} latent clips")
        clip = read_latent_clip(folders[c.index])
    elif c.source == "synthetic":
        if "source" not in cfg.data or "cameras" not in cfg.data.source:
            raise ValueError("context.source=synthetic with model=gaia2 renders the rig of `data`: "
                             "use data=synthetic_rig")
        world = instantiate(cfg.data.source, num_clips=c.index + 1, seed=c.seed, clip_len=frames)
        clip = pipeline.encode(world[c.index])
    elif c.source == "folder":
        if not c.folder:
            raise ValueError("context.source=folder needs context.folder=<a clip folder or a root of them>")
        clip = pipeline.encode(folder_clip(c.folder, c.index))
    else:
        raise ValueError(f"context.source={c.source!r}: expected synthetic, folder or latents")
    if clip.mean.shape[1] < steps:
        raise ClipError(f"clip '{clip.clip_id}' has {clip.mean.shape[1]} latent steps "
                        f"({clip.mean.shape[1] * clip.temporal_downsampling} frames); mode={cfg.mode} needs {steps}")
    return cut_steps(clip, steps)


def commanded(cfg: DictConfig, clip: LatentClip, first_frame: int, fields: list[str]) -> LatentClip:
    """The clip with the user's actions, prompt and metadata on frames first_frame.. (absent settings: the clip's own).
    fields: the metadata fields of the world model."""
    metadata = OmegaConf.to_container(cfg.model.metadata) if cfg.model.metadata else {}
    check_metadata(metadata, fields)
    actions = None
    if cfg.speed is not None or cfg.curvature is not None:
        if clip.actions is None:
            raise ClipError(f"clip '{clip.clip_id}' has no actions; speed= / curvature= replace existing ones")
        n = clip.timestamps.shape[0] - first_frame
        start_speed = float(clip.actions[max(first_frame - 1, 0), 0])
        actions = future_actions(plain(cfg.speed), plain(cfg.curvature), n, clip.fps, start_speed)
    return with_labels(clip, first_frame, actions, cfg.prompt, metadata)


def plain(value: Any) -> Any:
    """A config node as plain Python containers (anything else unchanged)."""
    return OmegaConf.to_container(value) if OmegaConf.is_config(value) else value


def first_generated_frame(cfg: DictConfig, pipeline: Gaia2Pipeline) -> int:
    """The first frame the mode generates: after the clean context steps of a rollout, else 0."""
    return cfg.model.context_steps * pipeline.temporal if cfg.mode == "rollout" else 0


def conditioned_clip(cfg: DictConfig, pipeline: Gaia2Pipeline) -> LatentClip:
    """The clip of `cfg.context` with the user's commands (speed, curvature, prompt, model.metadata) and
    model.add_agents on the generated frames."""
    first = first_generated_frame(cfg, pipeline)
    clip = commanded(cfg, source_clip(cfg, pipeline, latent_steps(cfg)), first, pipeline.metadata.fields)
    return with_added_agents(clip, plain(cfg.model.add_agents) or [], first)


def inpaint_region(cfg: DictConfig) -> InpaintRegion:
    """model.inpaint as an InpaintRegion."""
    spec = cfg.model.inpaint
    cameras = None if spec.cameras is None else tuple(str(name) for name in spec.cameras)
    return InpaintRegion(str(spec.region), tuple(float(x) for x in spec.box), cameras)


def sample(cfg: DictConfig, pipeline: Gaia2Pipeline, clip: LatentClip) -> Gaia2Output:
    """cfg.num_futures samples of cfg.mode from `clip` (the pipeline call of the mode)."""
    g = cfg.model
    shared = {"num_futures": cfg.num_futures, "seed": int(cfg.seed), "drop": list(g.drop)}
    if cfg.mode == "rollout":
        return pipeline.rollout(clip, g.context_steps, g.steps, g.chunks, **shared)
    if cfg.mode == "scratch":
        return pipeline.scratch(clip, g.steps, **shared)
    if cfg.mode == "inpaint":
        return pipeline.inpaint(clip, g.steps, inpaint_region(cfg), **shared)
    return pipeline.edit(clip, g.steps, g.edit_strength, **shared)
