"""The `Clip`: one training example before batching (DESIGN.md §4).

Legend (einops):
    v  cameras (views), 1 for a single dashcam
    t  time steps (frames)
    c  colour channels (3, RGB)
    h w  image height and width in pixels
    n  agents in one frame

Absent labels are `None`, never zeros pretending to be data.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

AGENT_CATEGORIES: tuple[str, ...] = ("car", "bus", "truck", "cyclist", "pedestrian")
"""Agent category ids are indices into this tuple."""

DEFAULT_CAMERA_NAMES: tuple[str, ...] = ("front", "front_left", "front_right", "rear_left", "rear_right")


class ClipError(ValueError):
    """Raised when a clip, its files or its labels break the data contract; the message names the culprit."""


@dataclass
class CameraSpec:
    """A pinhole camera of the rig.

    intrinsics: (3, 3) float, pixels; extrinsics: (4, 4) float, camera→ego transform with the
    camera frame in OpenCV convention (x right, y down, z forward) and the ego frame x forward,
    y left, z up.
    """

    name: str
    intrinsics: np.ndarray
    extrinsics: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        self.intrinsics = np.asarray(self.intrinsics, dtype=np.float64)
        self.extrinsics = np.asarray(self.extrinsics, dtype=np.float64)
        if self.intrinsics.shape != (3, 3):
            raise ClipError(f"camera '{self.name}': intrinsics must be 3x3, got {self.intrinsics.shape}")
        if self.extrinsics.shape != (4, 4):
            raise ClipError(f"camera '{self.name}': extrinsics must be 4x4, got {self.extrinsics.shape}")

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "intrinsics": self.intrinsics.tolist(),
            "extrinsics": self.extrinsics.tolist(),
            "width": int(self.width),
            "height": int(self.height),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "CameraSpec":
        return cls(d["name"], d["intrinsics"], d["extrinsics"], int(d["width"]), int(d["height"]))

    def resized(self, width: int, height: int) -> "CameraSpec":
        """The same camera after scaling its image to (width, height)."""
        k = self.intrinsics.copy()
        k[0] *= width / self.width
        k[1] *= height / self.height
        return replace(self, intrinsics=k, width=width, height=height)


@dataclass
class AgentBoxes:
    """Agents of one frame as 3D boxes in the ego frame.

    centre: (n, 3) metres; size: (n, 3) length, width, height in metres; yaw: (n,) radians about
    ego z; category: (n,) int index into AGENT_CATEGORIES; track_id: (n,) int, stable over time.
    """

    centre: np.ndarray
    size: np.ndarray
    yaw: np.ndarray
    category: np.ndarray
    track_id: np.ndarray

    def __post_init__(self) -> None:
        self.centre = np.asarray(self.centre, dtype=np.float32).reshape(-1, 3)
        self.size = np.asarray(self.size, dtype=np.float32).reshape(-1, 3)
        self.yaw = np.asarray(self.yaw, dtype=np.float32).reshape(-1)
        self.category = np.asarray(self.category, dtype=np.int64).reshape(-1)
        self.track_id = np.asarray(self.track_id, dtype=np.int64).reshape(-1)
        n = len(self.centre)
        for name in ("size", "yaw", "category", "track_id"):
            if len(getattr(self, name)) != n:
                raise ClipError(f"agents: '{name}' has {len(getattr(self, name))} entries, centre has {n}")

    def __len__(self) -> int:
        return len(self.centre)

    @classmethod
    def empty(cls) -> "AgentBoxes":
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0))

    def to_json(self) -> list[dict[str, Any]]:
        return [
            {
                "centre": self.centre[i].tolist(),
                "size": self.size[i].tolist(),
                "yaw": float(self.yaw[i]),
                "category": AGENT_CATEGORIES[int(self.category[i])],
                "track_id": int(self.track_id[i]),
            }
            for i in range(len(self))
        ]

    @classmethod
    def from_json(cls, items: list[dict[str, Any]], where: str = "agents") -> "AgentBoxes":
        if not items:
            return cls.empty()
        try:
            category = [_category_id(a["category"], where) for a in items]
            return cls(
                [a["centre"] for a in items],
                [a["size"] for a in items],
                [a["yaw"] for a in items],
                category,
                [a["track_id"] for a in items],
            )
        except KeyError as err:
            raise ClipError(f"{where}: an agent is missing field {err}") from None


def _category_id(category: str | int, where: str) -> int:
    if isinstance(category, int):
        if not 0 <= category < len(AGENT_CATEGORIES):
            raise ClipError(f"{where}: category id {category} outside 0..{len(AGENT_CATEGORIES) - 1}")
        return category
    if category not in AGENT_CATEGORIES:
        raise ClipError(f"{where}: unknown agent category '{category}', expected one of {AGENT_CATEGORIES}")
    return AGENT_CATEGORIES.index(category)


@dataclass
class Clip:
    """One example: multi-camera frames with every condition GAIA-1/2 use.

    frames: (v, t, c, h, w) uint8 RGB; timestamps: (t,) float64 seconds; actions: (t, 2) float32
    (speed m/s, curvature 1/m) or None; text: t captions (None entries allowed) or None;
    agents: t AgentBoxes or None; cameras: v CameraSpec or None; meta: clip-level metadata
    (weather, time_of_day, country, ...); frame_meta: t dicts of per-frame metadata
    (traffic_light, ...) or None.
    """

    clip_id: str
    frames: np.ndarray
    timestamps: np.ndarray
    actions: np.ndarray | None = None
    text: list[str | None] | None = None
    agents: list[AgentBoxes] | None = None
    cameras: list[CameraSpec] | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    frame_meta: list[dict[str, Any]] | None = None

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64)
        if self.actions is not None:
            self.actions = np.asarray(self.actions, dtype=np.float32)
        self.validate()

    @property
    def num_views(self) -> int:
        return int(self.frames.shape[0])

    @property
    def num_frames(self) -> int:
        return int(self.frames.shape[1])

    @property
    def fps(self) -> float:
        """Mean frame rate from the timestamps (0 for a single frame)."""
        if self.num_frames < 2:
            return 0.0
        return float((self.num_frames - 1) / (self.timestamps[-1] - self.timestamps[0]))

    def validate(self) -> None:
        """Check every field against the frame count; raise ClipError naming the field."""
        f = self.frames
        if f.ndim != 5 or f.shape[2] != 3 or f.dtype != np.uint8:
            raise ClipError(f"clip '{self.clip_id}': frames must be uint8 (v, t, 3, h, w), got {f.dtype} {f.shape}")
        t = self.num_frames
        if self.timestamps.shape != (t,):
            raise ClipError(f"clip '{self.clip_id}': timestamps shape {self.timestamps.shape}, expected ({t},)")
        if t > 1 and not np.all(np.diff(self.timestamps) > 0):
            raise ClipError(f"clip '{self.clip_id}': timestamps must be strictly increasing")
        if self.actions is not None and self.actions.shape != (t, 2):
            raise ClipError(f"clip '{self.clip_id}': actions shape {self.actions.shape}, expected ({t}, 2)")
        for name in ("text", "agents", "frame_meta"):
            value = getattr(self, name)
            if value is not None and len(value) != t:
                raise ClipError(f"clip '{self.clip_id}': {name} has {len(value)} entries for {t} frames")
        if self.cameras is not None and len(self.cameras) != self.num_views:
            raise ClipError(f"clip '{self.clip_id}': {len(self.cameras)} cameras for {self.num_views} views")

    def select_frames(self, index: np.ndarray | list[int]) -> "Clip":
        """A clip holding only the frames at `index` (e.g. a temporal window or a resampling)."""
        idx = np.asarray(index, dtype=np.int64)

        def pick(seq: Any) -> list | None:
            return None if seq is None else [seq[i] for i in idx]

        return replace(
            self,
            frames=self.frames[:, idx],
            timestamps=self.timestamps[idx],
            actions=None if self.actions is None else self.actions[idx],
            text=pick(self.text),
            agents=pick(self.agents),
            frame_meta=pick(self.frame_meta),
        )

    def select_views(self, names: list[str]) -> "Clip":
        """A clip holding only the named cameras, in the given order."""
        if self.cameras is None:
            raise ClipError(f"clip '{self.clip_id}': cannot select views by name without camera specs")
        have = [c.name for c in self.cameras]
        missing = [n for n in names if n not in have]
        if missing:
            raise ClipError(f"clip '{self.clip_id}': cameras {missing} not in {have}")
        idx = [have.index(n) for n in names]
        return replace(self, frames=self.frames[idx], cameras=[self.cameras[i] for i in idx])
