"""Static roadside objects: buildings with windows, trees, street lamps, speed-limit signs,
guard rails and hedges, placed along the route by environment (urban, suburban, rural, highway).
Objects face the road: a box's +x axis follows the road heading at its place."""

from __future__ import annotations

import numpy as np

from gaia_app.data.synthetic.geometry import (
    BACK,
    FRONT,
    LEFT,
    RIGHT,
    Decals,
    Mesh,
    box_vertices,
    decals,
    solids,
    spheres,
)
from gaia_app.data.synthetic.planning import KERB_WIDTH, SIDEWALK_WIDTH
from gaia_app.data.synthetic.road import RoadLayout
from gaia_app.data.synthetic.scenario import COUNTRIES, EGO_START, Setting

FACADES = np.array([[0.78, 0.72, 0.6], [0.62, 0.34, 0.26], [0.6, 0.6, 0.58], [0.88, 0.86, 0.8], [0.85, 0.78, 0.55],
                    [0.45, 0.5, 0.55], [0.7, 0.55, 0.45], [0.55, 0.6, 0.5], [0.8, 0.8, 0.82]])
ROOFS = np.array([[0.45, 0.18, 0.14], [0.25, 0.25, 0.27], [0.4, 0.3, 0.22], [0.55, 0.3, 0.2]])
LEAVES = np.array([[0.2, 0.38, 0.15], [0.28, 0.45, 0.18], [0.16, 0.3, 0.14], [0.35, 0.45, 0.2], [0.12, 0.26, 0.15]])
GLASS = np.array([0.2, 0.25, 0.3])
LIT_WINDOW = np.array([1.0, 0.85, 0.55])
LAMP_GLOW = np.array([1.0, 0.9, 0.7])
TRUNK = np.array([0.3, 0.22, 0.15])
METAL = np.array([0.45, 0.46, 0.48])
BUILDING_STYLE = {  # length, depth, height ranges (m), setback range (m), fraction of frontage built
    "urban": ((10, 30), (10, 20), (8, 32), (0.0, 1.5), 0.9),
    "suburban": ((8, 13), (8, 11), (4, 7), (5, 12), 0.6),
    "rural": ((10, 25), (8, 14), (4, 8), (12, 30), 0.08),
    "highway": ((20, 50), (15, 30), (6, 12), (40, 80), 0.03),
}


def _frame_at(layout: RoadLayout, s, d, z=0.0) -> tuple[np.ndarray, np.ndarray]:
    """Bottom-centre points (n, 3) and road headings (n,) at Frenet (s, d)."""
    s, d = np.atleast_1d(np.asarray(s, float)), np.atleast_1d(np.asarray(d, float))
    s, d = np.broadcast_arrays(s, d)
    xy = layout.path.offset(s, d)
    return np.c_[xy, np.broadcast_to(z, s.shape)], layout.path.heading_at(s)


def _free(layout: RoadLayout, s: np.ndarray, margin: float) -> np.ndarray:
    """Mask of route s clear of junction boxes (and their side arms) by `margin` m."""
    s = np.asarray(s, float)
    ok = (s > 5.0) & (s < layout.path.length - 5.0)
    for j in layout.junctions:
        ok &= (s < j.s_entry - margin) | (s > j.s_exit + margin)
    return ok


def _roadside(setting: Setting, layout: RoadLayout) -> float:
    """|d| (m) where the roadside begins: the sidewalk's outer edge, or a verge beyond the asphalt."""
    geo = layout.geometry
    return geo.edge + geo.shoulder + KERB_WIDTH + (SIDEWALK_WIDTH if setting.sidewalk else 1.5)


def _window_grid(parent: int, face: int, length: float, height: float, rng: np.random.Generator,
                 lights_on: bool, bands: bool) -> Decals:
    """Windows on a facade of `length` × `height` m: a grid, or glass bands (offices)."""
    floor, bay = 3.2, rng.uniform(2.6, 3.6)
    rows, cols = max(1, int((height - 0.8) / floor)), max(1, int(length / bay))
    if bands:
        u0, u1 = np.full(rows, 0.03), np.full(rows, 0.97)
        v0 = (np.arange(rows) * floor + 0.9) / height
        v1 = v0 + (floor - 1.1) / height
    else:
        c, r = (g.ravel() for g in np.meshgrid(np.arange(cols), np.arange(rows)))
        u0, u1 = (c + 0.22) / cols, (c + 0.78) / cols
        v0 = (r * floor + 1.0) / height
        v1 = v0 + 1.5 / height
    n = len(u0)
    lit = lights_on & (rng.random(n) < 0.25)
    colour = np.where(lit[:, None], LIT_WINDOW * rng.uniform(0.6, 0.9, (n, 1)), GLASS * rng.uniform(0.6, 1.4, (n, 1)))
    return decals(np.full(n, parent), face, np.stack([u0, v0, u1, np.minimum(v1, 0.97)], 1), colour, lit)


