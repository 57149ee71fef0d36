"""Ego actions (speed, curvature) from the signals users actually have. Pure, vectorised numpy.

GAIA-1/2 condition on actions `(t, 2)`: speed in m/s and curvature in 1/m. Conventions, in the
ego frame (x forward, y left, z up): curvature, yaw rate and steering angle are positive when
turning left (counter-clockwise seen from above); angles are radians, times seconds, positions
metres.

Curvature is ill-conditioned near standstill (κ = ψ̇ / v with v → 0). Below `min_speed` the value
is *held*: the last curvature measured while moving is kept (and the first one is used for
frames before the car first moves), because the steering geometry of a stopped car does not
snap back to straight. If the car never reaches `min_speed`, there is no measurement at all and
curvature is 0 (straight). NaN never appears in the output.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from gaia_app.data.clip import ClipError

DEFAULT_MIN_SPEED = 0.5
# labels outside these are refused, not trained on: |speed| ≤ 100 m/s (reversing is negative), |curvature| ≤ 1 1/m
# (a 1 m turning radius, tighter than any road vehicle)
LABEL_RANGES = {"speed": 100.0, "curvature": 1.0}
"""m/s; below it curvature is held rather than computed (see module docstring)."""


def hold_where_invalid(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Replace entries where `valid` is False by the last valid one before (else the first valid after).

    values, valid: (t,). All invalid → zeros (no measurement to hold). Returns float64 (t,).
    """
    values = np.asarray(values, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool) & np.isfinite(values)
    if not valid.any():
        return np.zeros_like(values)
    # index of the last valid entry at or before each position (forward fill) ...
    last = np.maximum.accumulate(np.where(valid, np.arange(len(values)), -1))
    # ... and before the first valid entry, use the first valid one (back fill).
    last[last < 0] = np.argmax(valid)
    return values[last]


def curvature_from_yaw_rate(
    yaw_rate: np.ndarray, speed: np.ndarray, min_speed: float = DEFAULT_MIN_SPEED
) -> np.ndarray:
    """Curvature κ = ψ̇ / v (1/m) from yaw rate ψ̇ (rad/s) and speed v (m/s), both (t,).

    Where |v| < min_speed the value is held (module docstring). Returns float64 (t,).
    """
    yaw_rate = np.asarray(yaw_rate, dtype=np.float64)
    speed = np.asarray(speed, dtype=np.float64)
    moving = np.abs(speed) >= min_speed
    kappa = np.divide(yaw_rate, speed, out=np.zeros_like(yaw_rate), where=moving)
    return hold_where_invalid(kappa, moving)


def curvature_from_steering(steering_angle: np.ndarray, wheelbase: float, steering_ratio: float = 1.0) -> np.ndarray:
    """Kinematic bicycle model: κ = tan(δ) / L (1/m).

    steering_angle: (t,) radians, at the steering wheel when steering_ratio > 1 (then the road
    wheel angle is δ = angle / ratio), at the road wheels when steering_ratio = 1.
    wheelbase L: metres. Valid at low lateral acceleration (no tyre slip). Returns float64 (t,).
    """
    if wheelbase <= 0 or steering_ratio <= 0:
        raise ValueError(f"wheelbase ({wheelbase} m) and steering_ratio ({steering_ratio}) must be positive")
    delta = np.asarray(steering_angle, dtype=np.float64) / steering_ratio
    return np.tan(delta) / wheelbase


