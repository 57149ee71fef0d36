"""Torch datasets that turn clip sources into model-ready samples.

A clip source is any indexable collection of `Clip`s (`SyntheticClipDataset`, `ClipFolderDataset`).
Samples are dicts of tensors; frames become float in [-1, 1].
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np
import torch
from torch.utils.data import Dataset

from gaia_app.data.agent_regions import agent_box_masks
from gaia_app.data.clip import Clip, ClipError
from gaia_app.data.transforms import resample_clip, resize_clip, to_float


class ClipSource(Protocol):
    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> Clip: ...


def fit_to_resolution(clip: Clip, height: int, width: int, mode: str) -> Clip:
    """Resize (and centre-crop in 'crop' mode) unless the frames already have the size."""
    if clip.frames.shape[-2:] == (height, width):
        return clip
    return resize_clip(clip, height, width, mode=mode)


class FramesDataset(Dataset):
    """Item i: `frames_per_clip` random frames of clip i, every camera → {"image": (k·v, 3, H, W)}, and with
    `agent_boxes` {"agent_box": (k·v, H, W) bool}, the clip's agent boxes projected into each image
    (gaia_app/data/agent_regions.py).

    Used for image tokenizers, which see single frames (GAIA-1 §2.2).
    """

    def __init__(self, source: ClipSource, height: int, width: int, frames_per_clip: int = 1, resize_mode: str = "crop",
                 agent_boxes: bool = False):
        self.source, self.height, self.width = source, height, width
        self.frames_per_clip, self.resize_mode, self.agent_boxes = frames_per_clip, resize_mode, agent_boxes

    def __len__(self) -> int:
        return len(self.source)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        clip = self.source[index]
        k = min(self.frames_per_clip, clip.num_frames)
        # random per call: Lightning seeds workers, so runs stay reproducible
        pick = torch.randperm(clip.num_frames)[:k].sort().values.numpy()
        clip = fit_to_resolution(clip.select_frames(pick), self.height, self.width, self.resize_mode)
        frames = torch.from_numpy(clip.frames).flatten(0, 1)  # (v t) c h w
        if self.agent_boxes:
            return {"image": to_float(frames), "agent_box": torch.from_numpy(agent_box_masks(clip)).flatten(0, 1)}
        return {"image": to_float(frames)}


class ClipsDataset(Dataset):
    """Item i: a window of `clip_len` steps of clip i resampled to `fps`, with all its conditions.

    Returns {"video": (v, t, 3, H, W), "timestamps": (t,), "actions"?: (t, 2), "text"?: list[str],
    "agents"?: list[AgentBoxes], "intrinsics"?/"extrinsics"?: (v, 3, 3)/(v, 4, 4), "meta": dict,
    "clip_id": str}. Absent labels stay absent.
    """

    def __init__(self, source: ClipSource, height: int, width: int, clip_len: int, fps: float | None = None,
                 cameras: Sequence[str] | None = None, resize_mode: str = "crop", random_window: bool = True):
        self.source, self.height, self.width = source, height, width
        self.clip_len, self.fps, self.cameras = clip_len, fps, cameras
        self.resize_mode, self.random_window = resize_mode, random_window

    def __len__(self) -> int:
        return len(self.source)

    def window(self, clip: Clip) -> Clip:
        """Resample by timestamps, then cut `clip_len` consecutive steps."""
        if self.fps is not None:
            clip = resample_clip(clip, self.fps)
        if clip.num_frames < self.clip_len:
            raise ClipError(f"clip '{clip.clip_id}': {clip.num_frames} frames at {self.fps} Hz, "
                            f"need clip_len={self.clip_len}")
        last = clip.num_frames - self.clip_len
        start = int(torch.randint(0, last + 1, ()).item()) if self.random_window else 0
        return clip.select_frames(np.arange(start, start + self.clip_len))

    def __getitem__(self, index: int) -> dict[str, Any]:
        clip = self.source[index]
        if self.cameras is not None:
            clip = clip.select_views(list(self.cameras))
        clip = fit_to_resolution(self.window(clip), self.height, self.width, self.resize_mode)
        return clip_to_sample(clip)


def clip_to_sample(clip: Clip) -> dict[str, Any]:
    """Tensors for the fields a clip has; absent labels are left out, never zero-filled."""
    sample: dict[str, Any] = {
        "clip_id": clip.clip_id,
        "video": to_float(torch.from_numpy(clip.frames)),
        "timestamps": torch.from_numpy(clip.timestamps - clip.timestamps[0]).float(),
        "meta": dict(clip.meta),
    }
    if clip.actions is not None:
        sample["actions"] = torch.from_numpy(clip.actions)
    if clip.text is not None:
        sample["text"] = [t or "" for t in clip.text]
    if clip.agents is not None:
        sample["agents"] = clip.agents
    if clip.cameras is not None:
        sample["intrinsics"] = torch.tensor(np.stack([c.intrinsics for c in clip.cameras]), dtype=torch.float32)
        sample["extrinsics"] = torch.tensor(np.stack([c.extrinsics for c in clip.cameras]), dtype=torch.float32)
    return sample
