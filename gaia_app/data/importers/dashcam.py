"""Import a plain dashcam video (any frame rate, no labels) into one or more clip folders.

    python -m gaia_app.data.importers.dashcam drive.mp4 --out data/clips --clip-seconds 10 --height 288 --width 512

The clips carry timestamps, and with a logger's telemetry (`--telemetry log.csv`, joined by time,
gaia_app/data/importers/telemetry.py) ego speed and curvature per frame; no text, agents or camera
calibration, because the video has none (absent labels are never invented). Timestamps are frame
index / container fps, so a variable-frame-rate source is treated as constant-rate at its average rate.

    python -m gaia_app.data.importers.dashcam drive.mp4 --out data/clips --clip-seconds 10 \
        --telemetry drive_log.csv --telemetry-offset 12.4
"""

from __future__ import annotations

import argparse
import logging
import math
import re
from collections.abc import Iterator
from itertools import islice
from pathlib import Path

import numpy as np
from tqdm import tqdm

from gaia_app.data.clip import ClipError
from gaia_app.data.clip_writer import ClipFolderWriter, label_rows, meta_json
from gaia_app.data.importers.telemetry import actions_at, position_at, read_telemetry
from gaia_app.data.names import check_camera_name, check_clip_id
from gaia_app.data.transforms import ResizePlan, plan_resize, resample_indices, resize_image
from gaia_app.data.video_io import count_intact_packets, iter_frames, video_info

log = logging.getLogger(__name__)


def _resize_plan(width: int, height: int, out_h: int | None, out_w: int | None, mode: str) -> ResizePlan | None:
    """The resize to apply, or None. Without a target size, an odd size loses its last row/column:
    libx264's yuv420p needs even sizes (see video_io.write_video)."""
    if (out_h is None) != (out_w is None):
        raise ValueError("give both height and width, or neither")
    if out_h is not None:
        return plan_resize(width, height, out_w, out_h, mode)
    if width % 2 or height % 2:
        log.info("cropping %dx%d to an even size for H.264", width, height)
        return ResizePlan(width, height, 0, 0, width - width % 2, height - height % 2)
    return None


def _selected_frames(video: Path, keep: np.ndarray, plan: ResizePlan | None, bar: tqdm) -> Iterator[np.ndarray]:
    """Decode `video` once, yielding only frames whose index is in `keep` (sorted), resized by `plan`."""
    wanted = np.zeros(int(keep[-1]) + 1, dtype=bool)
    wanted[keep] = True
    for index, frame in enumerate(iter_frames(video)):
        if index >= len(wanted):
            return
        if wanted[index]:
            bar.update(1)
            yield frame if plan is None else resize_image(frame, plan)


def _clip_ids(stem: str, clip_id: str | None, count: int) -> list[str]:
    """Clip folder names: the given clip id (checked), else the file stem made plain (other characters → '_')."""
    base = check_clip_id(clip_id, "--clip-id") if clip_id else \
        re.sub(r"[^A-Za-z0-9._-]", "_", stem).lstrip("._-").replace("..", "_") or "clip"
    return [base] if count == 1 else [f"{base}_{k:04d}" for k in range(count)]


def import_dashcam(
    video_path: str | Path,
    out_root: str | Path,
    clip_len_s: float | None = None,
    camera: str = "front",
    fps: float | None = None,
    height: int | None = None,
    width: int | None = None,
    resize_mode: str = "crop",
    clip_id: str | None = None,
    overwrite: bool = False,
    progress: bool = True,
    telemetry: str | Path | None = None,
    telemetry_offset: float = 0.0,
    max_gap: float = 0.5,
    wheelbase: float | None = None,
    steering_ratio: float = 1.0,
) -> list[Path]:
    """Cut a dashcam video into clip folders under `out_root`; returns their paths in time order.

    clip_len_s: seconds per clip (None: one clip for the whole video; a tail shorter than a clip
    is dropped, logged). camera: view name (`<camera>.mp4`). fps: rate (Hz) to keep, picked by
    timestamps (None: every frame). height, width: output size in pixels (both or neither),
    with `resize_mode` "crop" (aspect kept) or "stretch". clip_id: base name (default: the file
    stem; split clips get `_0000`, `_0001`, ...). The video is decoded once, streaming.
    telemetry: a CSV / JSONL log whose time minus `telemetry_offset` (s) is the video's time; every kept frame gets
    its speed and curvature, interpolated (telemetry.py; `max_gap` s between samples at most, `wheelbase` and
    `steering_ratio` for a steering-angle log). It is checked against every frame before any clip is written.
    """
    check_camera_name(camera, "--camera")
    check_import_settings(clip_len_s, fps, height, width, max_gap, wheelbase, steering_ratio)
    video = Path(video_path)
    info = video_info(video)
    num_frames = info.num_frames or count_intact_packets(video)  # some containers do not say
    source_t = np.arange(num_frames) / info.fps  # (n,) seconds
    keep = resample_indices(source_t, fps) if fps is not None else np.arange(num_frames)
    rate = fps or info.fps
    per_clip = len(keep) if clip_len_s is None else int(round(clip_len_s * rate))
    if per_clip < 1 or len(keep) < per_clip:
        raise ClipError(f"{video}: {len(keep)} frames at {rate:g} Hz, shorter than one clip of {clip_len_s} s")
    n_clips = len(keep) // per_clip
    if n_clips * per_clip < len(keep):
        dropped = len(keep) - n_clips * per_clip
        log.info("%s: dropping the last %d frames, shorter than a %g s clip", video, dropped, clip_len_s)
    plan = _resize_plan(info.width, info.height, height, width, resize_mode)
    chunks = keep[: n_clips * per_clip].reshape(n_clips, per_clip)
    actions, log_ = None, None
    if telemetry is not None:
        log_ = read_telemetry(telemetry, telemetry_offset)
        actions = actions_at(log_, source_t[chunks.reshape(-1)], max_gap, wheelbase, steering_ratio)
        actions = actions.reshape(n_clips, per_clip, 2)
    with tqdm(total=chunks.size, unit="frame", desc=video.name, disable=not progress) as bar:
        frames = _selected_frames(video, chunks.reshape(-1), plan, bar)
        paths = []
        for k, (cid, chunk) in enumerate(zip(_clip_ids(video.stem, clip_id, n_clips), chunks)):
            start = None if log_ is None else position_at(log_, float(source_t[chunk[0]]))
            path = _write_one(out_root, cid, islice(frames, per_clip), source_t[chunk], rate, camera, video, overwrite,
                              None if actions is None else actions[k], start)
            if path is None:
                break
            paths.append(path)
    log.info("%s: wrote %d clip(s) of %d frames to %s", video, len(paths), per_clip, out_root)
    return paths


