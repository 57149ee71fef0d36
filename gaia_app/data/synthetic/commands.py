"""Random open-loop ego commands: clips in which the ego leaves its policy and obeys a command.

The policy (policy.py) follows its lane and traffic, so its actions are predictable from the frames: a world model
trained on policy clips alone can predict every future without reading the actions, and nothing teaches it
what a command does. A clip that switches, at a random moment, to a random constant acceleration and curvature
shows the effect of actions that the past does not give away. The same commands train the controllability probes
(gaia_app/protocols/controllability.py), which must read such open-loop futures.
"""

from __future__ import annotations

import numpy as np

# acceleration (m/s²) and curvature (1/m) ranges that contain every preset of generate.py (brake −4, accelerate
# +2, left/right ±0.02, strong ±0.05); straight a third of the time
ACCELERATION_RANGE = (-4.5, 2.5)
CURVATURE_RANGE = (-0.05, 0.05)
STRAIGHT_SHARE = 1 / 3
MAX_SPEED = 30.0  # m/s, the cap of commanded speeds


def draw_command(rng: np.random.Generator,
                 acceleration_range: tuple[float, float] = ACCELERATION_RANGE) -> tuple[float, float]:
    """One random (acceleration m/s² uniform in `acceleration_range`, curvature 1/m)."""
    acceleration = rng.uniform(*acceleration_range)
    curvature = 0.0 if rng.random() < STRAIGHT_SHARE else rng.uniform(*CURVATURE_RANGE)
    return float(acceleration), float(curvature)


def command_profile(start_speed: float, acceleration: float, curvature: float, steps: int, dt: float) -> np.ndarray:
    """(steps, 2) (speed, curvature) of a constant command from `start_speed`, one row per dt after the switch."""
    speed = np.clip(start_speed + acceleration * dt * np.arange(1, steps + 1), 0.0, MAX_SPEED)
    return np.stack([speed, np.full(steps, curvature)], axis=1)


def check_acceleration_range(value: object) -> tuple[float, float]:
    """(low, high) m/s² with low < high, both finite; ValueError naming the setting otherwise."""
    try:
        low, high = (float(v) for v in value)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(f"open_loop_acceleration: expected [low, high] in m/s², got {value!r}") from None
    if not (np.isfinite(low) and np.isfinite(high) and low < high):
        raise ValueError(f"open_loop_acceleration: expected finite low < high in m/s², got {value!r}")
    return low, high


def open_loop_actions(rng: np.random.Generator, policy: np.ndarray, fps: float,
                      acceleration_range: tuple[float, float] = ACCELERATION_RANGE) -> np.ndarray:
    """(t, 2) actions: the policy's (t, 2) until a random frame in the middle half of the clip, then a random command
    (acceleration uniform in `acceleration_range`)."""
    return open_loop_command(rng, policy, fps, acceleration_range)[0]


def open_loop_command(rng: np.random.Generator, policy: np.ndarray, fps: float,
                      acceleration_range: tuple[float, float] = ACCELERATION_RANGE) -> tuple[np.ndarray, int]:
    """`open_loop_actions` and the frame at which its command starts (the first frame not the policy's)."""
    t = len(policy)
    if t < 4:
        raise ValueError(f"open-loop commands need clips of at least 4 frames, got {t}")
    switch = int(rng.integers(t // 4, max(t // 4 + 1, 3 * t // 4)))
    acceleration, curvature = draw_command(rng, acceleration_range)
    tail = command_profile(float(policy[max(switch - 1, 0), 0]), acceleration, curvature, t - switch, 1.0 / fps)
    return np.concatenate([policy[:switch], tail]).astype(np.float64), switch
