"""Meshes of things that change every frame: agents (cars, buses, trucks, cyclists,
pedestrians, with brake lights, indicators and walking legs) and traffic-light heads.

Agent meshes are built once per clip in each agent's own frame (x forward, y left, z up,
origin at the footprint centre) and posed every frame by a rigid transform; only leg swing and
lamp colours change. Every part carries the agent's track id as `instance`, and the parts of one
agent fill exactly its 3D box (length × width × height), so 2D boxes, masks and 3D labels agree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gaia_app.data.synthetic.geometry import (
    BACK,
    FRONT,
    LEFT,
    RIGHT,
    TOP,
    Decals,
    Mesh,
    Solids,
    Spheres,
    box_vertices,
    decals,
    solids,
    spheres,
)
from gaia_app.data.synthetic.road import RoadLayout
from gaia_app.data.synthetic.simulate import AgentPoses, FrameState
from gaia_app.data.synthetic.world import BUS, CAR, CYCLIST, PEDESTRIAN, TRUCK, Agents

GLASS = np.array([0.12, 0.15, 0.19])
TYRE = np.array([0.06, 0.06, 0.06])
TRIM = np.array([0.12, 0.12, 0.13])
SKIN = np.array([[0.93, 0.76, 0.62], [0.78, 0.57, 0.42], [0.55, 0.38, 0.26], [0.36, 0.24, 0.16]])
LAMP = {"red": np.array([1.0, 0.12, 0.08]), "amber": np.array([1.0, 0.62, 0.05]), "green": np.array([0.15, 1.0, 0.45])}
LAMP_OFF = np.array([0.12, 0.12, 0.12])
HEAD_LIGHT = np.array([1.0, 0.97, 0.85])
TAIL_LIGHT = np.array([0.85, 0.08, 0.06])
BRAKE_LIGHT = np.array([1.0, 0.1, 0.08])
INDICATOR = np.array([1.0, 0.6, 0.05])
INDICATOR_HZ = 1.5
PAINT, HEAD, TAIL, INDICATE_RIGHT, INDICATE_LEFT = range(5)
"""Decal roles: fixed colour, headlight, tail/brake light, right and left indicators."""


def _box(size: np.ndarray, forward=0.0, lateral=0.0, z0=0.0, top_scale=None, top_shift=None) -> np.ndarray:
    """(n, 8, 3) boxes of `size` (n, 3) with bottom centre (forward, lateral, z0) in the agent frame."""
    n = len(size)
    centre = np.c_[np.broadcast_to(forward, n), np.broadcast_to(lateral, n), np.broadcast_to(z0, n)]
    return box_vertices(centre, np.zeros(n), size, top_scale, top_shift)


@dataclass
class Part:
    """Agent parts of one kind: mesh in agent frames, owner agent index per solid / sphere,
    leg swing sign per solid, role per decal."""

    mesh: Mesh
    solid_owner: np.ndarray
    sphere_owner: np.ndarray
    swing: np.ndarray
    role: np.ndarray


def _part(mesh: Mesh, solid_owner, sphere_owner=None, swing=None, role=None) -> Part:
    b, d = len(mesh.solids), len(mesh.decals)
    return Part(mesh, np.asarray(solid_owner, np.int64),
                np.zeros(0, np.int64) if sphere_owner is None else np.asarray(sphere_owner, np.int64),
                np.zeros(b) if swing is None else np.asarray(swing, float),
                np.full(d, PAINT) if role is None else np.asarray(role, np.int64))


def _lights(parent: np.ndarray, v: tuple[float, float]) -> tuple[Decals, np.ndarray]:
    """Headlights (FRONT), tail lights and indicators (BACK) on solids `parent`; colours set per frame."""
    out, roles = [], []
    for (u0, u1), indicator in (((0.04, 0.22), INDICATE_RIGHT), ((0.78, 0.96), INDICATE_LEFT)):
        # Face u runs from the agent's right (-y) to its left (+y) on both FRONT and BACK.
        out += [decals(parent, FRONT, [u0, v[0], u1, v[1]], HEAD_LIGHT),
                decals(parent, BACK, [u0, v[0], u1, v[1]], TAIL_LIGHT),
                decals(parent, BACK, [u0, v[1], u1, min(v[1] + 0.08, 1.0)], TAIL_LIGHT * 0.5)]
        roles += [np.full(len(parent), HEAD), np.full(len(parent), TAIL), np.full(len(parent), indicator)]
    return Decals.concat(out), np.concatenate(roles)


def _wheels(parent: np.ndarray, v_top: float, spots) -> Decals:
    return Decals.concat([decals(parent, face, [u0, 0.0, u1, v_top], TYRE)
                          for face in (LEFT, RIGHT) for u0, u1 in spots])


def _with_lights(mesh: Mesh, paint: list[Decals], lit_parent: np.ndarray,
                 v: tuple[float, float]) -> tuple[Mesh, np.ndarray]:
    lamps, roles = _lights(lit_parent, v)
    painted = Decals.concat(paint)
    mesh.decals = Decals.concat([painted, lamps])
    return mesh, np.r_[np.full(len(painted), PAINT), roles]


def car_parts(a: Agents, idx: np.ndarray) -> Part:
    """Body (0.18 m clearance to 60 % height) and a tapered glass cabin on top."""
    n, size = len(idx), a.size[idx]
    body_h = 0.6 * size[:, 2]
    body = _box(np.c_[size[:, :2], body_h - 0.18], z0=0.18)
    cabin = _box(np.c_[size[:, 0] * 0.62, size[:, 1] * 0.96, size[:, 2] - body_h], -0.05 * size[:, 0], 0.0, body_h,
                 np.tile([0.72, 0.82], (n, 1)), -0.04 * size[:, 0])
    paint = a.colour[idx]
    cabin_colour = np.repeat(GLASS[None, None], n, 0).repeat(6, 1)
    cabin_colour[:, TOP] = paint
    mesh = Mesh(Solids(np.concatenate([body, cabin]), np.concatenate([np.repeat(paint[:, None], 6, 1), cabin_colour]),
                       np.zeros((2 * n, 6), bool), np.r_[a.track_id[idx], a.track_id[idx]]))
    body_i = np.arange(n)
    mesh, role = _with_lights(mesh, [_wheels(body_i, 0.55, ((0.1, 0.26), (0.74, 0.9))),
                                     decals(body_i, FRONT, [0.0, 0.0, 1.0, 0.22], TRIM),
                                     decals(body_i, BACK, [0.0, 0.0, 1.0, 0.22], TRIM)], body_i, (0.5, 0.75))
    return _part(mesh, np.r_[idx, idx], role=role)


def bus_parts(a: Agents, idx: np.ndarray, lights_on: bool) -> Part:
    """One tall box with a window band (lit inside at night), windscreen and wheels."""
    n, size = len(idx), a.size[idx]
    mesh = Mesh(solids(_box(np.c_[size[:, :2], size[:, 2] - 0.15], z0=0.15), a.colour[idx], instance=a.track_id[idx]))
    i = np.arange(n)
    band = np.array([0.75, 0.7, 0.5]) if lights_on else GLASS
    mesh, role = _with_lights(mesh, [decals(i, LEFT, [0.04, 0.5, 0.96, 0.88], band, lights_on),
                                     decals(i, RIGHT, [0.04, 0.5, 0.96, 0.88], band, lights_on),
                                     decals(i, FRONT, [0.05, 0.42, 0.95, 0.92], GLASS),
                                     decals(i, BACK, [0.1, 0.6, 0.9, 0.9], GLASS),
                                     _wheels(i, 0.22, ((0.12, 0.22), (0.72, 0.82)))], i, (0.25, 0.4))
    return _part(mesh, idx, role=role)


def truck_parts(a: Agents, idx: np.ndarray) -> Part:
    """A cab at the front and a cargo box behind it."""
    n, size = len(idx), a.size[idx]
    cab_len = np.full(n, 2.3)
    cab = _box(np.c_[cab_len, size[:, 1], size[:, 2] * 0.8 - 0.35], size[:, 0] / 2 - cab_len / 2, 0.0, 0.35)
    box_len = size[:, 0] - cab_len - 0.3
    cargo = _box(np.c_[box_len, size[:, 1], size[:, 2] - 0.5], -size[:, 0] / 2 + box_len / 2, 0.0, 0.5)
    cargo_colour = np.where((a.track_id[idx] % 3 == 0)[:, None], a.colour[idx] * 0.9, [0.88, 0.88, 0.86])
    mesh = Mesh(solids(np.concatenate([cab, cargo]), np.concatenate([a.colour[idx], cargo_colour]),
                       instance=np.r_[a.track_id[idx], a.track_id[idx]]))
    cab_i, cargo_i = np.arange(n), np.arange(n, 2 * n)
    mesh, role = _with_lights(mesh, [decals(cab_i, FRONT, [0.06, 0.5, 0.94, 0.9], GLASS),
                                     decals(cab_i, LEFT, [0.35, 0.55, 0.9, 0.88], GLASS),
                                     decals(cab_i, RIGHT, [0.1, 0.55, 0.65, 0.88], GLASS),
                                     _wheels(cab_i, 0.3, ((0.3, 0.7),)), _wheels(cargo_i, 0.25, ((0.08, 0.3),))],
                              cargo_i, (0.25, 0.4))
    return _part(mesh, np.r_[idx, idx], role=role)


def cyclist_parts(a: Agents, idx: np.ndarray) -> Part:
    """A thin bike with two wheels, a leaning rider and a head."""
    n, size = len(idx), a.size[idx]
    bike = _box(np.c_[size[:, 0], np.full(n, 0.08), np.full(n, 0.95)])
    rider = _box(np.c_[np.full(n, 0.4), size[:, 1], size[:, 2] - 0.95 - 0.24], -0.1, 0.0, 0.95,
                 np.tile([0.8, 0.85], (n, 1)), np.full(n, 0.12))
    head = np.c_[np.full(n, 0.05), np.zeros(n), size[:, 2] - 0.12]
    track = a.track_id[idx]
    mesh = Mesh(solids(np.concatenate([bike, rider]),
                       np.concatenate([np.tile([0.15, 0.15, 0.17], (n, 1)), a.colour[idx]]),
                       instance=np.r_[track, track]),
                _wheels(np.arange(n), 0.75, ((0.0, 0.4), (0.6, 1.0))),
                spheres(head, 0.12, SKIN[track % len(SKIN)], instance=track))
    return _part(mesh, np.r_[idx, idx], idx)


def pedestrian_parts(a: Agents, idx: np.ndarray) -> Part:
    """Two legs (swung every frame), a torso and a head."""
    n, size = len(idx), a.size[idx]
    height = size[:, 2]
    leg_h, torso_h = 0.47 * height, 0.34 * height
    legs = [_box(np.c_[np.full(n, 0.14), np.full(n, 0.15), leg_h], 0.0, side * 0.1) for side in (1, -1)]
    torso = _box(np.c_[size[:, 0] * 0.6, size[:, 1], torso_h], z0=leg_h)
    track = a.track_id[idx]
    trousers = np.where((track % 2 == 0)[:, None], [0.15, 0.17, 0.25], [0.25, 0.22, 0.2])
    head_r = (height - leg_h - torso_h) / 2
    mesh = Mesh(solids(np.concatenate(legs + [torso]), np.concatenate([trousers, trousers, a.colour[idx]]),
                       instance=np.r_[track, track, track]),
                spheres=spheres(np.c_[np.zeros((n, 2)), height - head_r], head_r, SKIN[track % len(SKIN)],
                                instance=track))
    return _part(mesh, np.r_[idx, idx, idx], idx, swing=np.r_[np.ones(n), -np.ones(n), np.zeros(n)])


class AgentMeshes:
    """All agent meshes of a clip in agent frames, posed per frame."""

    def __init__(self, agents: Agents, lights_on: bool):
        def of(cat: int) -> np.ndarray:
            return np.flatnonzero(agents.category == cat)

        parts = [car_parts(agents, of(CAR)), bus_parts(agents, of(BUS), lights_on), truck_parts(agents, of(TRUCK)),
                 cyclist_parts(agents, of(CYCLIST)), pedestrian_parts(agents, of(PEDESTRIAN))]
        self.mesh = Mesh.concat([p.mesh for p in parts])
        self.solid_owner = np.concatenate([p.solid_owner for p in parts])
        self.sphere_owner = np.concatenate([p.sphere_owner for p in parts])
        self.swing = np.concatenate([p.swing for p in parts])
        self.role = np.concatenate([p.role for p in parts if len(p.mesh.solids) or len(p.mesh.spheres)]
                                   or [np.zeros(0)])
        self.lights_on = lights_on

    def posed(self, poses: AgentPoses, t: float, near: np.ndarray) -> Mesh:
        """World-frame mesh of the agents selected by the boolean mask `near` (n agents)."""
        owner = self.solid_owner
        verts = self.mesh.solids.verts.copy()
        swing = 0.18 * np.sin(poses.phase[owner]) * (poses.speed[owner] > 0.1) * self.swing
        verts[:, :4, 0] += swing[:, None]  # feet move, hips stay
        world = _place(verts, poses.xy[owner], poses.yaw[owner])
        sp = self.mesh.spheres
        centres = _place(sp.centre[:, None], poses.xy[self.sphere_owner], poses.yaw[self.sphere_owner])[:, 0]
        mesh = Mesh(Solids(world, self.mesh.solids.colour, self.mesh.solids.emissive, self.mesh.solids.instance),
                    self._lamp_decals(poses, t), Spheres(centres, sp.radius, sp.colour, sp.emissive, sp.instance))
        return mesh.select(near[owner], near[self.sphere_owner])

    def _lamp_decals(self, poses: AgentPoses, t: float) -> Decals:
        d = self.mesh.decals
        owner = self.solid_owner[d.parent]
        braking = poses.braking[owner]
        blink = (t * INDICATOR_HZ) % 1.0 < 0.5
        indicate = blink & (((self.role == INDICATE_LEFT) & (poses.indicator[owner] > 0)) |
                            ((self.role == INDICATE_RIGHT) & (poses.indicator[owner] < 0)))
        colour, emissive = d.colour.copy(), d.emissive.copy()
        head, tail = self.role == HEAD, self.role == TAIL
        colour[head] = HEAD_LIGHT if self.lights_on else HEAD_LIGHT * 0.75
        emissive[head] = self.lights_on
        colour[tail] = np.where(braking[tail, None], BRAKE_LIGHT, TAIL_LIGHT * (1.0 if self.lights_on else 0.6))
        emissive[tail] = self.lights_on | braking[tail]
        colour[indicate], emissive[indicate] = INDICATOR, True
        return Decals(d.parent, d.face, d.uv, colour, emissive)


def _place(local: np.ndarray, xy: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Rotate (n, k, 3) agent-frame points by yaw (n,) and move them to xy (n, 2)."""
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    x, y = local[..., 0], local[..., 1]
    return np.stack([xy[:, :1] + c * x - s * y, xy[:, 1:] + s * x + c * y, local[..., 2]], axis=-1)


