"""The on-disk clip folder (DESIGN.md §4): validated reading and a Dataset over a root of them.

```
<root>/<clip_id>/<camera>.mp4    one per camera, same frame count and rate (H.264)
<root>/<clip_id>/labels.jsonl    one JSON object per frame: t, speed, curvature, text?, agents?, extra keys
<root>/<clip_id>/meta.json       fps, cameras (name, intrinsics, extrinsics, width, height), metadata
```
`docs/data.md` is the user's description of the format. Readers validate and raise ClipError
naming the file, line and field; the Dataset reports and counts the clips it skips.
Writing lives in `clip_writer.py`.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gaia_app.data.actions import ACTION_COLUMNS, actions_from_labels
from gaia_app.data.clip import AgentBoxes, CameraSpec, Clip, ClipError
from gaia_app.data.names import check_camera_name
from gaia_app.data.transforms import resample_indices
from gaia_app.data.video_io import VideoReadError, count_intact_packets, read_video, video_info

log = logging.getLogger(__name__)

META_FILE = "meta.json"
LABELS_FILE = "labels.jsonl"
VIDEO_SUFFIX = ".mp4"
RESERVED_LABEL_KEYS = frozenset({"t", "text", "agents", *ACTION_COLUMNS})
"""Label keys with a meaning; every other key of a labels line is per-frame metadata (Clip.frame_meta)."""
CAMERA_NAMES_KEY = "camera_names"
"""Clip.meta key that names the views of a clip without camera specs (e.g. a plain dashcam)."""
FPS_TOLERANCE = 0.1
"""Relative mismatch allowed between meta.json fps and the rate of the label timestamps."""


# ---------------------------------------------------------------- reading


@dataclass
class _Labels:
    """Parsed labels.jsonl: timestamps (t,) s; actions (t, 2) or None; text, agents, frame_meta or None."""

    timestamps: np.ndarray
    actions: np.ndarray | None
    text: list[str | None] | None
    agents: list[AgentBoxes] | None
    frame_meta: list[dict[str, Any]] | None


@dataclass
class _Layout:
    """A clip folder's validated metadata and labels, before any video is decoded."""

    clip_dir: Path
    names: list[str]
    cameras: list[CameraSpec] | None
    videos: list[Path]
    metadata: dict[str, Any]
    labels: _Labels


def _read_text(path: Path) -> str:
    if not path.is_file():
        raise ClipError(f"{path}: missing")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise ClipError(f"{path}: not UTF-8 text (byte {err.start})") from None


def _load_json(path: Path) -> Any:
    try:
        return json.loads(_read_text(path))
    except json.JSONDecodeError as err:
        raise ClipError(f"{path}: invalid JSON at line {err.lineno}: {err.msg}") from None