def _check_track(xy: np.ndarray, timestamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    xy = np.asarray(xy, dtype=np.float64)
    t = np.asarray(timestamps, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) != len(t):
        raise ValueError(f"poses: xy must be (t, 2) with t = {len(t)} timestamps, got {xy.shape}")
    if len(t) < 3 or not np.all(np.diff(t) > 0):
        raise ValueError("poses: need at least 3 samples with strictly increasing timestamps")
    return xy, t


def speed_from_poses(xy: np.ndarray, timestamps: np.ndarray) -> np.ndarray:
    """Speed (m/s) from positions xy (t, 2) metres at timestamps (t,) seconds.

    Second-order finite differences (central inside, one-sided at the ends). Returns (t,).
    """
    xy, t = _check_track(xy, timestamps)
    velocity = np.gradient(xy, t, axis=0, edge_order=2)  # (t, 2) m/s
    return np.linalg.norm(velocity, axis=1)


def unwrap_yaw(yaw: np.ndarray) -> np.ndarray:
    """Remove 2π jumps from a yaw sequence (t,) radians so that it can be differentiated."""
    return np.unwrap(np.asarray(yaw, dtype=np.float64))


def yaw_rate_from_yaw(yaw: np.ndarray, timestamps: np.ndarray) -> np.ndarray:
    """Yaw rate ψ̇ (rad/s) from headings yaw (t,) radians at timestamps (t,) seconds."""
    return np.gradient(unwrap_yaw(yaw), np.asarray(timestamps, dtype=np.float64), edge_order=2)


def curvature_from_poses(
    xy: np.ndarray,
    timestamps: np.ndarray,
    yaw: np.ndarray | None = None,
    min_speed: float = DEFAULT_MIN_SPEED,
) -> np.ndarray:
    """Curvature (1/m) of a driven path, positive to the left.

    xy: (t, 2) metres in a z-up frame; timestamps: (t,) seconds; yaw: optional (t,) vehicle
    heading in radians. With yaw, κ = ψ̇ / v (heading change over distance, robust for a car
    whose heading is measured); without, the path geometry κ = (ẋÿ − ẏẍ) / |v|³, which needs
    smooth positions. Below min_speed the value is held (module docstring). Returns (t,).
    """
    xy, t = _check_track(xy, timestamps)
    if yaw is not None:
        return curvature_from_yaw_rate(yaw_rate_from_yaw(yaw, t), speed_from_poses(xy, t), min_speed)
    vel = np.gradient(xy, t, axis=0, edge_order=2)
    acc = np.gradient(vel, t, axis=0, edge_order=2)
    speed = np.linalg.norm(vel, axis=1)
    moving = speed >= min_speed
    cross = vel[:, 0] * acc[:, 1] - vel[:, 1] * acc[:, 0]
    kappa = np.divide(cross, speed**3, out=np.zeros_like(cross), where=moving)
    return hold_where_invalid(kappa, moving)


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from unit quaternions (..., 4) in (w, x, y, z) order."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def yaw_from_rotation(rotation: np.ndarray, forward_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)) -> np.ndarray:
    """Heading (radians, about world z, 0 = world +x) of a body axis.

    rotation: (..., 3, 3) body→world in a z-up world frame; forward_axis: the body's forward
    direction in body coordinates, e.g. (0, 0, 1) for an OpenCV camera (z forward). The axis is
    projected onto the ground plane, so pitch and roll do not change the result. Returns (...,).
    """
    forward = np.asarray(rotation, dtype=np.float64) @ np.asarray(forward_axis, dtype=np.float64)
    return np.arctan2(forward[..., 1], forward[..., 0])


ACTION_COLUMNS: tuple[str, ...] = ("speed", "curvature", "yaw_rate", "steering_angle", "x", "y", "yaw")
"""Per-frame label columns that can carry the ego action (see `actions_from_labels`)."""


def actions_from_labels(
    columns: Mapping[str, np.ndarray],
    timestamps: np.ndarray | None = None,
    *,
    wheelbase: float | None = None,
    steering_ratio: float = 1.0,
    min_speed: float = DEFAULT_MIN_SPEED,
    where: str = "labels",
) -> np.ndarray:
    """Build actions (t, 2) = (speed m/s, curvature 1/m) from whichever per-frame columns exist.

    columns: name → (t,) values. Speed comes from `speed`, else from poses `x`, `y` (m) and
    `timestamps` (s). Curvature, first available of: `curvature` (1/m); `yaw_rate` (rad/s);
    `steering_angle` (rad) with `wheelbase` (m) and `steering_ratio`; poses `x`, `y` (and `yaw`,
    rad, when present). Raises ClipError naming `where` and the missing columns.
    """
    have = {k for k, v in columns.items() if v is not None}
    has_poses = {"x", "y"} <= have and timestamps is not None
    xy = np.stack([columns["x"], columns["y"]], axis=1) if has_poses else None
    if "speed" in have:
        speed = np.asarray(columns["speed"], dtype=np.float64)
    elif has_poses:
        speed = speed_from_poses(xy, timestamps)
    else:
        raise ClipError(f"{where}: cannot build actions: need column 'speed' or poses 'x', 'y'; have {sorted(have)}")
    if "curvature" in have:
        curvature = np.asarray(columns["curvature"], dtype=np.float64)
    elif "yaw_rate" in have:
        curvature = curvature_from_yaw_rate(columns["yaw_rate"], speed, min_speed)
    elif "steering_angle" in have and wheelbase is not None:
        curvature = curvature_from_steering(columns["steering_angle"], wheelbase, steering_ratio)
    elif has_poses:
        curvature = curvature_from_poses(xy, timestamps, columns.get("yaw"), min_speed)
    else:
        hint = " ('steering_angle' also needs a wheelbase in meta.json)" if "steering_angle" in have else ""
        raise ClipError(
            f"{where}: cannot build actions: need one of 'curvature', 'yaw_rate', 'steering_angle' "
            f"or poses 'x', 'y'{hint}; have {sorted(have)}"
        )
    actions = np.stack([speed, curvature], axis=1).astype(np.float32)
    if not np.all(np.isfinite(actions)):
        bad = int(np.flatnonzero(~np.isfinite(actions).all(axis=1))[0])
        raise ClipError(f"{where}: action at frame {bad} is not finite: {actions[bad].tolist()}")
    for channel, (name, limit) in enumerate(LABEL_RANGES.items()):
        outside = np.flatnonzero(np.abs(actions[:, channel]) > limit)
        if len(outside):
            raise ClipError(f"{where}: {name} {float(actions[outside[0], channel]):g} at frame {int(outside[0])} "
                            "is outside "
                            f"[-{limit:g}, {limit:g}] {'m/s' if name == 'speed' else '1/m'} (wrong units?)")
    return actions
