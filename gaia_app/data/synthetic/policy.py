"""Ego behaviour: policies that choose (speed m/s, curvature 1/m) every frame, and the exact
integration of those actions into a pose.

Steering is pure pursuit towards a point ahead on the target lateral offset (a lane centre, or a
smooth lane-change profile). Speed is IDM towards a behaviour-specific desired speed, limited
by the curvature ahead (comfortable lateral acceleration) and by obstacles: the lead agent,
red/amber lights, occupied zebra crossings. Behaviours (`BEHAVIOURS`): cruise, follow,
accelerate, brake, turn, lane_change.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gaia_app.data.synthetic.world import Ego, World, idm_accel

BEHAVIOURS = ("cruise", "follow", "accelerate", "brake", "turn", "lane_change")
MAX_CURVATURE = 0.3
"""Steering limit (1/m): a turning radius of about 3.3 m."""
LATERAL_ACCEL = 2.5
"""Comfortable lateral acceleration (m/s²) that limits the speed in curves."""
COMFORT_DECEL = 2.0


@dataclass
class EgoPlan:
    """What the ego wants to do in one clip.

    behaviour: one of BEHAVIOURS (descriptive; the numbers below realise it); lane: starting lane;
    v_desired: cruising speed (m/s); a_max: IDM acceleration (m/s²); change_t0 / change_len /
    change_to: lane change start (s, may be negative = already under way), duration (s), target lane;
    brake_t0 / brake_decel: hard-brake event start (s) and deceleration (m/s²);
    actions: (t, 2) open-loop (speed, curvature) that replace the policy when given.
    """

    behaviour: str
    lane: int
    v_desired: float
    a_max: float = 1.5
    change_t0: float = np.inf
    change_len: float = 4.0
    change_to: int | None = None
    brake_t0: float = np.inf
    brake_decel: float = 4.0
    actions: np.ndarray | None = None


def smoothstep(u: np.ndarray | float) -> np.ndarray | float:
    u = np.clip(u, 0.0, 1.0)
    return 3 * u * u - 2 * u ** 3


def integrate_pose(x: float, y: float, yaw: float, speed: float, curvature: float,
                   dt: float) -> tuple[float, float, float]:
    """Pose after driving `dt` s at constant speed and curvature (an exact circular arc)."""
    arc = speed * dt
    turn = arc * curvature
    chord = arc * np.sinc(turn / (2 * np.pi))
    mid = yaw + turn / 2
    return x + chord * np.cos(mid), y + chord * np.sin(mid), yaw + turn


class EgoDriver:
    """Closed-loop ego controller for one clip (or a replay of open-loop actions)."""

    def __init__(self, plan: EgoPlan, world: World):
        self.plan, self.world = plan, world
        geo = world.geometry
        self.d_start = float(geo.lane_offset(plan.lane))
        self.d_end = self.d_start if plan.change_to is None else float(geo.lane_offset(plan.change_to))

    def target_offset(self, t: float) -> float:
        """Lateral target d (m) at time t: lane centre or the lane-change profile."""
        u = (t - self.plan.change_t0) / self.plan.change_len
        return self.d_start + (self.d_end - self.d_start) * float(smoothstep(u))

    def lane_changing(self, t: float) -> bool:
        return self.plan.change_t0 <= t < self.plan.change_t0 + self.plan.change_len and self.d_end != self.d_start

    def action(self, frame: int, t: float, ego: Ego) -> tuple[float, float]:
        """(speed m/s, curvature 1/m) held from t to t+dt."""
        if self.plan.actions is not None:
            speed, curvature = self.plan.actions[frame]
            return float(speed), float(curvature)
        return ego.v, self.curvature(t, ego)

    def next_speed(self, frame: int, t: float, ego: Ego, dt: float) -> float:
        """Speed (m/s) at t+dt."""
        if self.plan.actions is not None:
            return float(self.plan.actions[min(frame + 1, len(self.plan.actions) - 1), 0])
        return max(0.0, ego.v + self.acceleration(t, ego) * dt)

    def curvature(self, t: float, ego: Ego) -> float:
        path = self.world.layout.path
        lookahead = float(np.clip(0.5 * ego.v + 3.0, 4.0, 20.0))
        target = path.offset(ego.s + lookahead, self.target_offset(t + lookahead / max(ego.v, 3.0)))
        dx, dy = target[0] - ego.x, target[1] - ego.y
        c, s = np.cos(ego.yaw), np.sin(ego.yaw)
        fwd, left = c * dx + s * dy, -s * dx + c * dy
        return float(np.clip(2 * left / (fwd * fwd + left * left), -MAX_CURVATURE, MAX_CURVATURE))

    def acceleration(self, t: float, ego: Ego) -> float:
        plan = self.plan
        if plan.brake_t0 <= t and ego.v > 0:
            return -plan.brake_decel
        v_des = min(plan.v_desired, self.curve_speed(ego))
        gap, v_lead = self.obstacle(t, ego)
        accel = idm_accel(np.array([ego.v]), np.array([v_des]), np.array([gap]), np.array([v_lead]),
                          np.array([plan.a_max]))
        return float(accel[0])

    def curve_speed(self, ego: Ego) -> float:
        """Highest speed (m/s) from which the ego can slow comfortably for every curve ahead."""
        path = self.world.layout.path
        ahead = np.arange(0.0, 80.0, 2.0)
        kappa = np.abs(path.curvature_at(ego.s + ahead))
        v_zone = np.sqrt(LATERAL_ACCEL / np.maximum(kappa, 1e-4))
        return float(np.min(np.sqrt(v_zone ** 2 + 2 * COMFORT_DECEL * ahead)))

    def obstacle(self, t: float, ego: Ego) -> tuple[float, float]:
        """(gap m, speed m/s) of the nearest thing to stop behind: lead agent, stop line, crossing."""
        a = self.world.agents
        gap, v_lead, _ = lead_agent(self.world, ego, a.s, a.d, a.v)
        front = np.array([ego.s + ego.front])
        stop = float(self.world.stop_obstacles(t, 0, 1, front, np.array([ego.v]))[0])
        return (stop, 0.0) if stop < gap else (gap, v_lead)


def lead_agent(world: World, ego: Ego, s: np.ndarray, d: np.ndarray, v: np.ndarray) -> tuple[float, float, int]:
    """(gap m, speed m/s, agent index) of the nearest same-direction lane user ahead of the ego
    within its lane corridor, given agent Frenet positions s, d (m) and speeds v (m/s); the gap
    runs from the ego's front bumper to the agent's rear. (inf, 0, -1) when there is none."""
    a = world.agents
    corridor = world.geometry.lane_width / 2 + a.size[:, 1] / 2 - 0.2
    on_route = (a.path == 0) & (a.direction == 1) & a.is_vehicle
    gap = s - a.size[:, 0] / 2 - (ego.s + ego.front)
    valid = on_route & (np.abs(d - ego.d) < corridor) & (gap > -0.5)
    if not np.any(valid):
        return np.inf, 0.0, -1
    i = int(np.argmin(np.where(valid, gap, np.inf)))
    return float(gap[i]), float(v[i]), i
