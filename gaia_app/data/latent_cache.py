"""Latent caches: GAIA-2 video-tokenizer latents of a multi-camera dataset, encoded once, with every condition.

Legend: v cameras, T frames, t = T / τ latent steps, C latent channels, h w latent grid.

One folder per clip, `<root>/<clip_id>/`:
    conditions.json   fps, τ, frame count, image size, cameras (name, intrinsics, extrinsics at the
                      encoded size), metadata, per-frame text, agents and frame metadata (null where absent)
    timestamps.npy    (T,) float64 seconds of each encoded frame
    actions.npy       (T, 2) float32 speed (m/s) and curvature (1/m) per frame (absent without labels)
    logvar.npy        (v, t, C, h, w) float16 posterior log-variance
    mean.npy          (v, t, C, h, w) float16 posterior mean — written last: its presence marks a finished clip
Every file is written atomically, so a crashed run leaves whole files only, and rerunning the command
skips the finished clips (resumable). Conditions stay per frame, so the world model can aggregate
them per latent step as it likes (GAIA-2 conditions on actions per step and timestamps).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gaia_app.data.clip import AgentBoxes, CameraSpec, ClipError
from gaia_app.data.names import inside
from gaia_app.utils.run_dir import atomic_save_npy, atomic_write_text

DONE_MARKER = "mean.npy"


@dataclass
class LatentClip:
    """One encoded clip. mean, logvar: (v, t, C, h, w) float; timestamps: (T,); actions: (T, 2) or None;
    cameras: v CameraSpecs at the encoded size or None; text / agents / frame_meta (traffic light, …): per
    frame or None; meta: clip-level metadata dict."""

    clip_id: str
    mean: np.ndarray
    logvar: np.ndarray
    temporal_downsampling: int
    fps: float
    image_size: tuple[int, int]
    timestamps: np.ndarray
    cameras: list[CameraSpec] | None
    meta: dict[str, Any]
    actions: np.ndarray | None = None
    text: list[str | None] | None = None
    agents: list[AgentBoxes] | None = None
    frame_meta: list[dict[str, Any]] | None = None

    def __post_init__(self) -> None:
        v, t = self.mean.shape[:2]
        frames = t * self.temporal_downsampling
        if self.mean.ndim != 5 or self.logvar.shape != self.mean.shape:
            raise ClipError(f"latent clip '{self.clip_id}': mean {self.mean.shape} and logvar {self.logvar.shape} "
                            "must both be (v, t, C, h, w)")
        expected = {"timestamps": (frames,), "actions": (frames, 2)}
        for name, shape in expected.items():
            value = getattr(self, name)
            if value is not None and value.shape != shape:
                raise ClipError(f"latent clip '{self.clip_id}': {name} {value.shape}, expected {shape} "
                                f"({t} latent steps × τ={self.temporal_downsampling})")
        for name in ("text", "agents", "frame_meta"):
            value = getattr(self, name)
            if value is not None and len(value) != frames:
                raise ClipError(f"latent clip '{self.clip_id}': {len(value)} {name} entries, expected {frames}")
        if self.cameras is not None and len(self.cameras) != v:
            raise ClipError(f"latent clip '{self.clip_id}': {len(self.cameras)} cameras for {v} latent views")


def clip_done(root: str | Path, clip_id: str) -> bool:
    """True when clip `clip_id` is fully written (its mean file, written last, exists)."""
    return inside(root, clip_id, DONE_MARKER).is_file()


def write_latent_clip(root: str | Path, clip: LatentClip) -> Path:
    """Write a clip's folder, every file atomically, the mean last; returns the folder."""
    folder = inside(root, clip.clip_id)
    conditions = {
        "fps": clip.fps,
        "temporal_downsampling": clip.temporal_downsampling,
        "frames": len(clip.timestamps),
        "image_size": list(clip.image_size),
        "cameras": None if clip.cameras is None else [camera.to_json() for camera in clip.cameras],
        "meta": clip.meta,
        "text": clip.text,
        "agents": None if clip.agents is None else [a.to_json() for a in clip.agents],
        "frame_meta": clip.frame_meta,
    }
    atomic_write_text(folder / "conditions.json", json.dumps(conditions))
    atomic_save_npy(folder / "timestamps.npy", np.asarray(clip.timestamps, np.float64))
    if clip.actions is not None:
        atomic_save_npy(folder / "actions.npy", np.asarray(clip.actions, np.float32))
    atomic_save_npy(folder / "logvar.npy", np.asarray(clip.logvar, np.float16))
    atomic_save_npy(folder / DONE_MARKER, np.asarray(clip.mean, np.float16))
    return folder


def read_latent_clip(folder: str | Path) -> LatentClip:
    """Load a clip folder written by `write_latent_clip`; errors name the file and what was expected."""
    folder = Path(folder)
    if not (folder / DONE_MARKER).is_file():
        raise ClipError(f"latent clip '{folder}': no {DONE_MARKER} (unfinished or not a latent cache folder)")
    conditions_path = folder / "conditions.json"
    try:
        conditions = json.loads(conditions_path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ClipError(f"{conditions_path}: unreadable conditions ({err})") from err
    missing = {"fps", "temporal_downsampling", "image_size", "cameras", "meta"} - set(conditions)
    if missing:
        raise ClipError(f"{conditions_path}: missing fields {sorted(missing)}")
    actions_path = folder / "actions.npy"
    agents = conditions.get("agents")
    return LatentClip(
        clip_id=folder.name,
        mean=np.load(folder / DONE_MARKER).astype(np.float32),
        logvar=np.load(folder / "logvar.npy").astype(np.float32),
        temporal_downsampling=int(conditions["temporal_downsampling"]),
        fps=float(conditions["fps"]),
        image_size=tuple(conditions["image_size"]),
        timestamps=np.load(folder / "timestamps.npy"),
        cameras=None if conditions["cameras"] is None else [CameraSpec.from_json(c) for c in conditions["cameras"]],
        meta=conditions["meta"],
        actions=np.load(actions_path) if actions_path.is_file() else None,
        text=conditions.get("text"),
        frame_meta=conditions.get("frame_meta"),
        agents=None if agents is None else [AgentBoxes.from_json(a, f"{conditions_path}: agents[{i}]")
                                            for i, a in enumerate(agents)],
    )


def find_latent_clips(root: str | Path) -> list[Path]:
    """The finished clip folders under `root`, sorted; an error when there are none."""
    root = Path(root)
    folders = sorted(p.parent for p in root.glob(f"*/{DONE_MARKER}"))
    if not folders:
        raise ClipError(f"latent cache '{root}': no finished clip folders (*/{DONE_MARKER}); "
                        "make one with `python generate.py mode=encode ckpt=<GAIA-2 tokenizer checkpoint>`")
    return folders
