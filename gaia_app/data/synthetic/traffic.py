"""Populating the synthetic world: agent sizes, colours and speeds, random traffic, pedestrians,
parked cars and cross traffic, plus explicitly placed agents (`AgentSpec`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gaia_app.data.clip import AGENT_CATEGORIES
from gaia_app.data.synthetic.road import CROSSING_HALF_LENGTH, RoadLayout
from gaia_app.data.synthetic.world import BUS, CAR, CYCLIST, PEDESTRIAN, TRUCK, Agents, CrossRoad

SIZE_RANGES = {  # category: ((length lo, hi), (width lo, hi), (height lo, hi)) in metres
    CAR: ((3.9, 4.9), (1.7, 1.95), (1.4, 1.65)),
    BUS: ((10.5, 12.5), (2.5, 2.55), (3.0, 3.3)),
    TRUCK: ((7.5, 11.0), (2.45, 2.55), (3.3, 3.9)),
    CYCLIST: ((1.7, 1.8), (0.6, 0.7), (1.7, 1.8)),
    PEDESTRIAN: ((0.35, 0.45), (0.55, 0.65), (1.55, 1.9)),
}
VEHICLE_COLOURS = np.array([  # RGB 0..1: white, black, silver, grey, red, blue, navy, green, beige, yellow
    [0.92, 0.92, 0.9], [0.08, 0.08, 0.09], [0.72, 0.73, 0.75], [0.42, 0.43, 0.45], [0.72, 0.1, 0.1],
    [0.15, 0.3, 0.65], [0.1, 0.13, 0.3], [0.15, 0.4, 0.25], [0.75, 0.68, 0.55], [0.9, 0.75, 0.15]])
VEHICLE_COLOUR_P = np.array([0.2, 0.18, 0.16, 0.12, 0.08, 0.08, 0.06, 0.04, 0.05, 0.03])
BUS_COLOURS = np.array([[0.8, 0.12, 0.1], [0.95, 0.78, 0.1], [0.2, 0.45, 0.75], [0.9, 0.9, 0.88], [0.2, 0.55, 0.3]])
CLOTHES = np.array([[0.1, 0.1, 0.12], [0.2, 0.25, 0.45], [0.6, 0.1, 0.1], [0.85, 0.85, 0.8], [0.35, 0.3, 0.25],
                    [0.2, 0.45, 0.3], [0.9, 0.55, 0.1], [0.5, 0.5, 0.55]])


@dataclass(frozen=True)
class AgentSpec:
    """One explicitly placed agent, relative to the ego at t=0.

    category: a name from AGENT_CATEGORIES; gap: metres from the ego front bumper to the agent's
    rear along the route (negative = behind the ego); lane: own-direction lane index (None = the
    ego lane); oncoming: drive against the ego; d: absolute lateral offset from the centreline (m),
    overriding lane; speed: m/s (None = its desired speed); parked: never moves.
    """

    category: str
    gap: float
    lane: int | None = None
    oncoming: bool = False
    d: float | None = None
    speed: float | None = None
    parked: bool = False

    def __post_init__(self) -> None:
        if self.category not in AGENT_CATEGORIES:
            raise ValueError(f"AgentSpec.category: expected one of {AGENT_CATEGORIES}, got {self.category!r}")


def _draw_sizes(rng: np.random.Generator, category: np.ndarray) -> np.ndarray:
    size = np.zeros((len(category), 3))
    for c, ranges in SIZE_RANGES.items():
        sel = category == c
        for k, (lo, hi) in enumerate(ranges):
            size[sel, k] = rng.uniform(lo, hi, sel.sum())
    return size


def _draw_colours(rng: np.random.Generator, category: np.ndarray) -> np.ndarray:
    n = len(category)
    colours = VEHICLE_COLOURS[rng.choice(len(VEHICLE_COLOURS), n, p=VEHICLE_COLOUR_P)]
    bus = category == BUS
    colours[bus] = BUS_COLOURS[rng.integers(0, len(BUS_COLOURS), bus.sum())]
    people = (category == PEDESTRIAN) | (category == CYCLIST)
    colours[people] = CLOTHES[rng.integers(0, len(CLOTHES), people.sum())]
    return np.clip(colours * rng.uniform(0.85, 1.1, (n, 1)), 0, 1)


def make_agents(rng: np.random.Generator, category, path, direction, s, d, v_desired, *, speed=None,
                parked=None, crosser=None, cross_t0=None, first_id: int = 0) -> Agents:
    """Agents with drawn sizes/colours; array arguments have one entry per agent."""
    category = np.asarray(category, dtype=np.int64)
    n = len(category)
    v_desired = np.asarray(v_desired, dtype=np.float64)
    parked = np.zeros(n, bool) if parked is None else np.asarray(parked, bool)
    return Agents(
        category=category, size=_draw_sizes(rng, category), colour=_draw_colours(rng, category),
        track_id=np.arange(first_id, first_id + n), path=np.asarray(path, np.int64),
        direction=np.asarray(direction, np.int64), s=np.asarray(s, np.float64), d=np.asarray(d, np.float64),
        v=np.where(parked, 0.0, v_desired if speed is None else np.asarray(speed, np.float64)),
        v_desired=v_desired, a_max=rng.uniform(1.0, 2.5, n), parked=parked,
        crosser=np.zeros(n, bool) if crosser is None else np.asarray(crosser, bool),
        cross_t0=np.full(n, np.inf) if cross_t0 is None else np.asarray(cross_t0, np.float64),
        phase=rng.uniform(0, 2 * np.pi, n))


def spawn_lane_traffic(rng: np.random.Generator, layout: RoadLayout, window: tuple[float, float], density: float,
                       limit: float, mix: dict[int, float], keep_clear: list[tuple[float, float, float]]) -> dict:
    """Vehicles on every route lane in the s window, spaced by at least a 1.5 s headway.

    limit: speed limit (m/s); mix: category → probability (cyclists ride only in the kerb lane,
    0.8 m from the kerb); keep_clear: (s_from, s_to, d) corridors left empty (the ego's lanes).
    Returns make_agents keyword arrays.
    """
    geo = layout.geometry
    cats, dirs, ss, ds, vs = [], [], [], [], []
    for oncoming in (False, True):
        for lane in range(geo.lanes):
            names = [c for c in mix if lane == 0 or c != CYCLIST]
            probs = np.array([mix[c] for c in names]) / sum(mix[c] for c in names)
            d_lane = float(geo.lane_offset(lane, oncoming))
            speed = limit * rng.uniform(0.75, 1.0) * (1.0 if oncoming else 0.93 ** lane)
            s = window[0] + rng.exponential(40.0 / density)
            while s < window[1]:
                cat = names[rng.choice(len(names), p=probs)]
                d = d_lane + np.sign(d_lane) * (geo.lane_width / 2 - 0.8) if cat == CYCLIST else d_lane
                in_corridor = any(lo - 8 < s < hi + 8 and abs(d - dc) < 1.5 for lo, hi, dc in keep_clear)
                if not in_corridor and not layout.in_junction(np.array(s)):
                    cats.append(cat)
                    dirs.append(-1 if oncoming else 1)
                    ss.append(s)
                    ds.append(d)
                    vs.append(rng.uniform(4.0, 6.5) if cat == CYCLIST else speed * rng.uniform(0.9, 1.05))
                s += 14.0 + 1.5 * speed + rng.exponential(45.0 / density)
    return dict(category=cats, path=np.zeros(len(cats)), direction=dirs, s=ss, d=ds, v_desired=vs)


def spawn_parked(rng: np.random.Generator, layout: RoadLayout, window: tuple[float, float], occupancy: float) -> dict:
    """Parked cars in the parking strips on both kerbs (every ~6.5 m slot, with `occupancy`)."""
    geo = layout.geometry
    slots = np.arange(window[0], window[1], 6.5)
    blocked = layout.in_junction(slots)
    for c in layout.crossings:
        blocked |= np.abs(slots - c) < CROSSING_HALF_LENGTH + 8
    for j in layout.junctions:
        blocked |= (slots > j.stop_s - 15) & (slots < j.s_exit + 10)
    s_all, d_all = [], []
    for side in (-1, 1):
        keep = ~blocked & (rng.random(len(slots)) < occupancy)
        s_all += list(slots[keep] + rng.uniform(-0.5, 0.5, keep.sum()))
        d_all += [side * (geo.edge + geo.shoulder / 2)] * int(keep.sum())
    n = len(s_all)
    dirs = np.where(np.array(d_all) * geo.drive_sign > 0, 1, -1) if n else np.zeros(0)
    return dict(category=[CAR] * n, path=np.zeros(n), direction=dirs, s=s_all, d=d_all, v_desired=np.zeros(n),
                parked=np.ones(n, bool))


def spawn_pedestrians(rng: np.random.Generator, layout: RoadLayout, window: tuple[float, float], density: float,
                      sidewalk_d: float, duration: float) -> dict:
    """Walkers on both sidewalks and people crossing at each zebra crossing in the window."""
    n_walk = rng.poisson(density * (window[1] - window[0]) / 14.0)
    side = rng.choice([-1, 1], n_walk)
    s = list(rng.uniform(*window, n_walk))
    d = list(side * (sidewalk_d + rng.uniform(-0.6, 0.6, n_walk)))
    dirs = list(rng.choice([-1, 1], n_walk))
    crosser, t0 = [False] * n_walk, [np.inf] * n_walk
    far = layout.geometry.edge + layout.geometry.shoulder + 1.0
    for c in layout.crossings:
        if not window[0] < c < window[1]:
            continue
        for _ in range(rng.integers(0, 4)):
            way = int(rng.choice([-1, 1]))
            s.append(c + rng.uniform(-1.2, 1.2))
            d.append(-way * far)
            dirs.append(way)
            crosser.append(True)
            t0.append(rng.uniform(-4.0, duration + 2.0))
    n = len(s)
    # A crosser already under way at t=0 starts part-way over the road.
    for i in range(n_walk, n):
        if t0[i] < 0:
            d[i] = float(np.clip(d[i] + dirs[i] * 1.3 * -t0[i], -far, far))
    return dict(category=[PEDESTRIAN] * n, path=np.zeros(n), direction=dirs, s=s, d=d,
                v_desired=rng.uniform(1.0, 1.6, n), crosser=crosser, cross_t0=t0)


def spawn_cross_traffic(rng: np.random.Generator, cross_roads: list[CrossRoad], layout: RoadLayout,
                        density: float) -> dict:
    """A few cars on each direction of every cross road (they obey the cross phase)."""
    geo = layout.geometry
    cats, paths, dirs, ss, ds, vs = [], [], [], [], [], []
    for k, road in enumerate(cross_roads):
        half = layout.junctions[road.junction].half_size
        for direction in (-1, 1):
            offset = half + 3.0
            for _ in range(rng.poisson(2.0 * density)):
                offset += rng.uniform(7.0, 30.0)
                cats.append(int(rng.choice([CAR, CAR, CAR, TRUCK, BUS])))
                paths.append(k + 1)
                dirs.append(direction)
                ss.append(road.centre_s - direction * offset)
                ds.append(float(geo.lane_offset(0, direction < 0)))
                vs.append(rng.uniform(8.0, 13.0))
    return dict(category=cats, path=paths, direction=dirs, s=ss, d=ds, v_desired=vs)


def place_specs(rng: np.random.Generator, specs: list[AgentSpec], layout: RoadLayout, ego_s: float,
                ego_front: float, ego_lane: int, first_id: int) -> Agents:
    """Agents for explicitly specified AgentSpecs: the nearest end of each sits `gap` m ahead of
    the ego's front bumper along the route."""
    geo = layout.geometry
    cats, dirs, ds, vs, parked = [], [], [], [], []
    for spec in specs:
        lane = ego_lane if spec.lane is None else spec.lane
        if not 0 <= lane < geo.lanes:
            raise ValueError(f"AgentSpec.lane: expected 0..{geo.lanes - 1}, got {lane}")
        cat = AGENT_CATEGORIES.index(spec.category)
        cats.append(cat)
        dirs.append(-1 if spec.oncoming else 1)
        parked.append(spec.parked)
        ds.append(float(geo.lane_offset(lane, spec.oncoming)) if spec.d is None else spec.d)
        default_speed = 1.3 if cat == PEDESTRIAN else 5.0 if cat == CYCLIST else 12.0
        vs.append(0.0 if spec.parked else default_speed if spec.speed is None else spec.speed)
    n = len(cats)
    agents = make_agents(rng, cats, np.zeros(n), dirs, np.zeros(n), ds, vs, parked=parked, first_id=first_id)
    gaps = np.array([spec.gap for spec in specs], dtype=np.float64)
    agents.s[:] = ego_s + ego_front + gaps + agents.size[:, 0] / 2
    return agents
