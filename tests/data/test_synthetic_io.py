"""Synthetic clips leave the process: export to clip folders, the Rerun world view, the gallery."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr
from rerun.chunk import RrdReader

from gaia_app.data.clip_folder import read_clip
from gaia_app.data.synthetic import SyntheticClipDataset, generate_clip
from gaia_app.data.synthetic.export import main as export_main
from gaia_app.data.synthetic.gallery import gallery_image
from gaia_app.viz.world import ego_poses, log_world
from gaia_app.viz.world import main as world_main


def test_export_writes_clip_folders_that_read_back(tmp_path: Path) -> None:
    folders = export_main(["--out", str(tmp_path), "--num-clips", "2", "--seed", "5", "--height", "64",
                           "--width", "112",
                           "--cameras", "front", "rear_left", "--clip-len", "6", "--fps", "12.5",
                           "--weather-mix", "rain=1", "--agent-density", "0.5"])
    expected = SyntheticClipDataset(num_clips=2, seed=5, cameras=["front", "rear_left"], clip_len=6, fps=12.5,
                                    weather_mix={"rain": 1.0}, agent_density=0.5)
    assert [f.name for f in folders] == ["synthetic-s5-000000", "synthetic-s5-000001"]
    for i, folder in enumerate(folders):
        assert sorted(p.name for p in folder.iterdir()) == ["front.mp4", "labels.jsonl", "meta.json", "rear_left.mp4"]
        back, clip = read_clip(folder), expected[i]
        assert back.frames.shape == clip.frames.shape and back.fps == np.float64(12.5)
        assert np.abs(back.frames.astype(int) - clip.frames.astype(int)).mean() < 6  # H.264 is lossy
        assert np.allclose(back.actions, clip.actions, atol=1e-5) and back.text == clip.text
        assert back.meta["weather"] == "rain" and back.meta["lane_types"] == clip.meta["lane_types"]
        assert back.frame_meta[0]["boxes_2d"] == clip.frame_meta[0]["boxes_2d"]
        assert np.allclose(back.agents[2].centre, clip.agents[2].centre, atol=1e-4)
        assert np.allclose(back.cameras[1].extrinsics, clip.cameras[1].extrinsics)


def test_log_world_writes_rig_agents_path_actions_and_captions(tmp_path: Path) -> None:
    clip = generate_clip(seed=4, cameras=3, clip_len=5)
    path = tmp_path / "world.rrd"
    rec = rr.RecordingStream("test_world", recording_id="world")
    rec.save(str(path))
    log_world(rec, clip)
    rec.flush()
    rec.disconnect()
    reader = RrdReader(str(path))
    assert len(reader.recordings()) == 1 and len(reader.blueprints()) == 1
    rows, static = {}, set()
    for chunk in reader.stream().collect().stream().to_chunks():
        if chunk.is_static:
            static.add(chunk.entity_path)
        else:
            assert "frame" in chunk.timeline_names
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    cams = [c.name for c in clip.cameras]
    assert {"/world", "/world/ego_path", *(f"/world/ego/rig/{c}" for c in cams)} <= static
    for entity in ["/world/ego", "/world/ego/agents", "/actions/speed", "/actions/curvature", "/text",
                   *(f"/world/ego/rig/{c}" for c in cams), *(f"/world/ego/rig/{c}/boxes" for c in cams)]:
        assert rows.get(entity) == 5, entity


def test_world_command_writes_a_recording(tmp_path: Path) -> None:
    path = tmp_path / "synthetic.rrd"
    world_main(["--rrd", str(path), "--frames", "3", "--cameras", "2", "--height", "32", "--width", "56"])
    entities = {chunk.entity_path for chunk in RrdReader(str(path)).stream().collect().stream().to_chunks()}
    assert {"/world/ego/rig/front", "/world/ego/rig/front_left", "/world/ego/agents", "/text"} <= entities


def test_ego_poses_fall_back_to_integrated_actions() -> None:
    clip = generate_clip(seed=9, clip_len=6)
    logged = ego_poses(clip)
    clip.frame_meta = None
    integrated = ego_poses(clip)  # starts at the origin, heading +x
    yaw0 = logged[0, 2]
    dx, dy = (logged[:, :2] - logged[0, :2]).T
    in_first_frame = np.c_[np.cos(yaw0) * dx + np.sin(yaw0) * dy, -np.sin(yaw0) * dx + np.cos(yaw0) * dy,
                           logged[:, 2] - yaw0]
    assert np.allclose(integrated, in_first_frame, atol=1e-3)


def test_gallery_grid_has_one_labelled_row_per_setting() -> None:
    rows = (("urban", "clear", "day", "cruise"), ("rural", "snow", "night", "brake"))
    image = gallery_image(seed=1, height=48, width=80, rows=rows)
    assert image.shape == (96, 400, 3) and image.dtype == np.uint8
    assert image[48:].mean() < image[:48].mean()  # the night row is darker
