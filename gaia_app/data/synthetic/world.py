"""Traffic of the synthetic world: traffic lights and agents with their own motion.

Agents live in Frenet coordinates on a path (the route, or a cross road through a junction):
s (m along the path), d (m to its left), direction ±1 along s. Vehicles and cyclists follow
their lane with the Intelligent Driver Model (IDM), stop at red and amber lights and in front of
occupied zebra crossings, brake now and then, and change lanes. Pedestrians walk along the
sidewalks or cross at zebra crossings. Everything is vectorised over agents.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gaia_app.data.clip import AGENT_CATEGORIES
from gaia_app.data.synthetic.road import CROSSING_HALF_LENGTH, LaneGeometry, Path, RoadLayout

CAR, BUS, TRUCK, CYCLIST, PEDESTRIAN = (AGENT_CATEGORIES.index(c)
                                        for c in ("car", "bus", "truck", "cyclist", "pedestrian"))
AMBER_SECONDS = 3.0
ALL_RED_SECONDS = 1.0
IDM_MIN_GAP = 2.0
"""IDM jam distance s0 (m)."""
IDM_HEADWAY = 1.4
"""IDM time headway T (s)."""
LANE_CHANGE_RATE = 1 / 40.0
"""Lane changes per vehicle per second (Poisson)."""
BRAKE_EVENT_RATE = 1 / 30.0
"""Spontaneous braking events per vehicle per second."""


@dataclass(frozen=True)
class LightCycle:
    """A fixed-time signal: own direction green for `green` s, amber, then red while the cross road runs.

    Opposing route traffic shares the own phase; the cross road gets green after an all-red gap.
    """

    green: float
    offset: float

    @property
    def period(self) -> float:
        return 2 * (self.green + AMBER_SECONDS + ALL_RED_SECONDS)

    def state(self, t: float, cross: bool = False) -> str:
        """'green', 'amber' or 'red' at time t (s) for the route (or the cross road)."""
        phase = (t + self.offset) % self.period
        if cross:
            phase = (phase - self.period / 2) % self.period
        if phase < self.green:
            return "green"
        return "amber" if phase < self.green + AMBER_SECONDS else "red"

    @classmethod
    def starting(cls, green: float, state: str, elapsed: float) -> "LightCycle":
        """A cycle that shows `state` to the route at t=0, `elapsed` seconds into that state."""
        start = {"green": 0.0, "amber": green, "red": green + AMBER_SECONDS}[state]
        return cls(green, start + elapsed)


@dataclass
class CrossRoad:
    """A straight cross road through a junction: its path, the route junction index, and the
    cross-path s of the junction centre."""

    path: Path
    junction: int
    centre_s: float


@dataclass
class Agents:
    """All agents of a clip as arrays of length n (structure of arrays).

    category: AGENT_CATEGORIES index; size: (n, 3) length, width, height (m); colour: (n, 3)
    RGB floats 0..1; track_id; path: 0 = route, k = cross road k-1; direction ±1; s, d, v
    (m, m, m/s); v_desired (m/s); a_max (m/s²); parked (never moves); walker / crosser roles for
    pedestrians; lane change (d_from, d_to, change_t0, change_len); brake events (brake_t0,
    brake_len); cross_t0 (time a crosser steps onto the road); phase (gait, rad).
    """

    category: np.ndarray
    size: np.ndarray
    colour: np.ndarray
    track_id: np.ndarray
    path: np.ndarray
    direction: np.ndarray
    s: np.ndarray
    d: np.ndarray
    v: np.ndarray
    v_desired: np.ndarray
    a_max: np.ndarray
    parked: np.ndarray
    crosser: np.ndarray
    cross_t0: np.ndarray
    d_from: np.ndarray = field(default=None)  # type: ignore[assignment]
    d_to: np.ndarray = field(default=None)  # type: ignore[assignment]
    change_t0: np.ndarray = field(default=None)  # type: ignore[assignment]
    change_len: np.ndarray = field(default=None)  # type: ignore[assignment]
    brake_t0: np.ndarray = field(default=None)  # type: ignore[assignment]
    brake_len: np.ndarray = field(default=None)  # type: ignore[assignment]
    accel: np.ndarray = field(default=None)  # type: ignore[assignment]
    phase: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        n = len(self.s)
        for name in ("d_from", "d_to"):
            if getattr(self, name) is None:
                setattr(self, name, self.d.copy())
        for name, value in (("change_t0", -np.inf), ("change_len", 1.0), ("brake_t0", np.inf),
                            ("brake_len", 0.0), ("accel", 0.0), ("phase", 0.0)):
            if getattr(self, name) is None:
                setattr(self, name, np.full(n, value))

    def __len__(self) -> int:
        return len(self.s)

    @property
    def is_pedestrian(self) -> np.ndarray:
        return self.category == PEDESTRIAN

    @property
    def is_vehicle(self) -> np.ndarray:
        """Lane users: cars, buses, trucks and cyclists."""
        return self.category != PEDESTRIAN

    def lane_change_progress(self, t: float) -> np.ndarray:
        """(n,) progress 0..1 of each agent's latest lane change at time t."""
        return np.clip((t - self.change_t0) / self.change_len, 0.0, 1.0)

    def lateral_rate(self, t: float) -> np.ndarray:
        """(n,) lateral speed (m/s, +d) from lane changes (derivative of the smoothstep profile)."""
        u = self.lane_change_progress(t)
        return (self.d_to - self.d_from) * 6 * u * (1 - u) / self.change_len

    def indicator(self, t: float) -> np.ndarray:
        """(n,) turn signal during a lane change: +1 left, -1 right, 0 off."""
        u = self.lane_change_progress(t)
        active = (u > 0) & (u < 1)
        return np.where(active, np.sign(self.d_to - self.d_from) * self.direction, 0).astype(np.int64)

    @classmethod
    def concat(cls, parts: list["Agents"]) -> "Agents":
        names = [f for f in cls.__dataclass_fields__]
        return cls(**{f: np.concatenate([getattr(p, f) for p in parts]) for f in names})


