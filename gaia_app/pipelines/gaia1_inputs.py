"""Inputs of GAIA-1 rollouts: context clips, commanded actions and the conditioning of each mode (GAIA-1 §7).

Legend: t0 context frames, f generated frames, both at the world model's rate; H × W images.

Modes (GAIA-1 Fig. 1, §7): `video` continues a context clip with no condition; `action` adds commanded
speed and curvature; `text` a prompt; `text_action` both; `text_only` generates from a prompt with no
video at all; `unconditional` from nothing. Context steps keep the clip's own actions and captions (what
the world model saw in training); the future steps get the commanded ones.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gaia_app.data.clip import Clip, ClipError
from gaia_app.data.datasets import fit_to_resolution
from gaia_app.data.transforms import resample_clip, to_float
from gaia_app.pipelines.gaia1 import Conditioning

# mode → (needs a context clip, uses a prompt, uses actions)
MODES: dict[str, tuple[bool, bool, bool]] = {
    "video": (True, False, False),
    "action": (True, False, True),
    "text": (True, True, False),
    "text_action": (True, True, True),
    "text_only": (False, True, False),
    "unconditional": (False, False, False),
}

# curvature presets in 1/m, positive = left (gaia_app.data.actions): 50 m and 20 m turning radii
CURVATURE_PRESETS = {"straight": 0.0, "left": 0.02, "right": -0.02, "strong_left": 0.05, "strong_right": -0.05}
# speed presets: m/s² applied from the context's last speed (keep: constant)
SPEED_PRESETS = {"keep": 0.0, "accelerate": 2.0, "brake": -4.0}
MAX_SPEED = 30.0
DEFAULT_SPEED = 8.0  # m/s when there is no context speed to start from
# what a commanded number may be: 0–70 m/s (252 km/h), |curvature| ≤ 0.5 1/m (a 2 m turning radius)
COMMAND_RANGES = {"speed": (0.0, 70.0), "curvature": (-0.5, 0.5)}


def future_frames(seconds: Any, rate: float, at_least: int = 1) -> int:
    """Generated steps for `seconds` of future at `rate` Hz (at least `at_least`); a clear error for seconds that are
    not a positive, finite number."""
    try:
        value = float(seconds)
    except (TypeError, ValueError):
        value = math.nan
    if not math.isfinite(value) or value <= 0 or isinstance(seconds, bool):
        raise ValueError(f"seconds={seconds!r}: expected a positive number of seconds of future to generate")
    return max(at_least, math.ceil(value * rate))


@dataclass
class ContextClip:
    """frames (t, 3, H, W) in [-1, 1] at the world model's rate: the t0 context frames, then the clip's real
    continuation where it has one; actions (t, 2) or None; captions (t) or None; source: (T, 3, H, W) the same
    span at the clip's own rate (`source_fps`), for side-by-side videos; name and meta describe the clip."""

    frames: torch.Tensor
    actions: np.ndarray | None
    captions: list[str | None] | None
    source: torch.Tensor
    source_fps: float
    name: str
    meta: dict[str, Any]


def synthetic_clip(seed: int, index: int, height: int, width: int, seconds: float) -> Clip:
    """Clip `index` of the built-in synthetic world with `seed`, `seconds` long at 25 Hz, front camera."""
    from gaia_app.data.synthetic import SyntheticClipDataset

    frames = int(math.ceil(seconds * 25.0)) + 1
    return SyntheticClipDataset(num_clips=index + 1, seed=seed, height=height, width=width, clip_len=frames)[index]


def folder_clip(folder: str | Path, index: int) -> Clip:
    """Clip `index` (sorted) of a clip-folder root, or the clip folder itself if `folder` is one."""
    from gaia_app.data.clip_folder import ClipFolderDataset, read_clip

    folder = Path(folder)
    if (folder / "meta.json").is_file():
        return read_clip(folder)
    clips = ClipFolderDataset(folder)
    if not 0 <= index < len(clips):
        raise ClipError(f"context.index={index}: {folder} has {len(clips)} usable clips")
    return clips[index]


def prepare_context(clip: Clip, context_frames: int, total_frames: int, rate: float, height: int, width: int,
                    resize_mode: str = "crop") -> ContextClip:
    """A clip → its first `total_frames` at `rate` (at least `context_frames`, else a ClipError), first camera."""
    clip = fit_to_resolution(clip, height, width, resize_mode)
    resampled = resample_clip(clip, rate)
    have = resampled.frames.shape[1]
    if have < context_frames:
        raise ClipError(f"context clip '{clip.clip_id}' has {have} frames at {rate:g} Hz "
                        f"({clip.frames.shape[1]} at its own rate); the rollout needs {context_frames} context frames")
    keep = min(have, total_frames)
    resampled = resampled.select_frames(np.arange(keep))
    end = float(resampled.timestamps[-1])
    source_fps = 1.0 / float(np.median(np.diff(clip.timestamps))) if len(clip.timestamps) > 1 else rate
    span = clip.select_frames(np.flatnonzero(clip.timestamps <= end + 1e-6))
    return ContextClip(frames=to_float(torch.from_numpy(resampled.frames[0])), actions=resampled.actions,
                       captions=None if resampled.text is None else list(resampled.text),
                       source=to_float(torch.from_numpy(span.frames[0])), source_fps=source_fps,
                       name=clip.clip_id, meta=dict(clip.meta))