def traffic_lights(layout: RoadLayout, state: FrameState, near_junctions: list[int]) -> Mesh:
    """Poles with three-lamp heads at every signalled junction: for the route (near and far side
    of the box, both directions) and for the cross road; lamps show the current phase."""
    geo, path = layout.geometry, layout.path
    kerb = geo.edge + geo.shoulder + 0.8
    bases, yaws, lamp_state = [], [], []
    for j in near_junctions:
        site = layout.junctions[j]
        if state.lights[j] is None:
            continue
        for s, side, facing in ((site.stop_s, geo.drive_sign, 0.0), (site.s_exit + 1.0, geo.drive_sign, 0.0),
                                (site.stop_s_oncoming, -geo.drive_sign, np.pi),
                                (site.s_entry - 1.0, -geo.drive_sign, np.pi)):
            # A head faces the traffic it controls: own traffic heads along the path, oncoming against it.
            bases.append(path.offset(np.array(s), np.array(side * kerb)))
            yaws.append(float(path.heading_at(s)) + facing + np.pi)
            lamp_state.append(state.lights[j])
        for arm in site.arm_headings:
            # Kerb-side corner of the arm's incoming lanes (incoming traffic heads arm + pi).
            outward = np.array([np.cos(arm), np.sin(arm)])
            incoming_left = np.array([np.cos(arm - np.pi / 2), np.sin(arm - np.pi / 2)])
            bases.append(site.centre + (site.half_size + 1.0) * outward + geo.drive_sign * kerb * incoming_left)
            yaws.append(arm)
            lamp_state.append(state.cross_lights[j])
    n = len(bases)
    if n == 0:
        return Mesh.empty()
    base, yaw = np.c_[np.array(bases), np.zeros(n)], np.array(yaws)
    pole = box_vertices(base, yaw, np.tile([0.14, 0.14, 2.6], (n, 1)))
    head = box_vertices(base + [0, 0, 2.5], yaw, np.tile([0.3, 0.36, 0.95], (n, 1)))
    mesh = Mesh(solids(np.concatenate([pole, head]), np.r_[np.tile([0.35, 0.36, 0.38], (n, 1)), np.tile(TRIM, (n, 1))]))
    parent = np.arange(n, 2 * n)
    lamps = []
    for colour, (v0, v1) in (("red", (0.68, 0.92)), ("amber", (0.38, 0.62)), ("green", (0.08, 0.32))):
        on = np.array([s == colour for s in lamp_state])
        lamps.append(decals(parent, FRONT, [0.18, v0, 0.82, v1], np.where(on[:, None], LAMP[colour], LAMP_OFF), on))
    mesh.decals = Decals.concat(lamps)
    return mesh
