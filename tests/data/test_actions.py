"""Action labels: curvature from yaw rate, steering and poses against trajectories with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from gaia_app.data.actions import (
    actions_from_labels,
    curvature_from_poses,
    curvature_from_steering,
    curvature_from_yaw_rate,
    hold_where_invalid,
    quaternion_to_rotation,
    speed_from_poses,
    yaw_from_rotation,
)
from gaia_app.data.clip import ClipError

T = np.arange(0, 10, 0.1)  # 10 Hz for 10 s


def circle(radius: float, speed: float, clockwise: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Positions (t, 2) and headings (t,) of a car driving a circle at constant speed."""
    sign = -1.0 if clockwise else 1.0
    angle = sign * speed / radius * T
    xy = radius * np.stack([np.sin(angle) * sign, sign * (1 - np.cos(angle))], axis=1)
    return xy, angle


def test_circle_gives_inverse_radius_both_ways():
    for clockwise, sign in ((False, 1.0), (True, -1.0)):  # left turns are positive
        xy, yaw = circle(radius=20.0, speed=5.0, clockwise=clockwise)
        np.testing.assert_allclose(speed_from_poses(xy, T), 5.0, rtol=2e-3)
        np.testing.assert_allclose(curvature_from_poses(xy, T), sign / 20.0, rtol=2e-3)
        np.testing.assert_allclose(curvature_from_poses(xy, T, yaw=yaw), sign / 20.0, rtol=2e-3)


def test_straight_line_gives_zero_curvature_and_known_speed():
    xy = np.stack([3.0 + 7.0 * T, -2.0 - 7.0 * T], axis=1)  # diagonal, |v| = 7·√2
    np.testing.assert_allclose(speed_from_poses(xy, T), 7.0 * np.sqrt(2), rtol=1e-9)
    np.testing.assert_allclose(curvature_from_poses(xy, T), 0.0, atol=1e-9)
    accelerating = np.stack([0.5 * 2.0 * T**2, np.zeros_like(T)], axis=1)  # x = a t² / 2, a = 2 m/s²
    np.testing.assert_allclose(speed_from_poses(accelerating, T), 2.0 * T, atol=1e-9)


def test_yaw_across_the_pi_wrap():
    xy, yaw = circle(radius=10.0, speed=8.0)  # turns more than once
    wrapped = np.angle(np.exp(1j * yaw))
    np.testing.assert_allclose(curvature_from_poses(xy, T, yaw=wrapped), 0.1, rtol=3e-3)


def test_yaw_rate_and_the_low_speed_rule():
    speed = np.array([0.0, 0.2, 5.0, 10.0, 0.1, 4.0])
    yaw_rate = np.array([0.3, 0.3, 0.5, -1.0, 0.7, 0.4])
    kappa = curvature_from_yaw_rate(yaw_rate, speed, min_speed=0.5)
    # frames below 0.5 m/s hold the last value measured while moving (the first one before that)
    np.testing.assert_allclose(kappa, [0.1, 0.1, 0.1, -0.1, -0.1, 0.1])
    assert np.all(curvature_from_yaw_rate(yaw_rate, np.zeros(6)) == 0)  # never moved: straight, no NaN
    np.testing.assert_array_equal(hold_where_invalid(np.array([np.nan, 2.0, np.nan]), np.ones(3, bool)), [2, 2, 2])


def test_steering_bicycle_model():
    angle = np.array([0.0, 0.1, -0.2])
    np.testing.assert_allclose(curvature_from_steering(angle, wheelbase=2.5), np.tan(angle) / 2.5)
    np.testing.assert_allclose(curvature_from_steering(angle * 15, 2.5, steering_ratio=15), np.tan(angle) / 2.5)
    with pytest.raises(ValueError, match="wheelbase"):
        curvature_from_steering(angle, wheelbase=0)


def test_rotation_helpers():
    half = np.pi / 8  # quaternion of a 45° turn about z
    rotation = quaternion_to_rotation(np.array([np.cos(half), 0, 0, np.sin(half)]))
    np.testing.assert_allclose(rotation @ [1, 0, 0], [np.sqrt(0.5), np.sqrt(0.5), 0], atol=1e-12)
    assert yaw_from_rotation(rotation) == pytest.approx(np.pi / 4)
    camera = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # OpenCV camera looking along world +x
    assert yaw_from_rotation(rotation @ camera, forward_axis=(0, 0, 1)) == pytest.approx(np.pi / 4)


def test_actions_from_labels_by_available_source():
    xy, yaw = circle(radius=25.0, speed=6.0)
    expected = np.stack([np.full_like(T, 6.0), np.full_like(T, 0.04)], axis=1)
    sources = [
        {"speed": np.full_like(T, 6.0), "curvature": np.full_like(T, 0.04)},
        {"speed": np.full_like(T, 6.0), "yaw_rate": np.full_like(T, 0.24)},
        {"speed": np.full_like(T, 6.0), "steering_angle": np.full_like(T, np.arctan(0.04 * 2.5))},
        {"x": xy[:, 0], "y": xy[:, 1]},
        {"x": xy[:, 0], "y": xy[:, 1], "yaw": yaw},
    ]
    for columns in sources:
        actions = actions_from_labels(columns, T, wheelbase=2.5)
        assert actions.dtype == np.float32
        np.testing.assert_allclose(actions, expected, rtol=3e-3)


def test_actions_from_labels_names_missing_columns():
    with pytest.raises(ClipError, match=r"my.jsonl: cannot build actions: need column 'speed' or poses"):
        actions_from_labels({"curvature": np.zeros(3)}, where="my.jsonl")
    message = r"need one of 'curvature', 'yaw_rate'.*also needs a wheelbase.*have \['speed', 'steering_angle'\]"
    with pytest.raises(ClipError, match=message):
        actions_from_labels({"speed": np.ones(3), "steering_angle": np.zeros(3)})