def _read_label_lines(path: Path) -> list[tuple[int, dict[str, Any]]]:
    """(line number, object) for each non-blank line of labels.jsonl."""
    rows = []
    for number, line in enumerate(_read_text(path).splitlines(), start=1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as err:
            raise ClipError(f"{path} line {number}: invalid JSON: {err.msg}") from None
        if not isinstance(row, dict):
            raise ClipError(f"{path} line {number}: expected a JSON object, got {type(row).__name__}")
        rows.append((number, row))
    if not rows:
        raise ClipError(f"{path}: no labels (expected one JSON object per frame)")
    return rows


def _column(rows: list[tuple[int, dict]], name: str, path: Path, required: bool = False) -> np.ndarray | None:
    """Numeric column `name` (t,) float64; None if no line has it; ClipError naming the first line lacking it."""
    present = [r.get(name) is not None for _, r in rows]
    if not any(present) and not required:
        return None
    if not all(present):
        number = rows[present.index(False)][0]
        other = " (other lines have it)" if any(present) else ""
        raise ClipError(f"{path} line {number}: missing field '{name}'{other}")
    values = []
    for number, row in rows:
        value = row[name]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ClipError(f"{path} line {number}: field '{name}' must be a finite number, got {value!r}")
        values.append(value)
    return np.asarray(values, dtype=np.float64)


def _text_column(rows: list[tuple[int, dict]], path: Path) -> list[str | None] | None:
    if not any("text" in r for _, r in rows):
        return None
    for number, row in rows:
        if not isinstance(row.get("text"), (str, type(None))):
            raise ClipError(f"{path} line {number}: field 'text' must be a string or null, got {row['text']!r}")
    return [row.get("text") for _, row in rows]


def _agents_column(rows: list[tuple[int, dict]], path: Path) -> list[AgentBoxes] | None:
    present = ["agents" in r for _, r in rows]
    if not any(present):
        return None
    if not all(present):
        # A frame without the key is unlabelled, not empty; an empty list says "no agents".
        raise ClipError(f"{path} line {rows[present.index(False)][0]}: missing field 'agents' (other lines have it)")
    out = []
    for number, row in rows:
        if not isinstance(row["agents"], list):
            raise ClipError(f"{path} line {number}: field 'agents' must be a list")
        where = f"{path} line {number}: field 'agents'"
        try:
            out.append(AgentBoxes.from_json(row["agents"], where=where))
        except ClipError:
            raise
        except (TypeError, ValueError, AttributeError) as err:  # wrong shapes or types inside a box
            raise ClipError(f"{where}: {err}") from None
    return out


def _parse_labels(path: Path, vehicle: dict[str, Any]) -> _Labels:
    rows = _read_label_lines(path)
    t = _column(rows, "t", path, required=True)
    step = np.diff(t)
    if np.any(step <= 0):
        number = rows[int(np.argmax(step <= 0)) + 1][0]
        raise ClipError(f"{path} line {number}: field 't' must increase strictly (seconds)")
    columns = {name: _column(rows, name, path) for name in ACTION_COLUMNS}
    actions = None
    if any(c is not None for c in columns.values()):
        try:
            actions = actions_from_labels(
                columns, t, wheelbase=vehicle.get("wheelbase"), steering_ratio=vehicle.get("steering_ratio", 1.0),
                where=str(path),
            )
        except ClipError:
            raise
        except ValueError as err:  # e.g. too few poses to differentiate, a non-positive wheelbase
            raise ClipError(f"{path}: cannot build actions: {err}") from None
    extras = [{k: v for k, v in r.items() if k not in RESERVED_LABEL_KEYS} for _, r in rows]
    return _Labels(t, actions, _text_column(rows, path), _agents_column(rows, path), extras if any(extras) else None)


def _cameras_from_meta(meta: dict[str, Any], path: Path) -> list[CameraSpec] | None:
    specs = meta.get("cameras")
    if not specs:
        return None
    if not isinstance(specs, list):
        raise ClipError(f"{path}: field 'cameras' must be a list")
    cameras = []
    for i, spec in enumerate(specs):
        try:
            cameras.append(CameraSpec.from_json(spec))
        except KeyError as err:
            raise ClipError(f"{path}: cameras[{i}] is missing field {err}") from None
        except (TypeError, ValueError) as err:
            raise ClipError(f"{path}: cameras[{i}]: {err}") from None
    return cameras


def _view_names_on_disk(clip_dir: Path, meta: dict[str, Any], cameras: list[CameraSpec] | None) -> list[str]:
    """Camera names, each a plain name (data/names.py): they pick `<camera>.mp4` here and name output files later."""
    meta_path = clip_dir / META_FILE
    if cameras is not None:
        return [check_camera_name(c.name, f"{meta_path}: cameras[{i}].name") for i, c in enumerate(cameras)]
    names = meta.get(CAMERA_NAMES_KEY)
    if names:
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise ClipError(f"{meta_path}: field '{CAMERA_NAMES_KEY}' must be a list of names")
        return [check_camera_name(n, f"{meta_path}: {CAMERA_NAMES_KEY}[{i}]") for i, n in enumerate(names)]
    # A plain folder without camera entries: each mp4's stem names its view.
    names = sorted(p.stem for p in clip_dir.glob(f"*{VIDEO_SUFFIX}") if not p.name.startswith("."))
    if not names:
        raise ClipError(f"{clip_dir}: no {VIDEO_SUFFIX} video")
    return [check_camera_name(n, f"{clip_dir / (n + VIDEO_SUFFIX)}") for n in names]


def check_no_escaping_links(clip_dir: Path) -> None:
    """Refuse a clip folder holding a symbolic link whose target lies outside it: reading (or sharding) the clip
    would read, and pack, whatever file it points to."""
    root = clip_dir.resolve()
    for path in clip_dir.rglob("*"):
        if path.is_symlink():
            target = path.resolve()
            if target != root and root not in target.parents:
                raise ClipError(f"{path}: a symbolic link to {target}, outside its clip folder; copy the file into "
                                "the folder instead")


def _check_fps(meta: dict[str, Any], meta_path: Path, labels: _Labels, labels_path: Path) -> None:
    fps = meta.get("fps")
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
        raise ClipError(f"{meta_path}: field 'fps' must be a positive finite number, got {fps!r}")
    if len(labels.timestamps) > 1:
        rate = 1.0 / float(np.median(np.diff(labels.timestamps)))
        if abs(rate - fps) > FPS_TOLERANCE * fps:
            raise ClipError(f"{labels_path}: field 't' runs at {rate:.4g} Hz but {meta_path.name} says fps {fps:g} "
                            "(t must be in seconds)")


def _load_layout(clip_dir: str | Path, cameras: list[str] | None) -> _Layout:
    clip_dir = Path(clip_dir)
    if not clip_dir.is_dir():
        raise ClipError(f"{clip_dir}: clip folder not found")
    meta_path, labels_path = clip_dir / META_FILE, clip_dir / LABELS_FILE
    check_no_escaping_links(clip_dir)
    meta = _load_json(meta_path)
    if not isinstance(meta, dict):
        raise ClipError(f"{meta_path}: expected a JSON object")
    specs = _cameras_from_meta(meta, meta_path)
    labels = _parse_labels(labels_path, meta.get("vehicle") or {})
    _check_fps(meta, meta_path, labels, labels_path)
    names = _view_names_on_disk(clip_dir, meta, specs)
    if cameras is not None:
        cameras = [check_camera_name(c, f"{clip_dir}: data cameras[{i}]") for i, c in enumerate(cameras)]
        missing = [c for c in cameras if c not in names]
        if missing:
            raise ClipError(f"{clip_dir}: cameras {missing} not in {names}")
        keep = [names.index(c) for c in cameras]
        names, specs = list(cameras), None if specs is None else [specs[i] for i in keep]
    videos = [clip_dir / f"{n}{VIDEO_SUFFIX}" for n in names]
    for video in videos:
        if not video.is_file():
            raise ClipError(f"{video}: camera video missing (listed in {meta_path.name})")
    metadata = dict(meta.get("metadata") or {})
    if specs is None:
        metadata[CAMERA_NAMES_KEY] = names
    return _Layout(clip_dir, names, specs, videos, metadata, labels)


def _check_counts(layout: _Layout, counts: list[int]) -> int:
    """All cameras and the labels agree on the frame count; returns it."""
    for name, count in zip(layout.names[1:], counts[1:]):
        if count != counts[0]:
            raise ClipError(f"{layout.clip_dir}: camera '{layout.names[0]}' has {counts[0]} frames "
                            f"but camera '{name}' has {count}")
    n_labels = len(layout.labels.timestamps)
    if n_labels != counts[0]:
        raise ClipError(f"{layout.clip_dir / LABELS_FILE}: {n_labels} label lines for {counts[0]} video frames")
    return counts[0]


def _check_sizes(layout: _Layout, sizes: list[tuple[int, int]]) -> None:
    """All views share one (width, height), which matches their camera specs."""
    for name, size in zip(layout.names, sizes):
        if size != sizes[0]:
            raise ClipError(f"{layout.clip_dir}: camera '{name}' is {size[0]}x{size[1]} but "
                            f"'{layout.names[0]}' is {sizes[0][0]}x{sizes[0][1]}; views must share one size")
    for cam, size in zip(layout.cameras or [], sizes):
        if (cam.width, cam.height) != size:
            raise ClipError(f"{layout.clip_dir / META_FILE}: camera '{cam.name}' width/height "
                            f"{cam.width}x{cam.height} but its video is {size[0]}x{size[1]}")


def inspect_clip(clip_dir: str | Path, cameras: list[str] | None = None) -> int:
    """Validate a clip folder without decoding video; returns its frame count.

    Checks meta.json, every labels.jsonl line, each camera's frame count and size from the mp4
    header, and that each mp4 stores every frame it claims (demuxed, not decoded), so a
    truncated file is caught here. Raises ClipError (VideoReadError for video) naming the file.
    """
    return _inspect(clip_dir, cameras)[0]


def _inspect(clip_dir: str | Path, cameras: list[str] | None) -> tuple[int, np.ndarray]:
    """`inspect_clip`'s checks → (frame count, (t,) timestamps in seconds)."""
    layout = _load_layout(clip_dir, cameras)
    infos = [video_info(v) for v in layout.videos]
    for video, info in zip(layout.videos, infos):
        stored = count_intact_packets(video)
        if stored < info.num_frames:
            raise VideoReadError(f"{video}: only {stored} of the {info.num_frames} frames its header claims "
                                 "are stored (truncated file)")
    _check_sizes(layout, [(i.width, i.height) for i in infos])
    return _check_counts(layout, [i.num_frames for i in infos]), layout.labels.timestamps


def read_clip(
    clip_dir: str | Path,
    cameras: list[str] | None = None,
    start: int = 0,
    max_frames: int | None = None,
) -> Clip:
    """Read and validate a clip folder into a Clip (frames (v, t, 3, h, w) uint8).

    cameras: names of the views to load, in order (default: all, as listed in meta.json).
    start, max_frames: decode only frames [start, start + max_frames) (clipped at the end), with
    their labels; decoding a window costs about as much as decoding from the keyframe before it.
    Raises ClipError naming the file, line and field for any contract break.
    """
    layout = _load_layout(clip_dir, cameras)
    infos = [video_info(v) for v in layout.videos]
    _check_sizes(layout, [(i.width, i.height) for i in infos])
    total = _check_counts(layout, [i.num_frames for i in infos])  # cheap header check before decoding
    if not 0 <= start < total:
        raise ClipError(f"{layout.clip_dir}: start frame {start} outside 0..{total - 1}")
    views = [read_video(v, start, max_frames)[0] for v in layout.videos]
    window = slice(start, start + len(views[0]))
    for name, view in zip(layout.names, views):
        if len(view) != len(views[0]):
            raise ClipError(f"{layout.clip_dir}: camera '{layout.names[0]}' decoded {len(views[0])} frames "
                            f"but camera '{name}' decoded {len(view)}")
    labels = layout.labels

    def pick(seq: Any) -> Any:
        return None if seq is None else seq[window]

    return Clip(
        clip_id=layout.clip_dir.name,
        frames=np.stack(views).transpose(0, 1, 4, 2, 3),  # (v, t, h, w, 3) -> (v, t, 3, h, w)
        timestamps=labels.timestamps[window],
        actions=pick(labels.actions),
        text=pick(labels.text),
        agents=pick(labels.agents),
        cameras=layout.cameras,
        meta=layout.metadata,
        frame_meta=pick(labels.frame_meta),
    )


# ---------------------------------------------------------------- dataset


class ClipFolderDataset(torch.utils.data.Dataset):
    """Every valid clip folder under `root`, in sorted order; item i is a Clip.

    Clips that fail validation (see `inspect_clip`), lack a requested camera or have fewer than
    `min_frames` frames are skipped, listed in `skipped` as (clip_id, reason) and reported in one
    warning. Raises ClipError naming root when no clip is usable.
    """

    def __init__(self, root: str | Path, min_frames: int = 1, cameras: list[str] | None = None) -> None:
        self.root = Path(root)
        self.min_frames = min_frames
        self.cameras = None if cameras is None else list(cameras)
        self.clip_ids: list[str] = []
        self.num_frames: list[int] = []
        self.timestamps: list[np.ndarray] = []
        self.skipped: list[tuple[str, str]] = []
        self._scan()

    def _scan(self) -> None:
        if not self.root.is_dir():
            raise ClipError(f"{self.root}: clip root folder not found")
        # Hidden folders are in-progress atomic writes (ClipFolderWriter) or not clips at all.
        for clip_dir in sorted(p for p in self.root.iterdir() if p.is_dir() and not p.name.startswith(".")):
            try:
                n, timestamps = _inspect(clip_dir, self.cameras)
            except (ClipError, OSError) as err:
                self.skipped.append((clip_dir.name, str(err)))
                continue
            if n < self.min_frames:
                self.skipped.append((clip_dir.name, f"{n} frames, fewer than min_frames={self.min_frames}"))
                continue
            self.clip_ids.append(clip_dir.name)
            self.num_frames.append(n)
            self.timestamps.append(timestamps)
        self._report()

    def _report(self) -> None:
        first = "; ".join(f"{cid}: {why}" for cid, why in self.skipped[:3])
        if not self.clip_ids:
            reasons = f": {first}" if first else ""
            raise ClipError(f"{self.root}: no usable clip folder ({len(self.skipped)} skipped){reasons}")
        if self.skipped:
            log.warning("%s: skipped %d of %d clip folders: %s%s", self.root, len(self.skipped),
                        len(self.skipped) + len(self.clip_ids), first, "; ..." if len(self.skipped) > 3 else "")

    def __len__(self) -> int:
        return len(self.clip_ids)

    def __getitem__(self, index: int) -> Clip:
        return read_clip(self.root / self.clip_ids[index], self.cameras)

    def describe(self, index: int) -> dict[str, Any]:
        """Clip-level metadata of clip `index` (meta.json "metadata", e.g. source_video, run_id, gps_start), read
        without decoding any video: for splits by run or place."""
        meta = json.loads((self.root / self.clip_ids[index] / META_FILE).read_text())
        return dict(meta.get("metadata") or {})

    def steps_at(self, index: int, fps: float | None) -> int:
        """Frames of clip `index` after resampling to `fps` (None: its own rate), from its labels alone."""
        timestamps = self.timestamps[index]
        return len(timestamps) if fps is None else len(resample_indices(timestamps, fps))
