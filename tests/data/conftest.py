"""Fixtures for the data I/O tests: a small labelled two-camera clip made in the test, and the shared real data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gaia_app.data.clip import AgentBoxes, CameraSpec, Clip

SHARED_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


@pytest.fixture(scope="session")
def real_dir() -> Path:
    """`../shared/data/real` beside the repository (session-scoped, so module fixtures can import from it);
    tests using it skip when it is absent."""
    real = SHARED_DATA / "real"
    if not real.is_dir():
        pytest.skip(f"real data folder {real} is absent (see shared/data/MANIFEST.md)")
    return real


def smooth_frames(t: int, h: int, w: int, seed: int) -> np.ndarray:
    """(t, h, w, 3) uint8: colour gradients with a moving square; smooth, so H.264 keeps it within a few levels."""
    y, x = np.mgrid[0:h, 0:w]
    base = np.stack([x * 200 / w, y * 200 / h, np.full((h, w), 60.0 + 40 * seed)], axis=-1)
    frames = np.repeat(base[None], t, axis=0)
    for i in range(t):
        frames[i, h // 4 : h // 4 + 12, 4 + 3 * i : 16 + 3 * i] = (230, 40, 40)
    return frames.astype(np.uint8)


def camera(name: str, w: int, h: int, yaw: float) -> CameraSpec:
    """A pinhole camera looking along ego yaw (radians), mounted 1.5 m up; OpenCV camera axes."""
    k = [[w * 0.8, 0, w / 2], [0, w * 0.8, h / 2], [0, 0, 1]]
    c, s = np.cos(yaw), np.sin(yaw)
    forward, left, up = np.array([c, s, 0.0]), np.array([-s, c, 0.0]), np.array([0.0, 0.0, 1.0])
    ext = np.eye(4)
    ext[:3, :3] = np.stack([-left, -up, forward], axis=1)  # camera x right, y down, z forward
    ext[:3, 3] = (0.5, 0.0, 1.5)
    return CameraSpec(name, k, ext, w, h)


def make_clip(clip_id: str = "clip_a", t: int = 8, h: int = 48, w: int = 64, fps: float = 10.0) -> Clip:
    """A two-camera clip with actions, text (one frame without), agents (one frame empty), frame meta."""
    frames = np.stack([smooth_frames(t, h, w, seed=v) for v in range(2)]).transpose(0, 1, 4, 2, 3)
    rng = np.random.default_rng(0)
    agents = [
        AgentBoxes(rng.normal(size=(i % 3, 3)), rng.uniform(1, 5, (i % 3, 3)), rng.uniform(-3, 3, i % 3),
                   np.arange(i % 3) % 5, np.arange(i % 3) + 7)
        for i in range(t)
    ]
    return Clip(
        clip_id=clip_id,
        frames=frames,
        timestamps=100.0 + np.arange(t) / fps,
        actions=np.stack([np.linspace(3, 5, t), np.linspace(-0.01, 0.02, t)], axis=1),
        text=[None] + [f"step {i}" for i in range(1, t)],
        agents=agents,
        cameras=[camera("front", w, h, 0.0), camera("rear_left", w, h, 2.5)],
        meta={"weather": "clear", "time_of_day": "day"},
        frame_meta=[{"traffic_light": "red" if i < 3 else "green"} for i in range(t)],
    )


@pytest.fixture
def clip() -> Clip:
    return make_clip()


@pytest.fixture
def clip_factory():
    """`make_clip(clip_id, t, h, w, fps)` for tests that need several or differently sized clips."""
    return make_clip


@pytest.fixture
def frames_factory():
    """`smooth_frames(t, h, w, seed)` -> (t, h, w, 3) uint8 that H.264 reproduces within a few levels."""
    return smooth_frames