def command_series(value: Any, name: str, presets: dict[str, float], frames: int) -> np.ndarray | str:
    """A commanded series: a preset name (returned as is), one number (held) or f numbers (one per future step)."""
    if isinstance(value, str):
        if value not in presets:
            raise ValueError(f"{name}={value!r}: expected one of {sorted(presets)}, a number or a list of {frames}")
        return value
    try:
        values = np.atleast_1d(np.asarray(value, dtype=np.float64))
    except (TypeError, ValueError):
        raise ValueError(f"{name}={value!r}: expected one of {sorted(presets)}, "
                         f"a number or a list of {frames}") from None
    if values.ndim != 1 or len(values) not in (1, frames):
        raise ValueError(f"{name}: {len(values)} values for {frames} future steps; give one per step, one number, "
                         f"or a preset of {sorted(presets)}")
    low, high = COMMAND_RANGES[name]
    if not (np.isfinite(values).all() and (values >= low).all() and (values <= high).all()):
        raise ValueError(f"{name}={value!r}: every commanded value must be a finite number in [{low:g}, {high:g}] "
                         f"{'m/s' if name == 'speed' else '1/m'}")
    return np.broadcast_to(values, (frames,)).copy()


def future_actions(speed: Any, curvature: Any, frames: int, rate: float, start_speed: float) -> np.ndarray:
    """(f, 2) commanded (speed m/s, curvature 1/m) for the future steps; presets start from `start_speed`."""
    speed_cmd = command_series(speed if speed is not None else "keep", "speed", SPEED_PRESETS, frames)
    curv_cmd = command_series(curvature if curvature is not None else "straight", "curvature", CURVATURE_PRESETS,
                              frames)
    if isinstance(speed_cmd, str):
        elapsed = np.arange(1, frames + 1) / rate
        speed_cmd = np.clip(start_speed + SPEED_PRESETS[speed_cmd] * elapsed, 0.0, MAX_SPEED)
    if isinstance(curv_cmd, str):
        curv_cmd = np.full(frames, CURVATURE_PRESETS[curv_cmd])
    return np.stack([speed_cmd, curv_cmd], axis=1).astype(np.float32)


def build_conditioning(mode: str, context: ContextClip | None, context_frames: int, frames: int, rate: float,
                       prompt: str | None = None, negative_prompt: str | None = None, speed: Any = None,
                       curvature: Any = None) -> tuple[Conditioning, np.ndarray | None]:
    """The Conditioning of one rollout, and the commanded future actions (f, 2) (None when not commanded).

    Context steps keep the clip's own actions; a clip without any gets its first commanded action there
    (the action stream is one per rollout: the world model has no per-step "no action" token).
    """
    if mode not in MODES:
        raise ValueError(f"mode={mode}: expected one of {sorted(MODES)}")
    needs_context, uses_text, uses_actions = MODES[mode]
    if uses_text and not prompt:
        raise ValueError(f"mode={mode} needs a prompt (prompt='It is night. ...')")
    if not uses_text and prompt:
        raise ValueError(f"mode={mode} takes no prompt; use mode=text, text_action or text_only")
    if not uses_actions and (speed is not None or curvature is not None):
        raise ValueError(f"mode={mode} takes no speed/curvature; use mode=action or text_action")
    if uses_actions and speed is None and curvature is None:
        raise ValueError(f"mode={mode} needs speed= and/or curvature= (a preset, a number or one value per step)")
    if needs_context != (context is not None):
        raise ValueError(f"mode={mode} {'needs' if needs_context else 'takes no'} context clip")
    t0, steps = (context_frames if needs_context else 0), (context_frames if needs_context else 0) + frames
    captions = _captions(prompt, context, t0, frames) if uses_text else None
    negative = [negative_prompt] * steps if negative_prompt else None
    commanded, actions = None, None
    if uses_actions:
        past = None if context is None or context.actions is None else context.actions[:t0]
        start = float(past[-1, 0]) if past is not None and len(past) else DEFAULT_SPEED
        commanded = future_actions(speed, curvature, frames, rate, start)
        past = past if past is not None else np.tile(commanded[:1], (t0, 1))
        actions = torch.from_numpy(np.concatenate([past, commanded]))
    return Conditioning(captions, actions, negative), commanded


def _captions(prompt: str, context: ContextClip | None, t0: int, frames: int) -> list[str | None]:
    """The context's own captions (the prompt where it has none), then the prompt for every future step."""
    past = list(context.captions[:t0]) if context is not None and context.captions is not None else [prompt] * t0
    return past + [prompt] * frames


def context_for(mode: str, source: str, seed: int, index: int, folder: str | None, context_frames: int,
                frames: int, rate: float, height: int, width: int) -> ContextClip | None:
    """The context clip of a rollout (None for modes without one): `source` synthetic (by seed) or folder."""
    if mode not in MODES:
        raise ValueError(f"mode={mode}: expected one of {sorted(MODES)}")
    if not MODES[mode][0]:
        return None
    if context_frames < 1:
        raise ValueError(f"context.frames must be ≥ 1 for mode={mode}, got {context_frames}")
    total = context_frames + frames
    if source == "synthetic":
        clip = synthetic_clip(seed, index, height, width, (total - 1) / rate)
    elif source == "folder":
        if not folder:
            raise ValueError("context.source=folder needs context.folder=<clip folder or root of clip folders>")
        clip = folder_clip(folder, index)
    else:
        raise ValueError(f"context.source={source!r}: expected 'synthetic' or 'folder'")
    return prepare_context(clip, context_frames, total, rate, height, width)


def describe_actions(actions: Sequence[Sequence[float]] | None) -> list[list[float]] | None:
    """JSON-friendly actions."""
    return None if actions is None else [[round(float(v), 4) for v in row] for row in actions]
