"""Edits of a GAIA-2 latent clip before generation: cut it to whole latent steps, add agents to its labels, and the
region an inpainting call regenerates (GAIA-2 report, inference: scenario editing and inpainting).

Legend: v cameras, t latent steps (τ frames each), T = t·τ frames, h w latent grid, N agents per frame.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from gaia_app.data.clip import AGENT_CATEGORIES, AgentBoxes
from gaia_app.data.latent_cache import LatentClip
from gaia_app.models.gaia2.conditioning import WorldConditions
from gaia_app.pipelines.gaia2_world_model import agent_token_positions

AGENT_KEYS = {"category", "centre", "size", "yaw", "velocity"}
INPAINT_REGIONS = ("agents", "box")


def cut_steps(clip: LatentClip, steps: int) -> LatentClip:
    """The first `steps` latent steps of `clip` and the labels of their frames."""
    frames = steps * clip.temporal_downsampling

    def cut(labels: Any) -> Any:
        return None if labels is None else labels[:frames]

    return replace(clip, mean=clip.mean[:, :steps], logvar=clip.logvar[:, :steps], timestamps=clip.timestamps[:frames],
                   actions=cut(clip.actions), text=cut(clip.text), agents=cut(clip.agents),
                   frame_meta=cut(clip.frame_meta))


def with_added_agents(clip: LatentClip, specs: Sequence[Mapping[str, Any]], first_frame: int) -> LatentClip:
    """The clip with the agents of `specs` added to its own on frames first_frame..: each a box in the ego frame at
    the first of those frames (centre (x forward, y left, z up) m, size (length, width, height) m, yaw rad,
    category), moving at `velocity` (vx, vy) m/s relative to the ego; a new track id each. The specs are read as
    `model.add_agents[i]` entries, so errors name that setting."""
    if not specs:
        return clip
    frames = clip.timestamps.shape[0]
    own = clip.agents or [AgentBoxes.empty() for _ in range(frames)]
    next_id = 1 + max((int(a.track_id.max()) for a in own if len(a)), default=0)
    added = [added_agent(spec, i, next_id + i) for i, spec in enumerate(specs)]
    elapsed = clip.timestamps - clip.timestamps[min(first_frame, frames - 1)]
    agents = list(own)
    for f in range(first_frame, frames):
        moved = [replace(box, centre=box.centre + np.r_[velocity * elapsed[f], 0.0]) for box, velocity in added]
        agents[f] = concat_agents([own[f], *moved])
    return replace(clip, agents=agents)


def added_agent(spec: Any, index: int, track_id: int) -> tuple[AgentBoxes, np.ndarray]:
    """One model.add_agents entry → (its box at the first edited frame, its (vx, vy) relative velocity m/s)."""
    where = f"model.add_agents[{index}]"
    if not isinstance(spec, Mapping):
        raise ValueError(f"{where}: expected a mapping with category, centre, size (and yaw, velocity), got {spec!r}")
    unknown, missing = sorted(set(spec) - AGENT_KEYS), sorted({"category", "centre", "size"} - set(spec))
    if unknown or missing:
        raise ValueError(f"{where}: unknown keys {unknown}, missing keys {missing} (keys: {sorted(AGENT_KEYS)})")
    if spec["category"] not in AGENT_CATEGORIES:
        raise ValueError(f"{where}.category={spec['category']!r}: expected one of {list(AGENT_CATEGORIES)}")
    centre, size = (numbers(spec[key], 3, f"{where}.{key}") for key in ("centre", "size"))
    velocity = numbers(spec.get("velocity", [0.0, 0.0]), 2, f"{where}.velocity")
    if (size <= 0).any():
        raise ValueError(f"{where}.size={size.tolist()}: length, width and height must be positive metres")
    yaw = float(numbers([spec.get("yaw", 0.0)], 1, f"{where}.yaw")[0])
    box = AgentBoxes(centre[None], size[None], [yaw], [AGENT_CATEGORIES.index(spec["category"])], [track_id])
    return box, velocity


def numbers(value: Any, n: int, where: str) -> np.ndarray:
    """`value` as n finite floats, or an error naming `where`."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        array = None
    if array is None or array.shape != (n,) or not np.isfinite(array).all():
        raise ValueError(f"{where}={value!r}: expected {n} finite numbers")
    return array


def concat_agents(parts: list[AgentBoxes]) -> AgentBoxes:
    """The boxes of every part, in order, as one frame's AgentBoxes."""
    return AgentBoxes(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                        ("centre", "size", "yaw", "category", "track_id")))


@dataclass(frozen=True)
class InpaintRegion:
    """What `Gaia2Pipeline.inpaint` regenerates (the rest of the clip is kept).

    region: "agents" (the latent cells under any visible agent box) or "box"; box: (x0, y0, x1, y1) as fractions of
    the image (region "box"); cameras: camera names the box applies to (None: every camera).
    """

    region: str = "agents"
    box: tuple[float, float, float, float] = (0.0, 0.0, 1.0, 1.0)
    cameras: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        if self.region not in INPAINT_REGIONS:
            raise ValueError(f"model.inpaint.region={self.region!r}: expected agents or box")
        x0, y0, x1, y1 = (float(x) for x in self.box)
        if not 0 <= x0 < x1 <= 1 or not 0 <= y0 < y1 <= 1:
            raise ValueError(f"model.inpaint.box={list(self.box)}: expected fractions x0 < x1, y0 < y1 in [0, 1]")

    def mask(self, clip: LatentClip, cond: WorldConditions, shape: Sequence[int], patch: int) -> torch.Tensor:
        """(1, v, t, h, w) True where the latents (shape (1, v, t, C, h, w)) are regenerated."""
        _, v, t, _, h, w = shape
        if self.region == "agents":
            return agent_cells(clip, cond, (v, t, h, w), patch)
        names = [c.name for c in clip.cameras]
        chosen = names if self.cameras is None else list(self.cameras)
        unknown = sorted(set(chosen) - set(names))
        if unknown:
            raise ValueError(f"model.inpaint.cameras: {unknown} not in the clip's rig {names}")
        x0, y0, x1, y1 = (float(x) for x in self.box)
        mask = torch.zeros(1, v, t, h, w, dtype=torch.bool)
        rows = slice(math.floor(y0 * h), max(math.ceil(y1 * h), math.floor(y0 * h) + 1))
        cols = slice(math.floor(x0 * w), max(math.ceil(x1 * w), math.floor(x0 * w) + 1))
        for name in chosen:
            mask[0, names.index(name), :, rows, cols] = True
        return mask


def agent_cells(clip: LatentClip, cond: WorldConditions, grid: tuple[int, int, int, int], patch: int) -> torch.Tensor:
    """(1, v, t, h, w) True on the latent cells of every token an agent box covers on any step."""
    v, t, h, w = grid
    positions = agent_token_positions(cond, (h, w), patch).cpu()
    if positions.numel() == 0:
        raise ValueError(f"model.inpaint.region=agents: no agent box of clip '{clip.clip_id}' is visible; "
                         "use model.inpaint.region=box")
    tokens = torch.zeros(v * (h // patch) * (w // patch), dtype=torch.bool)
    tokens[positions] = True
    cells = tokens.view(v, h // patch, w // patch).repeat_interleave(patch, 1).repeat_interleave(patch, 2)
    return cells[None, :, None].expand(1, v, t, h, w).clone()
