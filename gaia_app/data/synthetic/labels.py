"""Ground truth of a synthetic frame: agent 3D boxes in the ego frame, 2D boxes per camera, and
per-frame metadata (lights, junctions, crossings, the lead agent) measured along the route.

Distances ahead are measured along the route from the ego's front bumper (metres).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gaia_app.data.clip import AGENT_CATEGORIES, AgentBoxes
from gaia_app.data.synthetic.policy import lead_agent
from gaia_app.data.synthetic.render import NEAR, CameraRenderer, transform
from gaia_app.data.synthetic.road import CROSSING_HALF_LENGTH
from gaia_app.data.synthetic.simulate import FrameState
from gaia_app.data.synthetic.world import World

LABEL_RANGE = 100.0
"""Agents farther than this (m) from the ego are left out of the 3D labels."""
LOOKAHEAD = 100.0
"""Junctions, lights and crossings farther ahead than this (m) are not reported."""
EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]])


def agent_boxes(world: World, state: FrameState) -> AgentBoxes:
    """Agents within LABEL_RANGE as 3D boxes in the ego frame (centre at half height)."""
    a, ego = world.agents, state.ego
    rel = state.agents.xy - [ego.x, ego.y]
    keep = np.flatnonzero(np.linalg.norm(rel, axis=1) < LABEL_RANGE)
    c, s = np.cos(ego.yaw), np.sin(ego.yaw)
    x = c * rel[keep, 0] + s * rel[keep, 1]
    y = -s * rel[keep, 0] + c * rel[keep, 1]
    yaw = (state.agents.yaw[keep] - ego.yaw + np.pi) % (2 * np.pi) - np.pi
    size = a.size[keep]
    return AgentBoxes(np.c_[x, y, size[:, 2] / 2], size, yaw, a.category[keep], a.track_id[keep])


def _next_junction(world: World, s_front: float) -> tuple[int, float] | None:
    """(index, distance m to its stop line, 0 inside the box) of the next junction ahead."""
    for j, site in enumerate(world.layout.junctions):
        if site.s_exit > s_front:
            distance = max(0.0, site.stop_s - s_front)
            return (j, distance) if distance <= LOOKAHEAD else None
    return None


def _next_crossing(world: World, s_front: float) -> float | None:
    ahead = [c - s_front for c in world.layout.crossings if c + CROSSING_HALF_LENGTH > s_front]
    return max(0.0, min(ahead)) if ahead and min(ahead) <= LOOKAHEAD else None


def frame_meta(world: World, state: FrameState) -> dict[str, Any]:
    """Per-frame metadata (JSON-friendly): ego pose and lane, manoeuvre, next light, junction and
    crossing ahead with distances, pedestrians on crossings, the lead agent."""
    ego = state.ego
    s_front = ego.s + ego.front
    lane, _ = world.geometry.lane_of(ego.d)
    meta: dict[str, Any] = {"ego_pose": [round(ego.x, 3), round(ego.y, 3), round(ego.yaw, 5)], "ego_lane": lane,
                            "manoeuvre": manoeuvre(state)}
    junction = _next_junction(world, s_front)
    meta["intersection"] = None if junction is None else world.layout.junctions[junction[0]].spec.kind
    meta["intersection_distance"] = None if junction is None else round(junction[1], 2)
    meta["turn"] = None if junction is None else world.layout.junctions[junction[0]].spec.turn
    light = None if junction is None else state.lights[junction[0]]
    meta["traffic_light"] = light
    meta["traffic_light_distance"] = None if light is None else round(junction[1], 2)
    crossing = _next_crossing(world, s_front)
    meta["crossing"] = crossing is not None
    meta["crossing_distance"] = None if crossing is None else round(crossing, 2)
    a, p = world.agents, state.agents
    on_road = p.crossing & (np.abs(p.d) < world.geometry.edge + world.geometry.shoulder) & (a.path == 0)
    meta["pedestrians_crossing"] = int(np.sum(on_road & (np.abs(p.s - s_front) < LOOKAHEAD)))
    gap, speed, i = lead_agent(world, ego, p.s, p.d, p.speed)
    meta["lead_agent"] = None if i < 0 or gap > LOOKAHEAD else {
        "category": AGENT_CATEGORIES[int(a.category[i])], "track_id": int(a.track_id[i]),
        "distance": round(gap, 2), "speed": round(speed, 2)}
    return meta


def manoeuvre(state: FrameState) -> str:
    """What the ego is doing: stopped, lane_change, turn_left/right, braking, accelerating, cruising."""
    if state.speed < 0.3:
        return "stopped"
    if state.lane_changing:
        return "lane_change"
    if abs(state.curvature) > 0.02:
        return "turn_left" if state.curvature > 0 else "turn_right"
    if state.acceleration < -0.8:
        return "braking"
    return "accelerating" if state.acceleration > 0.6 else "cruising"


def boxes_2d(renderer: CameraRenderer, world: World, cam_from_world: np.ndarray, verts: np.ndarray,
             instance: np.ndarray, sphere_centre: np.ndarray, sphere_radius: np.ndarray,
             sphere_instance: np.ndarray) -> list[dict[str, Any]]:
    """2D boxes [x0, y0, x1, y1] (pixels, clipped to the image) of every agent whose parts project
    into the camera: the extent of its solids and discs after near-plane clipping. Not occlusion
    aware (see SyntheticSample.instance_ids for visibility)."""
    lo = np.full((len(world.agents), 2), np.inf)
    hi = np.full((len(world.agents), 2), -np.inf)
    if len(verts):
        cam = transform(cam_from_world, verts)  # (B, 8, 3)
        a, b = cam[:, EDGES[:, 0]], cam[:, EDGES[:, 1]]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (NEAR - a[..., 2]) / (b[..., 2] - a[..., 2])
        crossing = (a[..., 2] < NEAR) != (b[..., 2] < NEAR)
        hits = a + np.where(crossing, t, 0.0)[..., None] * (b - a)
        points = np.concatenate([cam, hits], axis=1)
        valid = np.concatenate([cam[..., 2] >= NEAR, crossing], axis=1)
        uv = _pixels(renderer, points)
        np.minimum.at(lo, instance, np.where(valid[..., None], uv, np.inf).min(axis=1))
        np.maximum.at(hi, instance, np.where(valid[..., None], uv, -np.inf).max(axis=1))
    if len(sphere_centre):
        cam = transform(cam_from_world, sphere_centre)
        ok = cam[:, 2] > sphere_radius + NEAR
        uv = _pixels(renderer, cam)
        r = (renderer.fx * sphere_radius / np.maximum(cam[:, 2], 1e-6))[:, None]
        np.minimum.at(lo, sphere_instance[ok], (uv - r)[ok])
        np.maximum.at(hi, sphere_instance[ok], (uv + r)[ok])
    lo = np.maximum(lo, 0.0)
    hi = np.minimum(hi, [renderer.w, renderer.h])
    out = []
    for i in np.flatnonzero((hi[:, 0] > lo[:, 0]) & (hi[:, 1] > lo[:, 1])):
        out.append({"track_id": int(world.agents.track_id[i]),
                    "category": AGENT_CATEGORIES[int(world.agents.category[i])],
                    "box": [round(float(v), 2) for v in (*lo[i], *hi[i])]})
    return out


def _pixels(renderer: CameraRenderer, cam: np.ndarray) -> np.ndarray:
    """(..., 2) continuous pixel coordinates (intrinsics convention) of camera-frame points."""
    z = np.maximum(cam[..., 2], 1e-6)
    return np.stack([renderer.fx * cam[..., 0] / z + renderer.cx, renderer.fy * cam[..., 1] / z + renderer.cy], axis=-1)
