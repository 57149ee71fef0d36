"""Clip transforms: temporal resampling by timestamps, resizing with intrinsics kept true, pixel scaling.

Legend (einops): v cameras, t frames, c channels (3), h w pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
import torch

from gaia_app.data.clip import CameraSpec, Clip, ClipError

RATE_TOLERANCE = 0.02
"""Relative slack when comparing a target rate with a source rate measured from jittery timestamps."""


def source_rate(timestamps: np.ndarray) -> float:
    """Frame rate (Hz) from the median frame interval of timestamps (t,) seconds; robust to a dropped frame."""
    t = np.asarray(timestamps, dtype=np.float64)
    if len(t) < 2:
        raise ClipError(f"cannot measure a frame rate from {len(t)} timestamp(s)")
    return float(1.0 / np.median(np.diff(t)))


def resample_indices(timestamps: np.ndarray, target_hz: float) -> np.ndarray:
    """Indices of the frames nearest to ticks at `target_hz`, starting at the first timestamp.

    timestamps: (t,) seconds, increasing. Ticks run t0, t0 + 1/target_hz, ... up to the last
    timestamp, so 25 Hz → 6.25 Hz picks every 4th frame and 30, 20 or 10 Hz sources get the
    nearest frame to each tick. A frame is never repeated. Raises ClipError naming both rates
    when target_hz exceeds the source rate (beyond RATE_TOLERANCE): upsampling would invent frames.
    Returns (k,) int64.
    """
    t = np.asarray(timestamps, dtype=np.float64)
    if target_hz <= 0:
        raise ClipError(f"target rate must be positive, got {target_hz} Hz")
    if len(t) == 1:
        return np.zeros(1, dtype=np.int64)
    src_hz = source_rate(t)
    if target_hz > src_hz * (1 + RATE_TOLERANCE):
        raise ClipError(f"cannot resample to {target_hz:g} Hz: the source runs at only {src_hz:.4g} Hz")
    period = 1.0 / target_hz
    # The small epsilon keeps a tick that lands exactly on the last timestamp despite rounding.
    ticks = t[0] + period * np.arange(int(np.floor((t[-1] - t[0]) / period + 1e-6)) + 1)
    right = np.clip(np.searchsorted(t, ticks), 1, len(t) - 1)
    left = right - 1
    nearest = np.where(ticks - t[left] <= t[right] - ticks, left, right)
    return np.unique(nearest)


def resample_clip(clip: Clip, target_hz: float) -> Clip:
    """The clip at `target_hz` by timestamps (see `resample_indices`); labels follow their frames."""
    return clip.select_frames(resample_indices(clip.timestamps, target_hz))


def window_indices(num_frames: int, window: int, stride: int) -> np.ndarray:
    """Frame indices of every full window of `window` frames, starts `stride` apart.

    Returns (n, window) int64; n = 0 (shape (0, window)) when the clip is shorter than a window.
    """
    if window < 1 or stride < 1:
        raise ValueError(f"window ({window}) and stride ({stride}) must be >= 1")
    starts = np.arange(0, max(num_frames - window + 1, 0), stride, dtype=np.int64)
    return starts[:, None] + np.arange(window, dtype=np.int64)[None, :]


@dataclass(frozen=True)
class ResizePlan:
    """How an image of (src_width, src_height) becomes (width, height).

    Scale to (scaled_width, scaled_height), then crop the window starting at pixel (x0, y0).
    """

    scaled_width: int
    scaled_height: int
    x0: int
    y0: int
    width: int
    height: int


def plan_resize(src_width: int, src_height: int, width: int, height: int, mode: str = "crop") -> ResizePlan:
    """Plan a resize to (width, height) pixels.

    mode "crop": scale uniformly until the image covers the target, then centre-crop (aspect
    preserved, borders lost); "stretch": scale each axis independently (aspect changes).
    """
    if width < 1 or height < 1:
        raise ValueError(f"target size must be positive, got {width}x{height}")
    if mode == "stretch":
        return ResizePlan(width, height, 0, 0, width, height)
    if mode != "crop":
        raise ValueError(f"resize mode must be 'crop' or 'stretch', got '{mode}'")
    scale = max(width / src_width, height / src_height)
    scaled_w = max(width, round(src_width * scale))
    scaled_h = max(height, round(src_height * scale))
    return ResizePlan(scaled_w, scaled_h, (scaled_w - width) // 2, (scaled_h - height) // 2, width, height)


def resize_image(image: np.ndarray, plan: ResizePlan) -> np.ndarray:
    """Apply a ResizePlan to one (h, w, c) uint8 image; returns (plan.height, plan.width, c)."""
    h, w = image.shape[:2]
    # INTER_AREA averages source pixels when shrinking (no aliasing); it is slower, so only there.
    shrinking = plan.scaled_width < w or plan.scaled_height < h
    interp = cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR
    scaled = cv2.resize(image, (plan.scaled_width, plan.scaled_height), interpolation=interp)
    return scaled[plan.y0 : plan.y0 + plan.height, plan.x0 : plan.x0 + plan.width]


def resize_camera(camera: CameraSpec, plan: ResizePlan) -> CameraSpec:
    """The camera seen through a ResizePlan: intrinsics scaled, then the principal point shifted by the crop."""
    scaled = camera.resized(plan.scaled_width, plan.scaled_height)
    k = scaled.intrinsics.copy()
    k[0, 2] -= plan.x0
    k[1, 2] -= plan.y0
    return replace(scaled, intrinsics=k, width=plan.width, height=plan.height)


def resize_clip(clip: Clip, height: int, width: int, mode: str = "crop") -> Clip:
    """Every view resized to (height, width) pixels (see `plan_resize` for modes); intrinsics follow.

    frames: (v, t, 3, h, w) uint8 → (v, t, 3, height, width) uint8.
    """
    v, t, c, h, w = clip.frames.shape
    plan = plan_resize(w, h, width, height, mode)
    out = np.empty((v, t, height, width, c), dtype=np.uint8)
    hwc = clip.frames.transpose(0, 1, 3, 4, 2)  # (v, t, h, w, c) view: cv2 wants channels last
    for i in range(v):
        for j in range(t):
            out[i, j] = resize_image(hwc[i, j], plan)
    cameras = None if clip.cameras is None else [resize_camera(cam, plan) for cam in clip.cameras]
    return replace(clip, frames=np.ascontiguousarray(out.transpose(0, 1, 4, 2, 3)), cameras=cameras)


def to_float(frames: np.ndarray | torch.Tensor) -> torch.Tensor:
    """uint8 pixels [0, 255] → float32 tensor in [-1, 1], any shape."""
    x = torch.as_tensor(frames)
    if x.dtype != torch.uint8:
        raise TypeError(f"to_float expects uint8 pixels, got {x.dtype}")
    return x.to(torch.float32) / 127.5 - 1.0


def to_uint8(x: torch.Tensor) -> torch.Tensor:
    """Float pixels in [-1, 1] → uint8 [0, 255] (rounded, values outside the range clamped); inverts `to_float`."""
    return ((x.detach().to(torch.float32) + 1.0) * 127.5).round().clamp(0, 255).to(torch.uint8)
