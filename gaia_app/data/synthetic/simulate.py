"""Run a planned clip frame by frame: the ego applies (speed, curvature), agents move, lights cycle.

Action semantics (GAIA-1 §2): action t = (speed m/s, curvature 1/m) of the ego at frame t, held
constant until frame t+1, so pose t+1 is the exact circular-arc integration of pose t.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from gaia_app.data.synthetic.planning import ScenePlan
from gaia_app.data.synthetic.policy import EgoDriver, integrate_pose
from gaia_app.data.synthetic.world import Ego, World

AGENT_SUBSTEP = 0.1
"""Longest agent integration step (s); low frame rates take several sub-steps per frame."""


@dataclass
class AgentPoses:
    """Agents in the world at one frame (n = all agents of the clip).

    xy: (n, 2) m; yaw: (n,) rad; speed: (n,) m/s; braking: (n,) bool (brake lights);
    indicator: (n,) -1 right / 0 / +1 left; phase: (n,) gait/wheel phase (rad); s, d: (n,)
    Frenet position on their path (m); crossing: (n,) bool, pedestrians crossing the road.
    """

    s: np.ndarray
    d: np.ndarray
    crossing: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    braking: np.ndarray
    indicator: np.ndarray
    phase: np.ndarray


@dataclass
class FrameState:
    """Everything that changes per frame: time (s), the ego (pose, speed, Frenet s/d), its action
    (speed m/s, curvature 1/m) and acceleration until the next frame (m/s²), agent poses, and each
    junction's light for the route and the cross road (None where a junction has no lights)."""

    t: float
    ego: Ego
    speed: float
    curvature: float
    acceleration: float
    lane_changing: bool
    agents: AgentPoses
    lights: list[str | None]
    cross_lights: list[str | None]


def agent_poses(world: World, t: float) -> AgentPoses:
    """World poses of all agents at time t from their Frenet state."""
    a = world.agents
    xy = np.zeros((len(a), 2))
    heading = np.zeros(len(a))
    for k, path in enumerate([world.layout.path] + [r.path for r in world.cross_roads]):
        sel = a.path == k
        if np.any(sel):
            xy[sel] = path.offset(a.s[sel], a.d[sel])
            heading[sel] = path.heading_at(a.s[sel])
    # Velocity in Frenet axes (along s, along d) gives the body yaw; crossers walk along d.
    along = np.where(a.crosser, 0.0, a.direction * np.maximum(a.v, 0.5))
    across = np.where(a.crosser, a.direction * 1.0, a.lateral_rate(t))
    yaw = heading + np.arctan2(across, along)
    return AgentPoses(a.s.copy(), a.d.copy(), a.crosser & (t >= a.cross_t0), xy, yaw, a.v.copy(),
                      (a.accel < -1.0) & a.is_vehicle, a.indicator(t), a.phase.copy())


def simulate(plan: ScenePlan, clip_len: int, fps: float) -> list[FrameState]:
    """States of frames 0..clip_len-1 at times i / fps. Mutates plan.world (agents move)."""
    world, dt = plan.world, 1.0 / fps
    driver = EgoDriver(plan.ego_plan, world)
    path = world.layout.path
    ego = replace(plan.ego)
    substeps = max(1, math.ceil(dt / AGENT_SUBSTEP - 1e-9))
    frames = []
    for i in range(clip_len):
        t = i * dt
        speed, curvature = driver.action(i, t, ego)
        next_speed = driver.next_speed(i, t, ego, dt)
        frames.append(FrameState(
            t, replace(ego), speed, curvature, (next_speed - speed) / dt, driver.lane_changing(t),
            agent_poses(world, t),
            [world.light_state(j, t) for j in range(len(world.lights))],
            [world.light_state(j, t, cross=True) for j in range(len(world.lights))]))
        for k in range(substeps):
            world.step(t + k * dt / substeps, dt / substeps, ego)
        x, y, yaw = integrate_pose(ego.x, ego.y, ego.yaw, speed, curvature, dt)
        s, d = path.project(np.array([x, y]), ego.s + speed * dt)
        ego = replace(ego, x=x, y=y, yaw=yaw, v=next_speed, s=s, d=d)
    return frames
