"""The synthetic camera rig: up to five pinhole cameras on the ego roof.

Frames (DESIGN.md §4): ego x forward, y left, z up, origin on the ground under the rear axle;
camera OpenCV x right, y down, z forward. `CameraSpec.extrinsics` maps camera → ego.
Adjacent default views overlap by about 15° so multi-view models see shared content.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gaia_app.data.clip import DEFAULT_CAMERA_NAMES, CameraSpec


@dataclass(frozen=True)
class CameraMount:
    """Where a camera sits and looks: yaw (deg, left positive), horizontal field of view (deg),
    position (x, y, z) in metres in the ego frame, pitch (deg, down positive)."""

    yaw_deg: float
    hfov_deg: float
    position: tuple[float, float, float]
    pitch_deg: float = 3.0


DEFAULT_MOUNTS: dict[str, CameraMount] = {
    "front": CameraMount(0.0, 70.0, (1.8, 0.0, 1.55)),
    "front_left": CameraMount(58.0, 80.0, (1.6, 0.5, 1.55)),
    "front_right": CameraMount(-58.0, 80.0, (1.6, -0.5, 1.55)),
    "rear_left": CameraMount(123.0, 80.0, (0.3, 0.6, 1.55)),
    "rear_right": CameraMount(-123.0, 80.0, (0.3, -0.6, 1.55)),
}

# Columns are the ego-frame directions of the camera axes (x right, y down, z forward) for a
# camera looking along ego +x.
_EGO_FROM_FORWARD_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def resolve_camera_names(cameras: int | Sequence[str]) -> list[str]:
    """Camera names from a count 1–5 (first k of DEFAULT_CAMERA_NAMES) or a list of names."""
    if isinstance(cameras, (int, np.integer)) and not isinstance(cameras, bool):
        if not 1 <= cameras <= len(DEFAULT_CAMERA_NAMES):
            raise ValueError(f"cameras: a count must be 1..{len(DEFAULT_CAMERA_NAMES)}, got {cameras}")
        return list(DEFAULT_CAMERA_NAMES[: int(cameras)])
    if isinstance(cameras, str) or not isinstance(cameras, Sequence):
        raise ValueError(f"cameras: expected an int 1..5 or a list of names from {DEFAULT_CAMERA_NAMES}, "
                         f"got {cameras!r}")
    names = [str(c) for c in cameras]
    unknown = [n for n in names if n not in DEFAULT_MOUNTS]
    if not names or unknown or len(set(names)) != len(names):
        raise ValueError(f"cameras: expected distinct names from {DEFAULT_CAMERA_NAMES}, got {names}")
    return names


def rotation_z(angle: float) -> np.ndarray:
    """(3, 3) rotation about +z by `angle` radians."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_y(angle: float) -> np.ndarray:
    """(3, 3) rotation about +y by `angle` radians (positive tilts +x towards -z)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def camera_spec(name: str, height: int, width: int, mount: CameraMount | None = None) -> CameraSpec:
    """A CameraSpec for `name` at (height, width) pixels; square pixels, principal point at the centre."""
    mount = mount or DEFAULT_MOUNTS[name]
    fx = 0.5 * width / np.tan(np.radians(mount.hfov_deg) / 2)
    intrinsics = np.array([[fx, 0.0, width / 2], [0.0, fx, height / 2], [0.0, 0.0, 1.0]])
    rotation = (rotation_z(np.radians(mount.yaw_deg)) @ rotation_y(np.radians(mount.pitch_deg))
                @ _EGO_FROM_FORWARD_CAMERA)
    extrinsics = np.eye(4)
    extrinsics[:3, :3] = rotation
    extrinsics[:3, 3] = mount.position
    return CameraSpec(name, intrinsics, extrinsics, width, height)


def build_rig(cameras: int | Sequence[str], height: int, width: int) -> list[CameraSpec]:
    """The rig for `cameras` (count or names) at (height, width) pixels."""
    return [camera_spec(name, height, width) for name in resolve_camera_names(cameras)]


def camera_from_ego(camera: CameraSpec) -> np.ndarray:
    """(4, 4) transform mapping ego-frame points into the camera frame."""
    return np.linalg.inv(camera.extrinsics)


def project_points(camera: CameraSpec, points_ego: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project (n, 3) ego-frame points: returns (n, 2) pixel coordinates and (n,) depth in metres
    (points with depth <= 0 are behind the camera and their pixels are meaningless)."""
    cam = (camera_from_ego(camera) @ np.c_[points_ego, np.ones(len(points_ego))].T)[:3].T
    depth = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (camera.intrinsics @ cam.T).T[:, :2] / depth[:, None]
    return uv, depth
