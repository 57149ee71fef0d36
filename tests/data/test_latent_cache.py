"""Latent cache files (GAIA-2 latent world model input): round trip, done marker, clear errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gaia_app.data.clip import AgentBoxes, CameraSpec, ClipError
from gaia_app.data.latent_cache import LatentClip, clip_done, find_latent_clips, read_latent_clip, write_latent_clip


def latent_clip(frames: int = 8, views: int = 2, **kw) -> LatentClip:
    rng = np.random.default_rng(0)
    steps = frames // 4
    agents = [AgentBoxes([[10.0, 1.0, 0.5]], [[4.5, 1.8, 1.5]], [0.1], [0], [7]) for _ in range(frames)]
    cameras = [CameraSpec(f"cam{i}", np.eye(3) * 50, np.eye(4), 112, 64) for i in range(views)]
    args = dict(clip_id="clip_0001", mean=rng.normal(size=(views, steps, 4, 2, 3)).astype(np.float32),
                logvar=rng.normal(size=(views, steps, 4, 2, 3)).astype(np.float32), temporal_downsampling=4, fps=12.5,
                image_size=(64, 112), timestamps=np.arange(frames) / 12.5, cameras=cameras, meta={"weather": "rain"},
                actions=rng.normal(size=(frames, 2)).astype(np.float32), text=["It is raining."] * frames,
                agents=agents, frame_meta=[{"traffic_light": "red"}] * frames)
    return LatentClip(**{**args, **kw})


def test_round_trip_keeps_latents_and_every_condition(tmp_path: Path) -> None:
    clip = latent_clip()
    assert not clip_done(tmp_path, clip.clip_id)
    folder = write_latent_clip(tmp_path, clip)
    assert clip_done(tmp_path, clip.clip_id) and find_latent_clips(tmp_path) == [folder]
    back = read_latent_clip(folder)
    np.testing.assert_allclose(back.mean, clip.mean, atol=2e-3, rtol=2e-3)  # stored as float16
    np.testing.assert_allclose(back.logvar, clip.logvar, atol=2e-3, rtol=2e-3)
    np.testing.assert_array_equal(back.timestamps, clip.timestamps)
    np.testing.assert_array_equal(back.actions, clip.actions)
    assert back.text == clip.text and back.frame_meta == clip.frame_meta and back.meta == clip.meta
    assert [c.name for c in back.cameras] == ["cam0", "cam1"]
    np.testing.assert_array_equal(back.agents[3].centre, clip.agents[3].centre)
    assert (back.fps, back.image_size, back.temporal_downsampling) == (12.5, (64, 112), 4)


def test_absent_labels_stay_absent(tmp_path: Path) -> None:
    back = read_latent_clip(write_latent_clip(tmp_path, latent_clip(actions=None, text=None, agents=None, cameras=None,
                                                                     frame_meta=None)))
    assert back.actions is None and back.text is None and back.agents is None and back.cameras is None
    assert back.frame_meta is None


@pytest.mark.parametrize("field, value, message", [
    ("timestamps", np.arange(6) / 12.5, r"timestamps \(6,\), expected \(8,\)"),
    ("actions", np.zeros((8, 3), np.float32), r"actions \(8, 3\), expected \(8, 2\)"),
    ("text", ["a"] * 7, "7 text entries, expected 8"),
    ("logvar", np.zeros((2, 2, 4, 2, 2), np.float32), "mean .* and logvar .* must both be"),
])
def test_inconsistent_fields_are_named(field: str, value, message: str) -> None:
    with pytest.raises(ClipError, match=message):
        latent_clip(**{field: value})


def test_unfinished_or_broken_folders_are_reported(tmp_path: Path) -> None:
    folder = write_latent_clip(tmp_path, latent_clip())
    (folder / "conditions.json").write_text(json.dumps({"fps": 12.5}))
    with pytest.raises(ClipError, match=r"conditions.json: missing fields "
                                        r"\['cameras', 'image_size', 'meta', 'temporal_downsampling'\]"):
        read_latent_clip(folder)
    (folder / "mean.npy").unlink()
    with pytest.raises(ClipError, match="no mean.npy"):
        read_latent_clip(folder)
    with pytest.raises(ClipError, match="no finished clip folders"):
        find_latent_clips(tmp_path)
