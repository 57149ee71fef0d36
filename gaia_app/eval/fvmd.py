"""Fréchet Video Motion Distance (FVMD; Liu et al. 2024, used by GAIA-2 §6 for temporal consistency).

Legend: b clips, t frames, k keypoints, H × W frames in [-1, 1].

FVMD compares how things move rather than how frames look: keypoints are tracked through each clip, their
velocities and accelerations summarised per clip as histograms, and the sets of summaries of real and of
generated clips compared with the Fréchet distance. The FVMD paper tracks with PIPs++; here tracks come from
OpenCV (Shi–Tomasi corners + pyramidal Lucas–Kanade), which needs no weights and runs on a CPU. Values are
therefore comparable between runs of this project, not with numbers published with PIPs++.

Per clip feature (`motion_features`, 2 × (8 + 6) = 28 numbers): for velocity and for acceleration (pixels per
frame, per frame², at the clip's own frame rate) an 8-bin orientation histogram weighted by magnitude and a
6-bin histogram of magnitudes, both averaged over valid track steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from gaia_app.eval.frechet import FrechetStatistics, frechet_distance

ORIENTATION_BINS = 8
MAGNITUDE_EDGES = (0.25, 0.5, 1.0, 2.0, 4.0)  # px per frame (or frame²); 6 bins with the open ends
FEATURE_DIM = 2 * (ORIENTATION_BINS + len(MAGNITUDE_EDGES) + 1)


@dataclass(frozen=True)
class Tracks:
    """points (t, k, 2) x, y in pixels; valid (t, k) bool: the point was tracked into frame i."""

    points: np.ndarray
    valid: np.ndarray


def to_gray_uint8(clip: torch.Tensor) -> np.ndarray:
    """(t, 3, H, W) in [-1, 1] → (t, H, W) uint8 luma."""
    if clip.ndim != 4 or clip.shape[1] != 3:
        raise ValueError(f"FVMD expects clips of shape (t, 3, H, W) in [-1, 1], got {tuple(clip.shape)}")
    rgb = ((clip.detach().float().clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
    return np.stack([cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY) for frame in rgb])


def _start_points(first: np.ndarray, max_points: int) -> np.ndarray:
    """Shi–Tomasi corners of the first frame; a regular grid where the frame has too few (flat images)."""
    corners = cv2.goodFeaturesToTrack(first, maxCorners=max_points, qualityLevel=0.01, minDistance=3)
    if corners is not None and len(corners) >= max_points // 4:
        return corners.reshape(-1, 2).astype(np.float32)
    h, w = first.shape
    side = max(int(np.sqrt(max_points * w / h)), 2)
    xs, ys = np.meshgrid(np.linspace(2, w - 3, side), np.linspace(2, h - 3, max(max_points // side, 2)))
    return np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float32)


def track(gray: np.ndarray, max_points: int = 64) -> Tracks:
    """Track corners of frame 0 through (t, H, W) uint8 frames with pyramidal Lucas–Kanade; a lost point stays lost."""
    points = _start_points(gray[0], max_points)
    out = np.zeros((len(gray), len(points), 2), np.float32)
    valid = np.zeros((len(gray), len(points)), bool)
    out[0], valid[0] = points, True
    for i in range(1, len(gray)):
        moved, status, _ = cv2.calcOpticalFlowPyrLK(gray[i - 1], gray[i], out[i - 1].reshape(-1, 1, 2), None,
                                                    winSize=(9, 9), maxLevel=2)
        out[i] = moved.reshape(-1, 2)
        valid[i] = valid[i - 1] & (status.ravel() == 1)
    return Tracks(out, valid)


def _histograms(vectors: np.ndarray) -> np.ndarray:
    """(m, 2) motion vectors → magnitude-weighted orientation histogram (8) ++ magnitude histogram (6), per vector."""
    size = ORIENTATION_BINS + len(MAGNITUDE_EDGES) + 1
    if len(vectors) == 0:
        return np.zeros(size)
    magnitude = np.linalg.norm(vectors, axis=1)
    angle = np.arctan2(vectors[:, 1], vectors[:, 0]) % (2 * np.pi)
    orientation = np.bincount((angle / (2 * np.pi) * ORIENTATION_BINS).astype(int) % ORIENTATION_BINS,
                              weights=magnitude, minlength=ORIENTATION_BINS)
    magnitudes = np.bincount(np.digitize(magnitude, MAGNITUDE_EDGES), minlength=len(MAGNITUDE_EDGES) + 1)
    return np.concatenate([orientation, magnitudes]) / len(vectors)


def motion_features(tracks: Tracks) -> np.ndarray:
    """(FEATURE_DIM,) velocity and acceleration histograms of one clip's tracks (module docstring); needs t ≥ 3."""
    if len(tracks.points) < 3:
        raise ValueError(f"FVMD needs clips of at least 3 frames (velocity and acceleration), got {len(tracks.points)}")
    velocity = np.diff(tracks.points, axis=0)
    velocity_valid = tracks.valid[1:]
    acceleration = np.diff(velocity, axis=0)
    acceleration_valid = tracks.valid[2:]
    return np.concatenate([_histograms(velocity[velocity_valid]), _histograms(acceleration[acceleration_valid])])


class FVMD:
    """Streaming FVMD: add batches of real and generated clips (b, t, 3, H, W) in [-1, 1], then `compute()`."""

    def __init__(self, max_points: int = 64):
        self.max_points = max_points
        self.real = FrechetStatistics(FEATURE_DIM)
        self.generated = FrechetStatistics(FEATURE_DIM)

    def features(self, clips: torch.Tensor) -> torch.Tensor:
        """(b, t, 3, H, W) → (b, FEATURE_DIM) float64 motion features."""
        if clips.ndim != 5:
            raise ValueError(f"FVMD expects a batch of clips (b, t, 3, H, W), got {tuple(clips.shape)}")
        rows = [motion_features(track(to_gray_uint8(clip), self.max_points)) for clip in clips]
        return torch.from_numpy(np.stack(rows))

    def update(self, clips: torch.Tensor, real: bool) -> FVMD:
        (self.real if real else self.generated).update(self.features(clips))
        return self

    def compute(self) -> float:
        """The Fréchet distance between the real and generated motion features (moments all-reduced over ranks)."""
        return frechet_distance(self.real.all_reduce(), self.generated.all_reduce())
