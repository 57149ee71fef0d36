"""How far a commanded contrast moves the picture: the image displacement that separates the two futures of each
contrast pair of the GAIA-2 action table (accelerate vs brake, left vs right), from the rig's geometry alone (issue
50, "diagnose before you scale").

Legend: N scenes, v cameras, H W pixels per camera, g generated frames.

The action table scores how much of a commanded contrast a world model's futures show. What it asks of the net is to
draw the static scene where the commanded motion puts it. For each scene of the table (the same worlds, contexts and
presets, protocols/controllability.commanded_actions) and each pair (high, low), the ego's pose after each generated
frame is integrated from the commanded actions (the twin probe's convention: frame i has moved by the actions of
frames < i), every pixel's ray meets the ground (or lies FAR away, models/gaia2/ego_flow.py), and the point is
projected after each pose:

    Δ_i(p) = |uv_high,i(p) − uv_low,i(p)|   pixels, generated frame i, pixel p of every camera

Reported per contrast, with 95 % intervals over scenes: the median of Δ over pixels at the last generated frame and
its mean over the generated frames (medians: a ground point near the camera moves by the width of the image), and
the share of pixels that the last frame moves by at least one latent cell and one world-model token. A static-ground
reading: agents and buildings stand above the ground, so nearby ones move more, distant ones about as the ground
behind them.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import numpy as np
import torch

from gaia_app.data.synthetic.generate import SyntheticSample
from gaia_app.eval.controllability import contrast_pairs, probe_clips
from gaia_app.eval.intervals import mean_interval
from gaia_app.models.gaia2.ego_flow import pose_flow
from gaia_app.protocols.controllability import CONTRASTS, commanded_actions


def ego_poses(actions: np.ndarray, first: int, rate: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The ego's move (g, 3) m and yaw (g,) rad at each generated frame first … f − 1, relative to the last context
    frame, from (f, 2) (speed m/s, curvature 1/m) actions; frame i has moved by the arcs of frames first − 1 … i − 1."""
    x = y = heading = 0.0
    moves, yaws = [], []
    for speed, curvature in actions[first - 1:-1]:
        distance = float(speed) / rate
        turn = distance * float(curvature)
        x += distance * np.cos(heading + turn / 2)
        y += distance * np.sin(heading + turn / 2)
        heading += turn
        moves.append([x, y, 0.0])
        yaws.append(heading)
    return torch.tensor(moves, dtype=torch.float64), torch.tensor(yaws, dtype=torch.float64)


def scene_positions(sample: SyntheticSample, actions: np.ndarray, first: int, rate: float) -> torch.Tensor:
    """(g, v, H, W, 2) pixels each pixel's static ground point has moved by at each generated frame, unclipped."""
    cameras = sample.clip.cameras
    if not cameras:
        raise ValueError(f"clip '{sample.clip.clip_id}': the displacement needs its cameras' intrinsics and extrinsics")
    height, width = cameras[0].height, cameras[0].width
    intrinsics = torch.tensor(np.stack([c.intrinsics for c in cameras]))[None]
    extrinsics = torch.tensor(np.stack([c.extrinsics for c in cameras]))[None]
    move, yaw = ego_poses(actions, first, rate)
    flow = pose_flow(move[None], yaw[None], intrinsics, extrinsics, (height, width), (height, width), limit=None)
    return flow[0]


def displacement_table(samples: list[SyntheticSample], commands: list[tuple[str, str]], first: int, frames: int,
                       cell_px: float, token_px: float) -> dict[str, Any]:
    """{summary: {contrast: {last, horizon, share_cell, share_token: interval over scenes}}, per_scene, the
    settings}: the module docstring's readings.

    samples: the action table's scenes (protocols/gaia2_evaluate.rig_samples), each at least `frames` frames;
    first: context frames; cell_px / token_px: pixels per latent cell and per world-model token."""
    if not samples:
        raise ValueError("displacement_table needs at least one scene")
    if not 0 < first < frames:
        raise ValueError(f"context frames {first}: expected 0 < first < frames = {frames}")
    rate = float(samples[0].clip.fps)
    contexts = probe_clips([s.clip for s in samples], rate, frames)
    commanded = commanded_actions(contexts, first, frames - first, rate, commands)  # (C·N, f, 2) command-major
    pairs = contrast_pairs(commanded[:, first:-1].unflatten(0, (len(commands), -1)))
    n = len(samples)
    per_scene: dict[str, dict[str, list[float]]] = {m: {"last": [], "horizon": [], "share_cell": [], "share_token": []}
                                                    for m in CONTRASTS}
    for metric, (high, low) in zip(CONTRASTS, pairs):
        for i, sample in enumerate(samples):
            moved = [scene_positions(sample, commanded[c * n + i].double().numpy(), first, rate) for c in (high, low)]
            gap = (moved[0] - moved[1]).norm(dim=-1).flatten(1)  # (g, v·H·W) pixels
            rows = per_scene[metric]
            rows["last"].append(float(gap[-1].median()))
            rows["horizon"].append(float(gap.median(dim=1).values.mean()))
            rows["share_cell"].append(float((gap[-1] >= cell_px).double().mean()))
            rows["share_token"].append(float((gap[-1] >= token_px).double().mean()))
    summary = {metric: {key: asdict(mean_interval(values)) for key, values in rows.items()}
               for metric, rows in per_scene.items()}
    return {"scenes": n, "commands": [list(c) for c in commands], "context_frames": first,
            "generated_frames": frames - first, "rate": rate, "cell_px": cell_px, "token_px": token_px,
            "context_speed": asdict(mean_interval(contexts.actions[:, first - 1, 0].tolist())),
            "contrasts": {m: ["/".join(commands[h]), "/".join(commands[lo])] for m, (h, lo) in zip(CONTRASTS, pairs)},
            "summary": summary, "per_scene": per_scene}


def markdown(table: dict[str, Any]) -> str:
    """The table as Markdown: one row per contrast."""
    def cell(d: dict[str, float], digits: int = 2) -> str:
        return f"{d['mean']:.{digits}f} [{d['low']:.{digits}f}, {d['high']:.{digits}f}]"

    lines = [f"{table['scenes']} scenes, {table['generated_frames']} generated frames at {table['rate']:g} Hz, "
             f"context speed {cell(table['context_speed'])} m/s; a latent cell {table['cell_px']:g} px, a token "
             f"{table['token_px']:g} px", "",
             "| contrast | pair | median displacement, last frame (px) | over the horizon (px) "
             "| pixels moved ≥ a cell | ≥ a token |", "|---|---|---:|---:|---:|---:|"]
    for metric, rows in table["summary"].items():
        lines.append(f"| {metric} | {' − '.join(table['contrasts'][metric])} | {cell(rows['last'])} | "
                     f"{cell(rows['horizon'])} | {cell(rows['share_cell'])} | {cell(rows['share_token'])} |")
    return "\n".join(lines) + "\n"
