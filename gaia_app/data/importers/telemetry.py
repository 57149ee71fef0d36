"""Join a logger's telemetry (CSV or JSONL) to video frames by time: ego speed and curvature per frame.

A dashcam with a logger records video and telemetry on separate clocks. The telemetry file has one record per
sample with a time `t` in seconds (on the video's clock after `offset_s`: t_video = t − offset_s) and any of:

    speed            m/s                            → speed
    lat, lon         degrees (WGS-84)               → speed (when no `speed`) and the path's curvature
    curvature        1/m, positive to the left      → curvature
    yaw_rate         rad/s, positive to the left    → curvature = yaw_rate / speed
    steering_angle   rad, positive to the left      → curvature = tan(angle / steering_ratio) / wheelbase

Curvature is taken from the first of curvature, yaw_rate, steering_angle, lat/lon that the file has. Each frame's
value is interpolated linearly between the two samples around it. Nothing is extrapolated or filled in: time
that is not strictly increasing, a frame outside the logged span, a gap between samples longer than `max_gap_s`
around a frame, or a non-finite value near one are errors naming the file, the row and the setting to change.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gaia_app.data.actions import (
    LABEL_RANGES,
    curvature_from_poses,
    curvature_from_steering,
    curvature_from_yaw_rate,
    speed_from_poses,
)
from gaia_app.data.clip import ClipError

EARTH_RADIUS_M = 6_371_000.0
COLUMNS = ("t", "speed", "lat", "lon", "curvature", "yaw_rate", "steering_angle")


@dataclass(frozen=True)
class Telemetry:
    """Samples of one log: t (n,) seconds on the video clock, and each column the file has, (n,) floats."""

    path: Path
    t: np.ndarray
    columns: dict[str, np.ndarray]


def read_records(path: Path) -> list[dict[str, object]]:
    """The records of a .csv (header row) or .jsonl (one object per line) file."""
    if not path.is_file():
        raise FileNotFoundError(f"telemetry file '{path}' does not exist")
    if path.suffix.lower() == ".csv":
        with path.open(newline="") as handle:
            return list(csv.DictReader(handle))
    if path.suffix.lower() in (".jsonl", ".ndjson"):
        records = []
        for line_no, line in enumerate(path.read_text().splitlines(), start=1):
            if line.strip():
                try:
                    records.append(json.loads(line))
                except json.JSONDecodeError as error:
                    raise ClipError(f"{path}:{line_no}: not a JSON object ({error.msg})") from None
        return records
    raise ClipError(f"telemetry file '{path}': expected a .csv or .jsonl file")


def column(records: list[dict[str, object]], name: str, path: Path) -> np.ndarray | None:
    """Column `name` as floats (None when no record has it); a record that lacks it or holds text is an error."""
    if not any(name in r and r[name] not in ("", None) for r in records):
        return None
    values = np.empty(len(records))
    for i, record in enumerate(records):
        try:
            values[i] = float(record[name])  # type: ignore[arg-type]
        except (KeyError, TypeError, ValueError):
            raise ClipError(f"{path}: record {i + 1} has {name}={record.get(name)!r}, expected a number "
                            f"(every record needs every column the file uses)") from None
    return values


def read_telemetry(path: str | Path, offset_s: float = 0.0) -> Telemetry:
    """The log in `path`, its times moved onto the video clock (t − offset_s), checked to increase strictly."""
    path = Path(path)
    records = read_records(path)
    if len(records) < 2:
        raise ClipError(f"{path}: {len(records)} telemetry records, need at least 2 to interpolate")
    t = column(records, "t", path)
    if t is None:
        raise ClipError(f"{path}: no 't' column (seconds); expected columns among {COLUMNS}")
    if not np.all(np.isfinite(t)):
        raise ClipError(f"{path}: record {int(np.argmax(~np.isfinite(t))) + 1} has a non-finite time t")
    if not np.all(np.diff(t) > 0):
        i = int(np.argmax(np.diff(t) <= 0)) + 1  # the record that does not come after its predecessor
        raise ClipError(f"{path}: time must increase strictly; record {i + 1} has t={t[i]:g} after t={t[i - 1]:g}")
    columns = {name: values for name in COLUMNS[1:] if (values := column(records, name, path)) is not None}
    if "speed" not in columns and not {"lat", "lon"} <= columns.keys():
        raise ClipError(f"{path}: no speed: give a 'speed' column (m/s) or 'lat'/'lon' (degrees)")
    return Telemetry(path, t - offset_s, columns)


def local_xy(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """(n, 2) metres east, north of the first fix (equirectangular: exact enough over a few kilometres)."""
    lat0 = np.radians(lat[0])
    east = np.radians(lon - lon[0]) * np.cos(lat0) * EARTH_RADIUS_M
    north = np.radians(lat - lat[0]) * EARTH_RADIUS_M
    return np.stack([east, north], axis=1)


def sample_actions(log: Telemetry, wheelbase: float | None = None, steering_ratio: float = 1.0) -> np.ndarray:
    """(n, 2) speed (m/s) and curvature (1/m) at each telemetry sample."""
    c = log.columns
    track = local_xy(c["lat"], c["lon"]) if {"lat", "lon"} <= c.keys() else None
    speed = c["speed"] if "speed" in c else speed_from_poses(track, log.t)
    if "curvature" in c:
        curvature = c["curvature"]
    elif "yaw_rate" in c:
        curvature = curvature_from_yaw_rate(c["yaw_rate"], speed)
    elif "steering_angle" in c:
        if wheelbase is None:
            raise ClipError(f"{log.path}: a steering_angle column needs the wheelbase (--wheelbase, metres)")
        curvature = curvature_from_steering(c["steering_angle"], wheelbase, steering_ratio)
    elif track is not None:
        curvature = curvature_from_poses(track, log.t)
    else:
        raise ClipError(f"{log.path}: no curvature source: "
                        "give 'curvature', 'yaw_rate', 'steering_angle' or 'lat'/'lon'")
    return np.stack([speed, curvature], axis=1)


def actions_at(log: Telemetry, frame_times: np.ndarray, max_gap_s: float = 0.5, wheelbase: float | None = None,
               steering_ratio: float = 1.0) -> np.ndarray:
    """(T, 2) float32 speed and curvature at each frame time (T,) seconds on the video clock, interpolated."""
    frame_times = np.asarray(frame_times, dtype=np.float64)
    first, last = log.t[0], log.t[-1]
    outside = (frame_times < first) | (frame_times > last)
    if outside.any():
        raise ClipError(f"{log.path}: frames at {frame_times[outside][0]:.3f} s (video clock) lie outside the logged "
                        f"span {first:.3f}–{last:.3f} s; check --telemetry-offset or trim the video")
    after = np.clip(np.searchsorted(log.t, frame_times, side="right"), 1, len(log.t) - 1)
    gaps = log.t[after] - log.t[after - 1]
    if (gaps > max_gap_s).any():
        i = int(np.argmax(gaps > max_gap_s))
        raise ClipError(f"{log.path}: no telemetry between {log.t[after[i] - 1]:.3f} s and {log.t[after[i]]:.3f} s "
                        f"(a {gaps[i]:.2f} s gap) around the frame at {frame_times[i]:.3f} s; the limit is "
                        f"--max-gap {max_gap_s} s")
    actions = sample_actions(log, wheelbase, steering_ratio)
    near = np.unique(np.concatenate([after - 1, after]))
    if not np.all(np.isfinite(actions[near])):
        row = int(near[~np.all(np.isfinite(actions[near]), axis=1)][0])
        raise ClipError(f"{log.path}: record {row + 1} gives a non-finite speed or curvature {actions[row].tolist()}")
    for channel, (name, limit) in enumerate(LABEL_RANGES.items()):  # what every clip reader accepts
        outside = near[np.abs(actions[near, channel]) > limit]
        if len(outside):
            row = int(outside[0])
            raise ClipError(f"{log.path}: record {row + 1} gives {name} {actions[row, channel]:g}, outside "
                            f"[-{limit:g}, {limit:g}] {'m/s' if name == 'speed' else '1/m'} (wrong units?)")
    return np.stack([np.interp(frame_times, log.t, actions[:, k]) for k in range(2)], axis=1).astype(np.float32)


def position_at(log: Telemetry, time_s: float) -> list[float] | None:
    """[lat, lon] at `time_s` on the video clock (interpolated), or None when the log has no GPS."""
    if not {"lat", "lon"} <= log.columns.keys():
        return None
    return [float(np.interp(time_s, log.t, log.columns[name])) for name in ("lat", "lon")]