def _building_rows(rng: np.random.Generator, setting: Setting, start: float, stop: float, front: float,
                   free) -> list[tuple[float, float, float, float, float, int]]:
    """(x_mid, lateral, length, depth, height, side) of buildings along a street from `start` to
    `stop` m, both sides, `front` m from its centre line; `free(x0, x1)` vetoes stretches."""
    (len_lo, len_hi), (dep_lo, dep_hi), (h_lo, h_hi), (set_lo, set_hi), fill = BUILDING_STYLE[setting.environment]
    rows = []
    for side in (-1, 1):
        x = start + rng.uniform(0, 10)
        while x < stop:
            length = rng.uniform(len_lo, len_hi)
            if rng.random() < fill and free(x, x + length):
                depth, height = rng.uniform(dep_lo, dep_hi), rng.uniform(h_lo, h_hi)
                rows.append((x + length / 2, side * (front + rng.uniform(set_lo, set_hi) + depth / 2), length, depth,
                             height, side))
            x += length + (rng.uniform(0.0, 1.5) if setting.environment == "urban" else rng.uniform(4.0, 20.0))
    return rows


def _arm_rows(rng: np.random.Generator, setting: Setting, layout: RoadLayout, front: float):
    """Buildings along the side arms of junctions: bottom centres (n, 3), yaws (n,) and rows."""
    bases, yaws, rows = [], [], []
    for site in layout.junctions:
        for arm in site.arm_headings:
            along = np.array([np.cos(arm), np.sin(arm)])
            left = np.array([-along[1], along[0]])
            for x, y, *rest in _building_rows(rng, setting, site.half_size + 16.0, site.half_size + 80.0, front,
                                              lambda a, b: True):
                bases.append(np.r_[site.centre + x * along + y * left, 0.0])
                yaws.append(arm)
                rows.append((x, y, *rest))
    return bases, yaws, rows


def buildings(rng: np.random.Generator, setting: Setting, layout: RoadLayout, lights_on: bool) -> Mesh:
    """Rows of buildings on both sides of the route and of junction arms: urban blocks are tall
    and close, suburban houses and rural farms have pitched roofs and set-backs, highways have
    almost none."""
    front = _roadside(setting, layout)
    rows = _building_rows(rng, setting, 0.0, layout.path.length, front,
                          lambda a, b: bool(_free(layout, np.array([a, b]), 16.0).all()))
    base, yaw = (_frame_at(layout, [r[0] for r in rows], [r[1] for r in rows]) if rows
                 else (np.zeros((0, 3)), np.zeros(0)))
    if setting.environment in ("urban", "suburban"):
        arm_bases, arm_yaws, arm_rows = _arm_rows(rng, setting, layout, front)
        if arm_rows:
            base, yaw, rows = np.r_[base, np.array(arm_bases)], np.r_[yaw, arm_yaws], rows + arm_rows
    if not rows:
        return Mesh.empty()
    _, _, length, depth, height, side = (np.array(c) for c in zip(*rows))
    sizes = np.stack([length, depth, height], 1)
    wall = FACADES[rng.integers(0, len(FACADES), len(rows))] * rng.uniform(0.85, 1.05, (len(rows), 1))
    body = solids(box_vertices(base, yaw, sizes), wall)
    body.colour[:, 1] *= 0.75  # flat roofs read darker than walls
    windows = []
    for i in range(len(rows)):
        towards_road = LEFT if side[i] < 0 else RIGHT
        bands = setting.environment == "urban" and rng.random() < 0.3
        windows.append(_window_grid(i, towards_road, length[i], height[i], rng, lights_on, bands))
        for face in (FRONT, BACK):
            windows.append(_window_grid(i, face, depth[i], height[i], rng, lights_on, bands))
    pitched = np.flatnonzero(height < 9) if setting.environment != "urban" else np.zeros(0, int)
    roof_size = np.c_[length[pitched] * 1.04, depth[pitched] * 1.1, rng.uniform(2.0, 3.5, len(pitched))]
    roof_base = base[pitched] + np.c_[np.zeros((len(pitched), 2)), height[pitched]]
    roof = solids(box_vertices(roof_base, yaw[pitched], roof_size, top_scale=np.tile([0.75, 0.02], (len(pitched), 1))),
                  ROOFS[rng.integers(0, len(ROOFS), len(pitched))])
    return Mesh.concat([Mesh(body, Decals.concat(windows)), Mesh(roof)])


