"""Video files in and out: OpenCV decodes, PyAV (libx264) encodes (ECOSYSTEM.md §5).

OpenCV's wheel decodes H.264/HEVC but cannot encode them, and its mp4v output is rejected by
Rerun and browsers, so writing goes through PyAV's bundled libx264.

Frames are numpy arrays in RGB order: one video is (t, h, w, 3) uint8.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np

from gaia_app.data.clip import ClipError

X264_OPTIONS = {"crf": "23", "preset": "veryfast", "bf": "0"}
"""libx264 settings: visually clean at a small size, fast, and no B-frames so that decode order
equals display order (simple seeking, no reordering delay)."""


class VideoReadError(ClipError):
    """A video cannot be opened, decodes no frames, or decodes fewer frames than its container claims."""


class VideoWriteError(ClipError):
    """Frames cannot be written as an H.264 mp4 (bad shape, dtype or odd size)."""


@dataclass(frozen=True)
class VideoInfo:
    """What the container says, without decoding: frame count (0 when unknown), rate (Hz), size (pixels)."""

    num_frames: int
    fps: float
    width: int
    height: int
    codec: str


def _open(path: str | Path) -> cv2.VideoCapture:
    if not Path(path).is_file():
        raise VideoReadError(f"{path}: video file not found")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise VideoReadError(f"{path}: cannot open video (unreadable, truncated or unsupported container)")
    return cap


def _fourcc(cap: cv2.VideoCapture) -> str:
    code = int(cap.get(cv2.CAP_PROP_FOURCC))
    return "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4)).strip("\x00") or "?"


def video_info(path: str | Path) -> VideoInfo:
    """Frame count, fps and size from the container header (cheap: nothing is decoded)."""
    cap = _open(path)
    try:
        info = VideoInfo(
            num_frames=int(cap.get(cv2.CAP_PROP_FRAME_COUNT)),
            fps=float(cap.get(cv2.CAP_PROP_FPS)),
            width=int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            height=int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            codec=_fourcc(cap),
        )
    finally:
        cap.release()
    if info.fps <= 0:
        raise VideoReadError(f"{path}: container reports no frame rate ({info.fps})")
    # Some containers (raw streams, some mkv) carry no frame count; 0 means "unknown".
    return info if info.num_frames > 0 else replace(info, num_frames=0)


def count_intact_packets(path: str | Path) -> int:
    """Number of complete compressed frames stored in the file, found by demuxing without decoding.

    Cheap integrity check for a truncated file: its header may still claim every frame while the
    bytes of the last ones are gone; those packets come back empty or flagged corrupt. Reads the
    file once (milliseconds per MB), decodes nothing.
    """
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            return sum(1 for p in container.demux(stream) if p.size > 0 and not p.is_corrupt)
    except (av.error.FFmpegError, IndexError) as err:
        raise VideoReadError(f"{path}: cannot demux video: {err}") from None


def iter_frames(path: str | Path, start: int = 0) -> Iterator[np.ndarray]:
    """Decode frames in order from index `start` to the end of the file.

    Yields (h, w, 3) uint8 RGB. No count check: a caller that must know whether the file is
    complete uses `read_video` (or compares with `video_info`).
    """
    cap = _open(path)
    try:
        if start > 0:
            # OpenCV seeks to the previous keyframe and decodes forward, so the frame is exact.
            cap.set(cv2.CAP_PROP_POS_FRAMES, start)
        while True:
            ok, bgr = cap.read()
            if not ok:
                return
            yield cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    finally:
        cap.release()


def read_video(path: str | Path, start: int = 0, max_frames: int | None = None) -> tuple[np.ndarray, float]:
    """Decode frames [start, start + max_frames) of a video (all remaining ones when max_frames is None).

    Returns frames (t, h, w, 3) uint8 RGB and the container's frame rate (Hz). Raises
    VideoReadError naming the file when it cannot be opened, when no frame decodes, or when
    fewer frames decode than the container claims for the window (a truncated or corrupt file);
    missing frames are never filled in.
    """
    info = video_info(path)
    if start < 0 or (info.num_frames and start >= info.num_frames):
        raise VideoReadError(f"{path}: start frame {start} outside 0..{info.num_frames - 1}")
    claimed = info.num_frames - start if info.num_frames else None  # None: the container does not say
    limit = claimed if max_frames is None else (max_frames if claimed is None else min(max_frames, claimed))
    frames = []
    for frame in iter_frames(path, start):
        frames.append(frame)
        if len(frames) == limit:
            break
    if not frames:
        raise VideoReadError(f"{path}: decoded 0 frames (codec '{info.codec}'; OpenCV cannot decode e.g. AV1)")
    if claimed is not None and len(frames) < limit:
        raise VideoReadError(
            f"{path}: decoded {len(frames)} of the {limit} frames the container claims from frame {start} "
            "(truncated or corrupt file)"
        )
    return np.stack(frames), info.fps


def _check_frame(frame: np.ndarray, path: str | Path, index: int) -> np.ndarray:
    if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
        raise VideoWriteError(f"{path}: frame {index} must be uint8 (h, w, 3), got {frame.dtype} {frame.shape}")
    h, w = frame.shape[:2]
    if h % 2 or w % 2:
        # yuv420p stores colour at half resolution, so libx264 needs even sizes; padding would
        # silently change the image size and break the camera intrinsics, so refuse instead.
        raise VideoWriteError(f"{path}: frame size {w}x{h} must be even for H.264 yuv420p; resize or crop first")
    return np.ascontiguousarray(frame)


def write_video(path: str | Path, frames: np.ndarray | Iterable[np.ndarray], fps: float) -> Path:
    """Write RGB frames as an H.264 mp4 (libx264, yuv420p, crf 23, preset veryfast, no B-frames).

    frames: (t, h, w, 3) uint8 or an iterable of (h, w, 3) uint8 (streamed, so long videos need
    not fit in memory); width and height must be even (VideoWriteError otherwise). fps: Hz.
    The file is written beside `path` under a temporary name and renamed into place, so readers
    never see a half-written video. The moov index goes first (faststart), which also lets
    `count_intact_packets` detect a truncated file.
    """
    path = Path(path)
    if fps <= 0:
        raise VideoWriteError(f"{path}: fps must be positive, got {fps}")
    # A hidden name beside the target (same filesystem, so the rename is atomic); created by
    # FFmpeg itself, so it gets the usual permissions (mkstemp would make it owner-only).
    tmp = str(path.parent / f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        count = _encode(tmp, frames, fps, path)
        if count == 0:
            raise VideoWriteError(f"{path}: no frames to write")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return path


def _encode(tmp: str, frames: np.ndarray | Iterable[np.ndarray], fps: float, path: Path) -> int:
    """Encode frames into `tmp`; returns the number of frames written."""
    rate = Fraction(fps).limit_denominator(1001)  # 29.97 -> 30000/1001, 6.25 -> 25/4
    count = 0
    with av.open(tmp, "w", format="mp4", options={"movflags": "+faststart"}) as out:
        stream = None
        for count, frame in enumerate(frames, start=1):
            frame = _check_frame(frame, path, count - 1)
            if stream is None:
                stream = out.add_stream("libx264", rate=rate)
                stream.height, stream.width = frame.shape[:2]
                stream.pix_fmt = "yuv420p"
                stream.options = dict(X264_OPTIONS)
            elif frame.shape[:2] != (stream.height, stream.width):
                raise VideoWriteError(f"{path}: frame {count - 1} is {frame.shape[1]}x{frame.shape[0]}, "
                                      f"the first was {stream.width}x{stream.height}")
            out.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
        if stream is not None:
            out.mux(stream.encode())
    return count
