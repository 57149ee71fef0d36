"""Writing clip folders (format in `clip_folder.py` and docs/data.md): atomic, never overwriting by accident."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from gaia_app.data.clip import AgentBoxes, CameraSpec, Clip, ClipError
from gaia_app.data.clip_folder import CAMERA_NAMES_KEY, LABELS_FILE, META_FILE, RESERVED_LABEL_KEYS, VIDEO_SUFFIX
from gaia_app.data.names import check_camera_name, check_clip_id
from gaia_app.data.video_io import write_video


def _json_default(value: Any) -> Any:
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def view_names(clip: Clip) -> list[str]:
    """Names of the clip's views: from its camera specs, else Clip.meta['camera_names'], else front/view<i>."""
    if clip.cameras is not None:
        return [c.name for c in clip.cameras]
    names = clip.meta.get(CAMERA_NAMES_KEY)
    if names is not None:
        if len(names) != clip.num_views:
            raise ClipError(
                f"clip '{clip.clip_id}': meta '{CAMERA_NAMES_KEY}' has {len(names)} names for {clip.num_views} views"
            )
        return list(names)
    return ["front"] if clip.num_views == 1 else [f"view{i}" for i in range(clip.num_views)]


def label_rows(
    timestamps: np.ndarray,
    actions: np.ndarray | None = None,
    text: list[str | None] | None = None,
    agents: list[AgentBoxes] | None = None,
    frame_meta: list[dict[str, Any]] | None = None,
) -> list[dict[str, Any]]:
    """labels.jsonl objects, one per frame: t (s), speed (m/s), curvature (1/m), text, agents, frame_meta keys.

    timestamps: (t,) seconds; actions: (t, 2); the lists have t entries. Absent fields stay absent.
    """
    rows = []
    for i, t in enumerate(np.asarray(timestamps, dtype=np.float64)):
        row: dict[str, Any] = {"t": float(t)}
        if actions is not None:
            row["speed"], row["curvature"] = (float(a) for a in actions[i])
        if text is not None:
            row["text"] = text[i]
        if agents is not None:
            row["agents"] = agents[i].to_json()
        extra = (frame_meta[i] if frame_meta is not None else None) or {}
        clash = RESERVED_LABEL_KEYS & extra.keys()
        if clash:
            raise ClipError(f"frame_meta[{i}] uses reserved label keys {sorted(clash)}")
        row.update(extra)
        rows.append(row)
    return rows