def trees(rng: np.random.Generator, setting: Setting, layout: RoadLayout, snowy: bool) -> Mesh:
    """Street trees and roadside trees: a trunk and 2–3 overlapping crown spheres (conifers: a
    stack of shrinking spheres)."""
    env = setting.environment
    spacing, near, far = {"urban": (18.0, 0.0, 0.0), "suburban": (9.0, 2.0, 14.0), "rural": (7.0, 3.0, 30.0),
                          "highway": (8.0, 8.0, 40.0)}[env]
    start = _roadside(setting, layout)
    kerb = layout.geometry.edge + layout.geometry.shoulder + KERB_WIDTH
    s_all = np.arange(rng.uniform(0, spacing), layout.path.length, spacing)
    s_all = np.repeat(s_all, 2) + rng.uniform(-spacing / 3, spacing / 3, 2 * len(s_all))
    side = np.tile([-1.0, 1.0], len(s_all) // 2)
    keep = _free(layout, s_all, 12.0) & (rng.random(len(s_all)) < (0.5 if env == "urban" else 0.7))
    s_all, side = s_all[keep], side[keep]
    if env == "urban":
        dist = np.full(len(s_all), kerb + 0.9)  # in the sidewalk, near the kerb
    else:
        dist = start + near + rng.exponential((far - near) / 3 + 1e-6, len(s_all))
    base, _ = _frame_at(layout, s_all, side * dist)
    n = len(base)
    trunk_h = rng.uniform(1.5, 3.0, n)
    crown_r = rng.uniform(1.4, 3.2, n)
    conifer = rng.random(n) < (0.1 if env in ("urban", "suburban") else 0.4)
    trunk = solids(box_vertices(base, rng.uniform(0, np.pi, n),
                                np.c_[np.full(n, 0.3), np.full(n, 0.3), trunk_h + crown_r]),
                   TRUNK * rng.uniform(0.8, 1.2, (n, 1)))
    centres, radii, colours = [], [], []
    leaf = LEAVES[rng.integers(0, len(LEAVES), n)] * rng.uniform(0.85, 1.15, (n, 1))
    if snowy:
        leaf = leaf * 0.6 + 0.35
    for k in range(3):
        shrink = np.where(conifer, 1.0 - 0.28 * k, rng.uniform(0.6, 0.9, n))
        r = crown_r * shrink
        up = np.where(conifer, trunk_h + crown_r * (0.6 + 0.9 * k), trunk_h + crown_r * rng.uniform(0.7, 1.3, n))
        jitter = np.where(conifer[:, None], 0.0, rng.uniform(-0.6, 0.6, (n, 2)) * crown_r[:, None])
        centres.append(base + np.c_[jitter, up])
        radii.append(r)
        colours.append(np.clip(leaf * rng.uniform(0.8, 1.2, (n, 1)), 0, 1))
    crowns = spheres(np.concatenate(centres), np.concatenate(radii), np.concatenate(colours))
    return Mesh(trunk, spheres=crowns)


def lamps(rng: np.random.Generator, setting: Setting, layout: RoadLayout, lights_on: bool) -> Mesh:
    """Street lamps (urban, suburban) every ~30 m on both kerbs: pole, arm over the road, lamp."""
    if setting.environment not in ("urban", "suburban"):
        return Mesh.empty()
    kerb = layout.geometry.edge + layout.geometry.shoulder + KERB_WIDTH + 0.4
    s_all = np.arange(rng.uniform(0, 30), layout.path.length, 30.0)
    s_all = s_all[_free(layout, s_all, 3.0)]
    side = np.where(np.arange(len(s_all)) % 2 == 0, -1.0, 1.0)
    base, yaw = _frame_at(layout, s_all, side * kerb)
    n, height = len(base), 7.5
    pole = box_vertices(base, yaw, np.tile([0.18, 0.18, height], (n, 1)))
    arm_base, _ = _frame_at(layout, s_all, side * (kerb - 0.9), height - 0.15)
    arm = box_vertices(arm_base, yaw, np.tile([0.12, 2.0, 0.12], (n, 1)))
    head, _ = _frame_at(layout, s_all, side * (kerb - 1.7), height - 0.3)
    glow = LAMP_GLOW if lights_on else METAL * 1.3
    return Mesh(solids(np.concatenate([pole, arm]), np.tile(METAL, (2 * n, 1))),
                spheres=spheres(head, 0.28, glow, emissive=lights_on))


def speed_signs(setting: Setting, layout: RoadLayout) -> Mesh:
    """Speed-limit signs on the own kerb ahead of the ego start and after every junction: a pole
    and a plate facing oncoming drivers (red-ringed in km/h countries, white in mph ones)."""
    geo = layout.geometry
    s_all = np.array([EGO_START + 45.0] + [j.s_exit + 25.0 for j in layout.junctions])
    s_all = s_all[s_all < layout.path.length - 5]
    d = geo.drive_sign * (_roadside(setting, layout) - 0.6 if setting.sidewalk else geo.edge + geo.shoulder + 1.0)
    base, yaw = _frame_at(layout, s_all, d)
    n = len(base)
    pole = box_vertices(base, yaw, np.tile([0.08, 0.08, 2.2], (n, 1)))
    metric = COUNTRIES[setting.country].speed_unit == "km/h"
    plate = box_vertices(base + [0, 0, 2.1], yaw, np.tile([0.06, 0.75, 0.75] if metric else [0.06, 0.6, 0.8], (n, 1)))
    ring = [0.75, 0.1, 0.1] if metric else [0.1, 0.1, 0.1]
    mesh = Mesh(solids(np.concatenate([pole, plate]), np.r_[np.tile(METAL, (n, 1)), np.tile(ring, (n, 1))]))
    face_idx = np.arange(n, 2 * n)
    mesh.decals = Decals.concat([decals(face_idx, BACK, [0.15, 0.15, 0.85, 0.85], [0.95, 0.95, 0.95]),
                                 decals(face_idx, BACK, [0.3, 0.45, 0.7, 0.55], [0.1, 0.1, 0.1])])
    return mesh


def guard_rails(rng: np.random.Generator, setting: Setting, layout: RoadLayout) -> Mesh:
    """Steel rails along highway shoulders and medians (and some rural roads), as 8 m pieces."""
    if setting.environment != "highway" and not (setting.environment == "rural" and rng.random() < 0.3):
        return Mesh.empty()
    geo = layout.geometry
    offsets = [geo.edge + geo.shoulder + 0.4]
    if geo.median > 0:
        offsets.append(geo.median / 2 - 0.5)
    s_all = np.arange(0.0, layout.path.length - 8.0, 8.0) + 4.0
    s_all = s_all[_free(layout, s_all, 10.0)]
    parts = []
    for off in offsets:
        for side in (-1, 1):
            base, yaw = _frame_at(layout, s_all, side * off, 0.45)
            parts.append(box_vertices(base, yaw, np.tile([8.05, 0.12, 0.32], (len(base), 1))))
    verts = np.concatenate(parts)
    return Mesh(solids(verts, np.tile(METAL * 1.3, (len(verts), 1))))


def hedges(rng: np.random.Generator, setting: Setting, layout: RoadLayout, snowy: bool) -> Mesh:
    """Front-garden hedges along suburban sidewalks."""
    if setting.environment != "suburban":
        return Mesh.empty()
    front = _roadside(setting, layout) + 0.6
    rows = []
    for side in (-1, 1):
        s = rng.uniform(0, 8)
        while s < layout.path.length:
            length = rng.uniform(4.0, 14.0)
            if rng.random() < 0.5 and _free(layout, np.array([s, s + length]), 14.0).all():
                rows.append((s + length / 2, side * front, length))
            s += length + rng.uniform(2.0, 10.0)
    if not rows:
        return Mesh.empty()
    s_mid, d, length = (np.array(c) for c in zip(*rows))
    base, yaw = _frame_at(layout, s_mid, d)
    n = len(base)
    colour = LEAVES[rng.integers(0, len(LEAVES), n)] * 0.9
    return Mesh(solids(box_vertices(base, yaw, np.c_[length, np.full(n, 0.8), rng.uniform(0.9, 1.5, n)]),
                       colour * 0.6 + 0.35 if snowy else colour))


def build_scenery(rng: np.random.Generator, setting: Setting, layout: RoadLayout, lights_on: bool) -> Mesh:
    """All static roadside objects of a clip."""
    snowy = setting.weather == "snow"
    return Mesh.concat([buildings(rng, setting, layout, lights_on), trees(rng, setting, layout, snowy),
                        lamps(rng, setting, layout, lights_on), speed_signs(setting, layout),
                        guard_rails(rng, setting, layout), hedges(rng, setting, layout, snowy)])