def check_import_settings(clip_len_s: float | None, fps: float | None, height: int | None, width: int | None,
                          max_gap: float, wheelbase: float | None, steering_ratio: float) -> None:
    """Each option in its range (ValueError naming the option, the value and the range) before anything is read."""
    positive = {"--clip-seconds": clip_len_s, "--fps": fps, "--max-gap": max_gap, "--wheelbase": wheelbase,
                "--steering-ratio": steering_ratio}
    for option, value in positive.items():
        if value is not None and not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{option} {value!r}: expected a positive finite number")
    for option, value in {"--height": height, "--width": width}.items():
        if value is not None and not (isinstance(value, int) and 8 <= value <= 8192):
            raise ValueError(f"{option} {value!r}: expected an integer number of pixels in [8, 8192]")


class _Counted:
    """Wraps an iterator and counts what it yields."""

    def __init__(self, items: Iterator[np.ndarray]) -> None:
        self.items, self.count = items, 0

    def __iter__(self) -> Iterator[np.ndarray]:
        for item in self.items:
            self.count += 1
            yield item


def _write_one(out_root, clip_id: str, frames: Iterator[np.ndarray], timestamps: np.ndarray, rate: float,
               camera: str, video: Path, overwrite: bool, actions: np.ndarray | None = None,
               gps_start: list[float] | None = None) -> Path | None:
    """Write one clip; None (and nothing written) when the source ends before the clip is full."""
    with ClipFolderWriter(out_root, clip_id, overwrite=overwrite) as writer:
        counted = _Counted(frames)
        try:
            writer.write_video(camera, counted, rate)
        except ClipError:
            if counted.count:  # a real encoding problem, not an exhausted source
                raise
        if counted.count < len(timestamps):
            # A truncated source: keep what was complete, never pad the clip.
            log.warning("%s: decoding stopped early (truncated file?); clip '%s' not written", video, clip_id)
            writer.abort()
            return None
        writer.write_labels(label_rows(timestamps, actions))
        metadata = {"source_video": video.name, "source_start_s": float(timestamps[0])}
        if gps_start is not None:  # where the clip starts: geofenced validation splits (data.val_region)
            metadata["gps_start"] = gps_start
        writer.write_meta(meta_json(rate, None, [camera], metadata))
    return writer.target


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("video", help="input video file (anything OpenCV decodes: H.264, HEVC, MPEG-4, VP9)")
    parser.add_argument("--out", required=True, help="root folder of the clip folders")
    parser.add_argument("--clip-seconds", type=float, help="split into clips of this many seconds")
    parser.add_argument("--fps", type=float, help="keep this frame rate (Hz), picked by timestamps")
    parser.add_argument("--height", type=int, help="output height in pixels (with --width)")
    parser.add_argument("--width", type=int, help="output width in pixels (with --height)")
    parser.add_argument("--resize-mode", choices=("crop", "stretch"), default="crop")
    parser.add_argument("--camera", default="front", help="view name, the mp4's file name")
    parser.add_argument("--clip-id", help="clip folder name (default: the video's file stem)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing clip folders")
    parser.add_argument("--telemetry", help="CSV / JSONL log with t (s) and speed or lat/lon, curvature or yaw_rate or "
                                            "steering_angle: per-frame speed and curvature joined by time")
    parser.add_argument("--telemetry-offset", type=float, default=0.0,
                        help="the log's time at the video's first frame (s): video time = t - offset")
    parser.add_argument("--max-gap", type=float, default=0.5, help="longest gap between log samples around a frame (s)")
    parser.add_argument("--wheelbase", type=float, help="metres, for a steering_angle log")
    parser.add_argument("--steering-ratio", type=float, default=1.0,
                        help="steering-wheel to road-wheel angle ratio, for a steering_angle log")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    paths = import_dashcam(args.video, args.out, args.clip_seconds, args.camera, args.fps, args.height, args.width,
                           args.resize_mode, args.clip_id, args.overwrite, telemetry=args.telemetry,
                           telemetry_offset=args.telemetry_offset, max_gap=args.max_gap, wheelbase=args.wheelbase,
                           steering_ratio=args.steering_ratio)
    print("\n".join(str(p) for p in paths))


if __name__ == "__main__":
    main()
