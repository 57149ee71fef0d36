"""Telemetry joined to video by time (issue 24, item 5): gaia_app/data/importers/telemetry.py and the dashcam
importer's --telemetry. A dashcam with a logger yields labelled clips in one command; gaps, unordered time and
frames outside the log are clear errors, and nothing is written then."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gaia_app.data.clip import ClipError
from gaia_app.data.clip_folder import read_clip
from gaia_app.data.importers.dashcam import import_dashcam
from gaia_app.data.importers.dashcam import main as dashcam_main
from gaia_app.data.importers.telemetry import actions_at, local_xy, read_telemetry
from gaia_app.data.video_io import write_video


@pytest.fixture
def video_30hz(tmp_path, frames_factory) -> Path:
    return write_video(tmp_path / "drive.mp4", frames_factory(90, 50, 66, 2), fps=30)


def write_csv(path: Path, header: list[str], rows: list[list[float]]) -> Path:
    path.write_text(",".join(header) + "\n" + "\n".join(",".join(f"{v:.9f}" for v in row) for row in rows) + "\n")
    return path


def test_speed_and_yaw_rate_are_interpolated_onto_frame_times(tmp_path: Path) -> None:
    """A 10 Hz log offset by 5 s from the video: speed ramps 10 → 12 m/s, yaw rate 0.2 rad/s (κ = ψ̇ / v)."""
    t = 5.0 + np.arange(0, 3.01, 0.1)
    speed = 10 + 2 * (t - 5.0) / 3
    log = read_telemetry(write_csv(tmp_path / "log.csv", ["t", "speed", "yaw_rate"],
                                   [[a, b, 0.2] for a, b in zip(t, speed)]), offset_s=5.0)
    frames = np.arange(90) / 30
    actions = actions_at(log, frames)
    assert actions.shape == (90, 2) and actions.dtype == np.float32
    np.testing.assert_allclose(actions[:, 0], 10 + 2 * frames / 3, atol=1e-4)
    np.testing.assert_allclose(actions[:, 1], 0.2 / (10 + 2 * frames / 3), rtol=1e-3)


def test_gps_track_gives_speed_and_curvature(tmp_path: Path) -> None:
    """A circle of radius 50 m driven at 10 m/s, logged as lat/lon at 10 Hz (JSONL): κ = 1/50, to the left."""
    t = np.arange(0, 10.01, 0.1)
    angle = 10 * t / 50  # counter-clockwise seen from above: a left turn
    east, north = 50 * np.sin(angle), 50 * (1 - np.cos(angle))
    lat0, lon0 = 51.5, -0.1
    lat = lat0 + np.degrees(north / 6_371_000.0)
    lon = lon0 + np.degrees(east / (6_371_000.0 * np.cos(np.radians(lat0))))
    path = tmp_path / "gps.jsonl"
    path.write_text("\n".join(json.dumps({"t": float(a), "lat": float(b), "lon": float(c)})
                              for a, b, c in zip(t, lat, lon)))
    np.testing.assert_allclose(local_xy(lat, lon), np.stack([east, north], 1), atol=0.05)
    actions = actions_at(read_telemetry(path), np.arange(1.0, 9.0, 0.5))
    np.testing.assert_allclose(actions[:, 0], 10.0, rtol=2e-3)
    np.testing.assert_allclose(actions[:, 1], 1 / 50, rtol=2e-2)


def test_steering_angle_needs_the_wheelbase(tmp_path: Path) -> None:
    path = write_csv(tmp_path / "s.csv", ["t", "speed", "steering_angle"], [[k * 0.1, 5.0, 0.3] for k in range(40)])
    with pytest.raises(ClipError, match="steering_angle column needs the wheelbase"):
        actions_at(read_telemetry(path), np.array([1.0]))
    actions = actions_at(read_telemetry(path), np.array([1.0]), wheelbase=2.8, steering_ratio=15.0)
    np.testing.assert_allclose(actions[0, 1], np.tan(0.3 / 15) / 2.8, rtol=1e-5)


@pytest.mark.parametrize("rows,frames,match", [
    ([[0.0, 1], [0.2, 1], [0.1, 1], [0.3, 1]], [0.05], r"record 3 has t=0\.1 after t=0\.2"),
    ([[0.0, 1], [0.1, 1], [1.5, 1], [1.6, 1]], [0.5], r"a 1\.40 s gap\) around the frame at 0\.500 s.*--max-gap 0\.5"),
    ([[0.0, 1], [0.1, 1], [0.2, 1]], [0.0, 0.3], r"frames at 0\.300 s .* outside the logged span 0\.000–0\.200 s"),
])
def test_bad_logs_are_named_errors(tmp_path: Path, rows, frames, match: str) -> None:
    path = write_csv(tmp_path / "bad.csv", ["t", "speed"], rows)
    with pytest.raises(ClipError, match=match):
        actions_at(read_telemetry(path), np.array(frames), max_gap_s=0.5)


def test_missing_columns_and_values_are_named(tmp_path: Path) -> None:
    with pytest.raises(ClipError, match="no 't' column"):
        read_telemetry(write_csv(tmp_path / "a.csv", ["time", "speed"], [[0, 1], [1, 1]]))
    with pytest.raises(ClipError, match="no speed"):
        read_telemetry(write_csv(tmp_path / "b.csv", ["t", "yaw_rate"], [[0, 1], [1, 1]]))
    (tmp_path / "c.csv").write_text("t,speed\n0,1\n0.1,fast\n")
    with pytest.raises(ClipError, match=r"record 2 has speed='fast', expected a number"):
        read_telemetry(tmp_path / "c.csv")
    with pytest.raises(ClipError, match="no curvature source"):
        actions_at(read_telemetry(write_csv(tmp_path / "d.csv", ["t", "speed"], [[0, 1], [0.2, 1]])), np.array([0.1]))


def test_dashcam_with_a_logger_writes_labelled_clips_in_one_command(tmp_path: Path, video_30hz: Path, capsys) -> None:
    log = write_csv(tmp_path / "log.csv", ["t", "speed", "curvature"],
                    [[100 + k * 0.05, 8.0 + k * 0.01, 0.01] for k in range(70)])  # 100.00 … 103.45 s
    dashcam_main([str(video_30hz), "--out", str(tmp_path / "clips"), "--clip-seconds", "1.5", "--fps", "10",
                  "--telemetry", str(log), "--telemetry-offset", "100"])
    paths = [Path(p) for p in capsys.readouterr().out.split()]
    assert [p.name for p in paths] == ["drive_0000", "drive_0001"]
    clip = read_clip(paths[1])
    times = clip.timestamps
    np.testing.assert_allclose(clip.actions[:, 0], 8.0 + 0.2 * times, atol=1e-3)  # 0.01 m/s per 0.05 s sample
    np.testing.assert_allclose(clip.actions[:, 1], 0.01, atol=1e-6)
    # a log that does not cover the video: an error before anything is written
    with pytest.raises(ClipError, match="outside the logged span"):
        import_dashcam(video_30hz, tmp_path / "none", clip_len_s=1.5, telemetry=log, telemetry_offset=101.0,
                       progress=False)
    assert not (tmp_path / "none").exists() or not any((tmp_path / "none").iterdir())
