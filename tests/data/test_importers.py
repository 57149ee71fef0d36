"""Importers: a plain dashcam video and the real PandaSet rig become valid clip folders."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from gaia_app.data.actions import quaternion_to_rotation
from gaia_app.data.clip import AGENT_CATEGORIES, ClipError
from gaia_app.data.clip_folder import ClipFolderDataset, inspect_clip, read_clip
from gaia_app.data.importers.dashcam import import_dashcam
from gaia_app.data.importers.dashcam import main as dashcam_main
from gaia_app.data.importers.pandaset import import_pandaset
from gaia_app.data.importers.pandaset import main as pandaset_main
from gaia_app.data.transforms import resample_clip
from gaia_app.data.video_io import write_video


@pytest.fixture
def video_30hz(tmp_path, frames_factory) -> Path:
    """3 s of 30 Hz video, 66x50 pixels (odd half-size on purpose: 33x25 would not encode)."""
    return write_video(tmp_path / "drive.mp4", frames_factory(90, 50, 66, 2), fps=30)


def test_dashcam_split_and_resample(tmp_path, video_30hz):
    paths = import_dashcam(video_30hz, tmp_path / "clips", clip_len_s=1.0, fps=10, progress=False)
    assert [p.name for p in paths] == ["drive_0000", "drive_0001", "drive_0002"]
    clip = read_clip(paths[1])
    assert clip.num_frames == 10 and clip.actions is None and clip.cameras is None
    np.testing.assert_allclose(clip.timestamps, 1.0 + np.arange(10) / 10, atol=1e-9)
    assert clip.meta == {"source_video": "drive.mp4", "source_start_s": 1.0, "camera_names": ["front"]}


def test_dashcam_resize_tail_and_overwrite(tmp_path, video_30hz, caplog):
    with caplog.at_level(logging.INFO):
        paths = import_dashcam(video_30hz, tmp_path, clip_len_s=0.7, camera="dash", height=24, width=32, progress=False)
    assert len(paths) == 4 and "dropping the last 6 frames" in caplog.text  # 90 = 4 x 21 + 6
    clip = read_clip(paths[0])
    assert clip.frames.shape == (1, 21, 3, 24, 32) and clip.meta["camera_names"] == ["dash"]
    with pytest.raises(ClipError, match="already exists"):
        import_dashcam(video_30hz, tmp_path, clip_len_s=0.7, progress=False)
    with pytest.raises(ClipError, match="shorter than one clip of 5.0 s"):
        import_dashcam(video_30hz, tmp_path / "x", clip_len_s=5.0, progress=False)


def test_dashcam_truncated_source_never_pads(tmp_path, video_30hz):
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(video_30hz.read_bytes()[: video_30hz.stat().st_size * 3 // 4])
    paths = import_dashcam(cut, tmp_path / "clips", clip_len_s=0.5, progress=False)
    assert len(paths) < 6 and all(read_clip(p).num_frames == 15 for p in paths)
    assert sorted(p.name for p in (tmp_path / "clips").iterdir()) == [p.name for p in paths]


def test_dashcam_cli(tmp_path, video_30hz, capsys):
    dashcam_main([str(video_30hz), "--out", str(tmp_path / "cli"), "--clip-seconds", "1.5", "--height", "16",
                  "--width", "16"])
    printed = capsys.readouterr().out.split()
    assert printed == [str(tmp_path / "cli" / "drive_0000"), str(tmp_path / "cli" / "drive_0001")]


# ---------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def udacity_root(real_dir, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("udacity")
    import_dashcam(real_dir / "udacity_solid_white_right.mp4", root, height=128, width=224, progress=False)
    return root


@pytest.mark.real_data
def test_real_dashcam_through_dataset(udacity_root):
    ds = ClipFolderDataset(udacity_root)
    assert ds.clip_ids == ["udacity_solid_white_right"] and ds.num_frames == [221] and ds.skipped == []
    clip = ds[0]
    assert clip.frames.shape == (1, 221, 3, 128, 224) and clip.fps == pytest.approx(25.0)
    assert clip.actions is None and clip.agents is None  # the video has no labels, none are invented
    assert 40 < clip.frames.mean() < 200 and clip.frames.std() > 20  # real pixels, not blank
    assert resample_clip(clip, 6.25).num_frames == 56


@pytest.fixture(scope="module")
def pandaset_clip(real_dir, tmp_path_factory):
    root = tmp_path_factory.mktemp("pandaset")
    path = import_pandaset(real_dir / "pandaset_002", root, height=128, width=224, progress=False)
    return read_clip(path)


@pytest.mark.real_data
def test_pandaset_rig(pandaset_clip):
    clip = pandaset_clip
    names = [c.name for c in clip.cameras]
    assert names == ["front", "front_left", "front_right", "left", "right", "back"]
    assert clip.frames.shape == (6, 80, 3, 128, 224) and clip.fps == pytest.approx(10.0, rel=1e-3)
    looks = {c.name: c.extrinsics[:3, :3] @ [0, 0, 1] for c in clip.cameras}  # optical axis in the ego frame
    np.testing.assert_allclose(looks["front"], [1, 0, 0], atol=0.03)
    np.testing.assert_allclose(looks["back"], [-1, 0, 0], atol=0.05)
    assert looks["left"][1] > 0.95 and looks["right"][1] < -0.95
    down = {c.name: c.extrinsics[:3, :3] @ [0, 1, 0] for c in clip.cameras}  # image "down" points to the road
    assert all(d[2] < -0.99 for d in down.values())
    # 960x540 scaled to 228x128 (covering 224x128), then 2 px cropped on each side
    fx, cx = clip.cameras[0].intrinsics[0, [0, 2]]
    np.testing.assert_allclose([fx, cx], [1970.0131 / 2 * 228 / 960, 485.0001 * 228 / 960 - 2])


@pytest.mark.real_data
def test_pandaset_ego_motion(pandaset_clip):
    speed, curvature = pandaset_clip.actions.T
    assert speed[0] < 0.5 and 5.0 < speed[-1] < 6.5 and np.all(speed >= 0)  # pulls away to about 5.7 m/s
    travelled = np.sum(speed[1:] * np.diff(pandaset_clip.timestamps))
    assert 18 < travelled < 24  # README: about 21 m
    assert np.all(np.abs(curvature) < 0.02)  # a nearly straight street (radius > 50 m)


@pytest.mark.real_data
def test_pandaset_agents(pandaset_clip):
    agents = pandaset_clip.agents
    counts = np.bincount(np.concatenate([a.category for a in agents]), minlength=len(AGENT_CATEGORIES))
    named = dict(zip(AGENT_CATEGORIES, counts.tolist()))
    # README counts: Car + Pickup Truck; Pedestrian (+ with Object); trucks; Bicycle + Motorcycle
    assert named == {"car": 7073, "bus": 0, "truck": 640, "cyclist": 158, "pedestrian": 1094}
    assert pandaset_clip.meta["dropped_agents"] == {"Cones": 320, "Towed Object": 80}
    # most agents are parked: as we drive ~21 m forward they move ~21 m backwards in the ego frame
    first, last = agents[0], agents[-1]
    common, i, j = np.intersect1d(first.track_id, last.track_id, return_indices=True)
    assert len(common) > 50
    assert -24 < np.median(last.centre[j, 0] - first.centre[i, 0]) < -18


@pytest.mark.real_data
def test_pandaset_boxes_project_onto_the_front_image(pandaset_clip):
    cam = pandaset_clip.cameras[0]
    boxes = pandaset_clip.agents[40]
    ego_to_cam = np.linalg.inv(cam.extrinsics)
    p = boxes.centre @ ego_to_cam[:3, :3].T + ego_to_cam[:3, 3]
    ahead = p[:, 2] > 2
    uv = (p[ahead] @ cam.intrinsics.T)[:, :2] / p[ahead, 2:]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    assert inside.sum() >= 10
    # box centres sit around or below the horizon (the camera is ~1.8 m up), never high in the sky
    assert np.all(uv[inside, 1] > 0.3 * cam.height)


@pytest.mark.real_data
def test_pandaset_cli_copies_videos_and_matches_the_raw_projection(real_dir, tmp_path, caplog, capsys):
    seq = real_dir / "pandaset_002"
    with caplog.at_level(logging.INFO):
        pandaset_main([str(seq), "--out", str(tmp_path)])
    assert "dropped 400 boxes" in caplog.text and "Cones 320, Towed Object 80" in caplog.text
    clip_dir = Path(capsys.readouterr().out.strip())
    assert inspect_clip(clip_dir) == 80  # copied mp4s, checked without decoding
    meta = json.loads((clip_dir / "meta.json").read_text())
    rows = (clip_dir / "labels.jsonl").read_text().splitlines()
    frame = 5  # near standstill, so the cameras' exposure offsets (up to 0.1 s) do not matter
    raw_boxes = json.loads((seq / "annotations" / "cuboids.jsonl").read_text().splitlines()[frame])["boxes"]
    world = np.array([b["center"] for b in raw_boxes if b["category"] not in ("Cones", "Towed Object")])
    ego = np.array([a["centre"] for a in json.loads(rows[frame])["agents"]])
    for cam in meta["cameras"]:
        pose = json.loads((seq / "calib_and_poses" / f"{cam['name']}_camera" / "poses.json").read_text())[frame]
        rot = quaternion_to_rotation(np.array([pose["heading"][k] for k in "wxyz"]))
        in_cam_raw = (world - [pose["position"][k] for k in "xyz"]) @ rot  # README: R^T (p - t)
        ext = np.array(cam["extrinsics"])
        in_cam_rig = (ego - ext[:3, 3]) @ ext[:3, :3]
        k = np.array(cam["intrinsics"])
        ahead = in_cam_raw[:, 2] > 2
        uv_raw = (in_cam_raw[ahead] @ k.T)[:, :2] / in_cam_raw[ahead, 2:]
        uv_rig = (in_cam_rig[ahead] @ k.T)[:, :2] / in_cam_rig[ahead, 2:]
        inside = np.all((uv_raw >= 0) & (uv_raw < [960, 540]), axis=1)
        assert inside.sum() >= 3, cam["name"]
        assert np.abs(uv_raw - uv_rig)[inside].max() < 3.0, cam["name"]  # pixels at 960x540
