"""Clip folders: exact label round trip, atomic writes, and validation errors that name file, line and field."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from gaia_app.data.clip import Clip, ClipError
from gaia_app.data.clip_folder import ClipFolderDataset, inspect_clip, read_clip
from gaia_app.data.clip_writer import write_clip
from gaia_app.data.video_io import VideoReadError, write_video


def _edit_labels(clip_dir: Path, edit) -> None:
    """Rewrite labels.jsonl after `edit(rows)` changed the parsed rows in place."""
    path = clip_dir / "labels.jsonl"
    rows = [json.loads(line) for line in path.read_text().splitlines()]
    edit(rows)
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n")


@pytest.fixture
def written(tmp_path, clip) -> Path:
    return write_clip(clip, tmp_path / "root")


def test_round_trip_keeps_labels_exactly(written, clip):
    back = read_clip(written)
    assert back.clip_id == clip.clip_id and back.frames.shape == clip.frames.shape
    assert np.abs(back.frames.astype(int) - clip.frames).mean() < 4
    np.testing.assert_array_equal(back.timestamps, clip.timestamps)
    np.testing.assert_array_equal(back.actions, clip.actions)
    assert back.text == clip.text and back.text[0] is None
    assert back.frame_meta == clip.frame_meta and back.meta == clip.meta
    for a, b in zip(back.agents, clip.agents):
        for field in ("centre", "size", "yaw", "category", "track_id"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert len(back.agents[0]) == 0  # an empty frame stays empty
    for a, b in zip(back.cameras, clip.cameras):
        assert (a.name, a.width, a.height) == (b.name, b.width, b.height)
        np.testing.assert_array_equal(a.intrinsics, b.intrinsics)
        np.testing.assert_array_equal(a.extrinsics, b.extrinsics)
    assert sorted(p.name for p in written.iterdir()) == ["front.mp4", "labels.jsonl", "meta.json", "rear_left.mp4"]


def test_read_a_window(written):
    full = read_clip(written)
    window = read_clip(written, start=5, max_frames=10)
    np.testing.assert_array_equal(window.frames, full.frames[:, 5:])
    np.testing.assert_array_equal(window.actions, full.actions[5:])
    assert window.text == full.text[5:] and window.frame_meta == full.frame_meta[5:] and len(window.agents) == 3
    with pytest.raises(ClipError, match="start frame 8 outside 0..7"):
        read_clip(written, start=8)


def test_select_cameras_when_reading(written):
    back = read_clip(written, cameras=["rear_left"])
    assert back.num_views == 1 and [c.name for c in back.cameras] == ["rear_left"]
    with pytest.raises(ClipError, match=r"cameras \['back'\] not in"):
        read_clip(written, cameras=["back"])


def test_overwrite_is_refused_then_allowed(tmp_path, written, clip):
    with pytest.raises(ClipError, match="already exists; pass overwrite=True"):
        write_clip(clip, written.parent)
    shorter = clip.select_frames(np.arange(4))
    write_clip(shorter, written.parent, overwrite=True)
    assert read_clip(written).num_frames == 4
    assert [p.name for p in written.parent.iterdir()] == ["clip_a"]  # no temporary folders left


def test_failed_write_leaves_nothing(tmp_path, clip):
    clip.frame_meta[2] = {"speed": 3.0}  # clashes with a label key
    with pytest.raises(ClipError, match="reserved label keys"):
        write_clip(clip, tmp_path)
    odd = Clip("odd", np.zeros((1, 2, 3, 47, 64), np.uint8), [0.0, 0.1])
    with pytest.raises(ClipError, match="must be even"):
        write_clip(odd, tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_clip_without_camera_specs_keeps_view_names(tmp_path, clip):
    plain = Clip("plain", clip.frames, clip.timestamps, meta={"camera_names": ["dash", "cabin"]})
    back = read_clip(write_clip(plain, tmp_path))
    assert back.cameras is None and back.actions is None and back.agents is None and back.text is None
    assert back.meta["camera_names"] == ["dash", "cabin"]


def test_folder_with_bare_meta_names_views_by_mp4_stem(tmp_path, frames_factory):
    clip_dir = tmp_path / "bare"
    clip_dir.mkdir()
    write_video(clip_dir / "dashcam.mp4", frames_factory(5, 32, 32, 0), fps=5)
    (clip_dir / "meta.json").write_text('{"fps": 5}')
    (clip_dir / "labels.jsonl").write_text("".join(f'{{"t": {i / 5}}}\n' for i in range(5)))
    back = read_clip(clip_dir)
    assert back.meta["camera_names"] == ["dashcam"] and back.actions is None and back.num_frames == 5


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda rows: rows[2].pop("curvature"), r"labels.jsonl line 3: missing field 'curvature' \(other lines"),
        (lambda rows: rows[4].pop("t"), r"labels.jsonl line 5: missing field 't'"),
        (lambda rows: rows[1].update(speed="fast"), r"labels.jsonl line 2: field 'speed' must be a finite number"),
        (lambda rows: rows[5].pop("agents"), r"labels.jsonl line 6: missing field 'agents'"),
        (lambda rows: rows[2]["agents"][0].pop("yaw"), r"labels.jsonl line 3: field 'agents'.*missing field 'yaw'"),
        (lambda rows: rows[3].update(t=rows[2]["t"]), r"labels.jsonl line 4: field 't' must increase"),
        (lambda rows: rows.pop(), r"labels.jsonl: 7 label lines for 8 video frames"),
        (lambda rows: [r.update(t=r["t"] * 1000) for r in rows], r"runs at 0.01 Hz but meta.json says fps 10"),
    ],
    ids=["curvature", "t", "not-a-number", "agents", "agent-field", "t-order", "count", "milliseconds"],
)
def test_bad_labels_name_file_line_and_field(written, edit, message):
    _edit_labels(written, edit)
    with pytest.raises(ClipError, match=message):
        read_clip(written)


def test_malformed_json_line(written):
    lines = (written / "labels.jsonl").read_text().splitlines()
    lines[3] = lines[3][:-5]
    (written / "labels.jsonl").write_text("\n".join(lines))
    with pytest.raises(ClipError, match="labels.jsonl line 4: invalid JSON"):
        read_clip(written)


def test_unlabelled_frames_give_no_actions(written):
    _edit_labels(written, lambda rows: [(r.pop("speed"), r.pop("curvature")) for r in rows])
    assert read_clip(written).actions is None


def test_actions_from_yaw_rate_labels(written):
    # A user's labels may carry yaw rate instead of curvature (docs/data.md, label options).
    _edit_labels(written, lambda rows: [r.update(yaw_rate=0.2 * r["speed"]) or r.pop("curvature") for r in rows])
    np.testing.assert_allclose(read_clip(written).actions[:, 1], 0.2, rtol=1e-6)


def test_actions_from_steering_need_the_vehicle_in_meta(written):
    _edit_labels(written, lambda rows: [r.update(steering_angle=0.05) or r.pop("curvature") for r in rows])
    with pytest.raises(ClipError, match=r"labels.jsonl: cannot build actions.*also needs a wheelbase in meta.json"):
        read_clip(written)
    meta = json.loads((written / "meta.json").read_text())
    meta["vehicle"] = {"wheelbase": 2.5, "steering_ratio": 10.0}
    (written / "meta.json").write_text(json.dumps(meta))
    np.testing.assert_allclose(read_clip(written).actions[:, 1], np.tan(0.005) / 2.5, rtol=1e-6)


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda d: (d / "meta.json").unlink(), "meta.json: missing"),
        (lambda d: (d / "labels.jsonl").unlink(), "labels.jsonl: missing"),
        (lambda d: (d / "rear_left.mp4").unlink(), "rear_left.mp4: camera video missing"),
        (lambda d: (d / "meta.json").write_text('{"fps": 10, "cameras": [{"name": "front"}]}'),
         r"meta.json: cameras\[0\] is missing field 'intrinsics'"),
        (lambda d: (d / "meta.json").write_text('{"cameras": null}'), "meta.json: field 'fps' must be a positive"),
    ],
    ids=["meta", "labels", "video", "camera-field", "fps"],
)
def test_missing_files_and_fields(written, damage, message):
    damage(written)
    with pytest.raises(ClipError, match=message):
        read_clip(written)


def test_cameras_with_different_frame_counts_name_both(written, frames_factory):
    write_video(written / "rear_left.mp4", frames_factory(6, 48, 64, 0), fps=10)
    message = "camera 'front' has 8 frames but camera 'rear_left' has 6"
    with pytest.raises(ClipError, match=message):
        inspect_clip(written)
    with pytest.raises(ClipError, match=message):
        read_clip(written)


def test_truncated_video_is_skipped_by_the_dataset_and_raises_on_read(tmp_path, clip_factory, caplog):
    root = tmp_path / "root"
    for name in ("b_good", "a_cut", "c_good"):
        write_clip(clip_factory(name, t=30), root)
    video = root / "a_cut" / "front.mp4"
    video.write_bytes(video.read_bytes()[: video.stat().st_size * 2 // 3])
    with pytest.raises(VideoReadError, match="a_cut/front.mp4"):
        read_clip(root / "a_cut")
    with caplog.at_level(logging.WARNING):
        ds = ClipFolderDataset(root)
    assert ds.clip_ids == ["b_good", "c_good"] and len(ds) == 2 and ds.num_frames == [30, 30]
    assert [cid for cid, _ in ds.skipped] == ["a_cut"] and "front.mp4" in ds.skipped[0][1]
    assert "skipped 1 of 3 clip folders" in caplog.text
    assert ds[1].clip_id == "c_good"


def test_dataset_min_frames_cameras_and_empty_root(tmp_path, clip_factory):
    root = tmp_path / "root"
    write_clip(clip_factory("short", t=3), root)
    write_clip(clip_factory("long", t=9), root)
    (root / "not_a_clip").mkdir()
    ds = ClipFolderDataset(root, min_frames=5, cameras=["rear_left"])
    assert ds.clip_ids == ["long"] and ds[0].num_views == 1
    assert dict(ds.skipped) == {"not_a_clip": f"{root / 'not_a_clip' / 'meta.json'}: missing",
                                "short": "3 frames, fewer than min_frames=5"}
    with pytest.raises(ClipError, match=f"{root}: no usable clip folder .*short: 3 frames"):
        ClipFolderDataset(root, min_frames=50)
    with pytest.raises(ClipError, match="clip root folder not found"):
        ClipFolderDataset(tmp_path / "nowhere")