def meta_json(
    fps: float,
    cameras: list[CameraSpec] | None,
    names: list[str],
    metadata: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The meta.json object: fps (Hz), cameras (specs or null), camera_names (view order), metadata."""
    if cameras is not None and [c.name for c in cameras] != list(names):
        raise ClipError(f"camera names {list(names)} differ from the camera specs {[c.name for c in cameras]}")
    return {
        "fps": float(fps),
        "cameras": None if cameras is None else [c.to_json() for c in cameras],
        CAMERA_NAMES_KEY: list(names),
        "metadata": {k: v for k, v in (metadata or {}).items() if k != CAMERA_NAMES_KEY},
    }


class ClipFolderWriter:
    """Writes one clip folder atomically.

    Files go into a hidden temporary folder beside the target (`<root>/.<clip_id>.tmp-*`, which
    the Dataset ignores) and the folder is renamed into place on a clean exit; on an exception it
    is removed, as after `abort()`. An existing clip is refused unless overwrite=True.

    >>> with ClipFolderWriter(root, "drive_0001") as w:
    ...     w.write_video("front", frames, fps); w.write_labels(rows); w.write_meta(meta)
    """

    def __init__(self, root: str | Path, clip_id: str, *, overwrite: bool = False) -> None:
        check_clip_id(clip_id, f"clip folder under {root}")
        self.root = Path(root)
        self.target = self.root / clip_id
        self.overwrite = overwrite
        self.tmp: Path | None = None
        self.aborted = False

    def __enter__(self) -> "ClipFolderWriter":
        self._refuse_existing()
        self.root.mkdir(parents=True, exist_ok=True)
        # mkdir (not mkdtemp, which is owner-only) so the clip gets the usual permissions.
        self.tmp = self.root / f".{self.target.name}.tmp-{uuid.uuid4().hex[:8]}"
        self.tmp.mkdir()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None and not self.aborted:
                self._commit()
        finally:
            if self.tmp is not None and self.tmp.exists():
                shutil.rmtree(self.tmp)

    def abort(self) -> None:
        """Discard everything written so far; nothing is committed on exit."""
        self.aborted = True

    def _refuse_existing(self) -> None:
        if self.target.exists() and not self.overwrite:
            raise ClipError(f"{self.target}: clip already exists; pass overwrite=True (--overwrite) to replace it")

    def _commit(self) -> None:
        for name in (META_FILE, LABELS_FILE):
            if not (self.tmp / name).is_file():
                raise ClipError(f"{self.target}: {name} was never written")
        self._refuse_existing()  # again: another writer may have created it meanwhile
        if self.target.exists():
            # os.replace cannot replace a non-empty folder: move the old one aside first.
            old = Path(tempfile.mkdtemp(dir=self.root, prefix=f".{self.target.name}.old-"))
            os.replace(self.target, old / "clip")
            os.replace(self.tmp, self.target)
            shutil.rmtree(old)
        else:
            os.replace(self.tmp, self.target)

    def write_video(self, camera: str, frames, fps: float) -> Path:
        """Encode frames (t, h, w, 3) uint8 RGB, or an iterable of (h, w, 3), as `<camera>.mp4`."""
        return write_video(self.video_path(camera), frames, fps)

    def copy_video(self, camera: str, source: str | Path) -> Path:
        """Copy an existing H.264 mp4 unchanged as `<camera>.mp4` (no re-encoding loss)."""
        return Path(shutil.copyfile(source, self.video_path(camera)))

    def video_path(self, camera: str) -> Path:
        """`<camera>.mp4` in the clip being written; the camera name must be plain (data/names.py)."""
        return self.tmp / f"{check_camera_name(camera, f'clip {self.target.name}')}{VIDEO_SUFFIX}"

    def write_labels(self, rows: list[dict[str, Any]]) -> None:
        """Write labels.jsonl, one JSON object per frame."""
        try:
            lines = [json.dumps(r, default=_json_default, allow_nan=False) for r in rows]
        except (TypeError, ValueError) as err:
            raise ClipError(f"{self.target / LABELS_FILE}: cannot encode labels as JSON: {err}") from None
        (self.tmp / LABELS_FILE).write_text("\n".join(lines) + "\n")

    def write_meta(self, meta: dict[str, Any]) -> None:
        """Write meta.json (see `meta_json` for the fields)."""
        try:
            text = json.dumps(meta, default=_json_default, allow_nan=False, indent=1)
        except (TypeError, ValueError) as err:
            raise ClipError(f"{self.target / META_FILE}: cannot encode metadata as JSON: {err}") from None
        (self.tmp / META_FILE).write_text(text + "\n")


def write_clip(clip: Clip, root: str | Path, *, overwrite: bool = False) -> Path:
    """Write `clip` as `<root>/<clip.clip_id>/` atomically; returns that folder.

    Raises ClipError if the clip exists and overwrite is False. Frames are re-encoded with H.264
    (lossy: expect a mean absolute error of a few grey levels); labels and metadata are exact.
    """
    names = view_names(clip)
    # A one-frame clip has no measurable rate; 1 Hz keeps the mp4 valid and claims nothing.
    fps = clip.fps or 1.0
    try:
        rows = label_rows(clip.timestamps, clip.actions, clip.text, clip.agents, clip.frame_meta)
    except ClipError as err:
        raise ClipError(f"clip '{clip.clip_id}': {err}") from None
    with ClipFolderWriter(root, clip.clip_id, overwrite=overwrite) as writer:
        for name, view in zip(names, clip.frames):
            writer.write_video(name, view.transpose(0, 2, 3, 1), fps)  # (t, 3, h, w) -> (t, h, w, 3)
        writer.write_labels(rows)
        writer.write_meta(meta_json(fps, clip.cameras, names, clip.meta))
    return writer.target