@dataclass
class Ego:
    """Ego state on the route: pose (x, y, yaw) in the world, speed (m/s), Frenet (s, d).
    Its origin is the rear axle; length/width of its footprint; front bumper `front` m ahead."""

    x: float
    y: float
    yaw: float
    v: float
    s: float
    d: float
    length: float = 4.7
    width: float = 1.9
    front: float = 3.7

    @property
    def centre_s(self) -> float:
        """Route s of the footprint centre."""
        return self.s + self.front - self.length / 2


@dataclass
class World:
    """Everything that moves in one clip: route layout, cross roads, lights, agents."""

    layout: RoadLayout
    cross_roads: list[CrossRoad]
    lights: list[LightCycle | None]
    agents: Agents
    rng: np.random.Generator

    @property
    def geometry(self) -> LaneGeometry:
        return self.layout.geometry

    def light_state(self, junction: int, t: float, cross: bool = False) -> str | None:
        cycle = self.lights[junction]
        return None if cycle is None else cycle.state(t, cross)

    # ------------------------------------------------------------ obstacles

    def stop_obstacles(self, t: float, path: int, direction: int, s: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Distance (m, along travel) to the nearest point each traveller must stop at: red lights,
        amber lights it can still stop for, occupied zebra crossings. inf when none. s, v: (n,)."""
        best = np.full(len(s), np.inf)
        for stop, state in self._stop_lines(t, path, direction):
            ahead = direction * (stop - s)
            stoppable = ahead > v * v / (2 * 6.0) if state == "amber" else ahead > -1.0
            hit = (ahead > -1.0) & stoppable
            best = np.where(hit, np.minimum(best, ahead), best)
        if path == 0:
            for c in self.occupied_crossings(t):
                stop = c - direction * (CROSSING_HALF_LENGTH + 1.5)
                ahead = direction * (stop - s)
                best = np.where(ahead > -0.5, np.minimum(best, ahead), best)
        return best

    def _stop_lines(self, t: float, path: int, direction: int) -> list[tuple[float, str]]:
        out = []
        if path == 0:
            for j, site in enumerate(self.layout.junctions):
                state = self.light_state(j, t)
                if state in ("red", "amber"):
                    out.append((site.stop_s if direction > 0 else site.stop_s_oncoming, state))
        else:
            road = self.cross_roads[path - 1]
            state = self.light_state(road.junction, t, cross=True)
            if state in ("red", "amber"):
                half = self.layout.junctions[road.junction].half_size + 1.0
                out.append((road.centre_s - direction * half, state))
        return out

    def occupied_crossings(self, t: float) -> list[float]:
        """Route s of zebra crossings with a pedestrian on (or stepping onto) the carriageway."""
        a = self.agents
        edge = self.geometry.edge + self.geometry.shoulder + 0.5
        busy = a.crosser & (a.cross_t0 <= t + 1.5) & (np.abs(a.d) < edge) & (a.path == 0)
        return sorted({c for c in self.layout.crossings if np.any(busy & (np.abs(a.s - c) < CROSSING_HALF_LENGTH + 1))})

    # ------------------------------------------------------------ dynamics

    def step(self, t: float, dt: float, ego: Ego) -> None:
        """Advance every agent from t to t+dt; `ego` is an obstacle for route traffic."""
        a = self.agents
        moving = ~a.parked
        self._update_lane_changes(t, dt)
        self._update_brake_events(t, dt)
        vehicles = np.flatnonzero(a.is_vehicle & moving)
        accel = self._vehicle_accel(t, vehicles, ego)
        a.accel[:] = 0.0
        a.accel[vehicles] = accel
        a.v[vehicles] = np.maximum(0.0, a.v[vehicles] + accel * dt)
        a.s[vehicles] += a.direction[vehicles] * a.v[vehicles] * dt
        self._walk(t, dt)
        a.phase += np.where(a.is_pedestrian, a.v * dt * 3.5, a.v * dt / 0.35)

    def _leaders(self, idx: np.ndarray, ego: Ego) -> tuple[np.ndarray, np.ndarray]:
        """Gap (m, bumper to bumper) and speed of the nearest lane user ahead of each agent in idx."""
        a = self.agents
        others = np.flatnonzero(a.is_vehicle)
        s_o = np.r_[a.s[others], ego.centre_s]
        d_o = np.r_[a.d[others], ego.d]
        len_o = np.r_[a.size[others, 0], ego.length]
        wid_o = np.r_[a.size[others, 1], ego.width]
        v_o = np.r_[a.v[others] * a.direction[others], ego.v]
        path_o = np.r_[a.path[others], 0]
        dir_o = np.r_[a.direction[others], 1]
        me = idx[:, None]
        ahead = a.direction[me] * (s_o[None] - a.s[me]) - (a.size[me, 0] + len_o[None]) / 2
        overlap = np.abs(d_o[None] - a.d[me]) < (a.size[me, 1] + wid_o[None]) / 2 + 0.3
        same = (path_o[None] == a.path[me]) & (dir_o[None] == a.direction[me]) & overlap
        same &= np.r_[others, -1][None] != me
        valid = same & (ahead > -0.5)
        gap = np.where(valid, ahead, np.inf)
        j = np.argmin(gap, axis=1)
        rows = np.arange(len(idx))
        return gap[rows, j], np.abs(v_o[j])

    def _vehicle_accel(self, t: float, idx: np.ndarray, ego: Ego) -> np.ndarray:
        a = self.agents
        if len(idx) == 0:
            return np.zeros(0)
        gap, v_lead = self._leaders(idx, ego)
        for path in np.unique(a.path[idx]):
            for direction in (-1, 1):
                sel = (a.path[idx] == path) & (a.direction[idx] == direction)
                if np.any(sel):
                    k = idx[sel]
                    stop = self.stop_obstacles(t, int(path), direction, a.s[k] + direction * a.size[k, 0] / 2, a.v[k])
                    closer = stop < gap[sel]
                    gap[sel] = np.where(closer, stop, gap[sel])
                    v_lead[sel] = np.where(closer, 0.0, v_lead[sel])
        braking = (t >= a.brake_t0[idx]) & (t < a.brake_t0[idx] + a.brake_len[idx])
        v_des = np.where(braking, 0.35 * a.v_desired[idx], a.v_desired[idx])
        return idm_accel(a.v[idx], v_des, gap, v_lead, a.a_max[idx])

    def _update_lane_changes(self, t: float, dt: float) -> None:
        a, geo = self.agents, self.geometry
        cars = np.flatnonzero((a.category <= TRUCK) & ~a.parked & (a.path == 0) & (t > a.change_t0 + a.change_len))
        start = cars[self.rng.random(len(cars)) < LANE_CHANGE_RATE * dt]
        for i in start:
            lane, oncoming = geo.lane_of(a.d[i])
            target = lane + self.rng.choice([-1, 1])
            if 0 <= target < geo.lanes and self._lane_free(i, float(geo.lane_offset(target, oncoming))):
                a.d_from[i], a.d_to[i] = a.d[i], geo.lane_offset(target, oncoming)
                a.change_t0[i], a.change_len[i] = t, self.rng.uniform(3.0, 5.0)
        u = a.lane_change_progress(t)
        changing = a.is_vehicle & ~a.parked
        a.d[:] = np.where(changing, a.d_from + (a.d_to - a.d_from) * (3 * u * u - 2 * u ** 3), a.d)

    def _update_brake_events(self, t: float, dt: float) -> None:
        """Now and then a driver slows to a third of its desired speed for 1.5–4 s (brake lights)."""
        a = self.agents
        braking = (t >= a.brake_t0) & (t < a.brake_t0 + a.brake_len)
        idle = np.flatnonzero(a.is_vehicle & ~a.parked & ~braking)
        start = idle[self.rng.random(len(idle)) < BRAKE_EVENT_RATE * dt]
        a.brake_t0[start], a.brake_len[start] = t, self.rng.uniform(1.5, 4.0, len(start))

    def _lane_free(self, i: int, d_target: float) -> bool:
        a = self.agents
        near = (a.is_vehicle & (a.path == a.path[i]) & (np.abs(a.d - d_target) < 1.5)
                & (np.abs(a.s - a.s[i]) < 12 + a.v[i]))
        return not np.any(near)

    def _walk(self, t: float, dt: float) -> None:
        a = self.agents
        walkers = a.is_pedestrian & ~a.crosser & ~a.parked
        a.s[walkers] += a.direction[walkers] * a.v[walkers] * dt
        crossing = a.crosser & (t >= a.cross_t0)
        far_side = self.geometry.edge + self.geometry.shoulder + 1.2
        done = crossing & (np.sign(a.d) == a.direction) & (np.abs(a.d) >= far_side)
        step = np.where(crossing & ~done, a.direction * a.v * dt, 0.0)
        a.d[:] = a.d + step
        a.crosser[done] = False  # arrived: walk on along the sidewalk


def idm_accel(v: np.ndarray, v_desired: np.ndarray, gap: np.ndarray, v_lead: np.ndarray,
              a_max: np.ndarray, b_comf: float = 2.5) -> np.ndarray:
    """Intelligent Driver Model acceleration (m/s²), clipped to [-8, a_max]. gap inf = free road."""
    v_desired = np.maximum(v_desired, 0.1)
    dv = v - v_lead
    s_star = IDM_MIN_GAP + np.maximum(0.0, v * IDM_HEADWAY + v * dv / (2 * np.sqrt(a_max * b_comf)))
    interaction = np.where(np.isfinite(gap), (s_star / np.maximum(gap, 0.1)) ** 2, 0.0)
    accel = a_max * (1 - (v / v_desired) ** 4 - interaction)
    return np.clip(accel, -8.0, a_max)
