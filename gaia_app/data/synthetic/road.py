"""Road geometry of the synthetic world: the route centreline, lanes, junctions and crossings.

World frame: x, y on the ground, z up, headings counter-clockwise from +x (radians).
The route is one centreline `Path` built from segment specs (straights, constant-curvature
curves, junctions that go straight or turn 90°). Positions on the road are Frenet coordinates
(s along the path in metres, d to the left of the centreline in metres).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

PATH_STEP = 0.5
"""Arc-length spacing (m) of the sampled centreline."""
CORNER_MARGIN = 2.0
"""Junction box half-size beyond the carriageway edge (m): room for the turning arcs."""
CROSSING_HALF_LENGTH = 2.0
"""Half the length (along s, m) of a zebra crossing."""

JUNCTION_KINDS = ("four_way", "t_junction")
TURNS = ("straight", "left", "right")


@dataclass(frozen=True)
class Straight:
    """A straight road piece of `length` metres, optionally with a zebra crossing in the middle."""

    length: float
    crossing: bool = False


@dataclass(frozen=True)
class Curve:
    """A constant-curvature piece: `length` metres at `curvature` 1/m (positive turns left)."""

    length: float
    curvature: float


@dataclass(frozen=True)
class Junction:
    """An intersection the route crosses (`turn`='straight') or turns at ('left'/'right')."""

    kind: str = "four_way"
    turn: str = "straight"
    traffic_light: bool = True
    crossing: bool = False

    def __post_init__(self) -> None:
        if self.kind not in JUNCTION_KINDS:
            raise ValueError(f"Junction.kind: expected one of {JUNCTION_KINDS}, got {self.kind!r}")
        if self.turn not in TURNS:
            raise ValueError(f"Junction.turn: expected one of {TURNS}, got {self.turn!r}")


Segment = Straight | Curve | Junction


@dataclass(frozen=True)
class LaneGeometry:
    """Cross-section of a two-way road.

    lanes: per direction; lane_width, median (gap between the directions) and shoulder (asphalt
    beyond the edge line) in metres; drive_sign: -1 when traffic keeps right (own lanes at d < 0),
    +1 when it keeps left. Lane 0 is the kerb-side lane, lanes-1 the one next to the centre.
    """

    lanes: int
    lane_width: float
    median: float = 0.0
    shoulder: float = 0.3
    drive_sign: int = -1

    @property
    def edge(self) -> float:
        """|d| of the carriageway edges (m)."""
        return self.median / 2 + self.lanes * self.lane_width

    def lane_offset(self, lane: np.ndarray | int, oncoming: np.ndarray | bool = False) -> np.ndarray:
        """Signed offset d (m) of a lane centre; oncoming lanes mirror the own lanes."""
        magnitude = self.median / 2 + (self.lanes - np.asarray(lane) - 0.5) * self.lane_width
        side = np.where(oncoming, -self.drive_sign, self.drive_sign)
        return side * magnitude

    def boundary_offset(self, boundary: int) -> float:
        """|d| of own-side lane boundary `boundary` (0 = centre/median side, lanes = kerb side)."""
        return self.median / 2 + boundary * self.lane_width

    def lane_of(self, d: float) -> tuple[int, bool]:
        """(lane index, oncoming) of a lateral offset, clamped to the carriageway."""
        oncoming = np.sign(d) == -self.drive_sign
        from_centre = (abs(d) - self.median / 2) / self.lane_width
        lane = self.lanes - 1 - int(np.clip(np.floor(from_centre), 0, self.lanes - 1))
        return lane, bool(oncoming)


class Path:
    """A sampled planar curve with arc-length parameter.

    xy: (n, 2) metres at spacing `step`; heading: (n,) radians, continuous (not wrapped);
    curvature: (n,) 1/m.
    """

    def __init__(self, xy: np.ndarray, heading: np.ndarray, curvature: np.ndarray, step: float = PATH_STEP):
        self.xy, self.heading, self.curvature, self.step = xy, heading, curvature, step
        self.length = step * (len(xy) - 1)

    @classmethod
    def integrate(cls, start_xy: np.ndarray, start_heading: float, curvature: np.ndarray,
                  step: float = PATH_STEP) -> "Path":
        """Integrate per-step curvature exactly (circular arcs between samples)."""
        turn = curvature * step
        heading = start_heading + np.concatenate([[0.0], np.cumsum(turn)])
        chord = step * np.sinc(turn / (2 * np.pi))  # 2 sin(kΔs/2)/k
        mid = heading[:-1] + turn / 2
        deltas = np.stack([chord * np.cos(mid), chord * np.sin(mid)], axis=1)
        xy = np.asarray(start_xy, dtype=np.float64) + np.concatenate([np.zeros((1, 2)), np.cumsum(deltas, 0)])
        return cls(xy, heading, np.concatenate([curvature, curvature[-1:]]), step)

    def _interp(self, values: np.ndarray, s: np.ndarray) -> np.ndarray:
        pos = np.clip(np.asarray(s, dtype=np.float64) / self.step, 0, len(self.xy) - 1.000001)
        i = pos.astype(np.int64)
        w = pos - i
        if values.ndim == 2:
            w = w[..., None]
        return values[i] * (1 - w) + values[i + 1] * w

    def point(self, s: np.ndarray | float) -> np.ndarray:
        """(..., 2) centreline points at arc length s."""
        return self._interp(self.xy, s)

    def heading_at(self, s: np.ndarray | float) -> np.ndarray:
        return self._interp(self.heading, s)

    def curvature_at(self, s: np.ndarray | float) -> np.ndarray:
        return self._interp(self.curvature, s)

    def offset(self, s: np.ndarray | float, d: np.ndarray | float) -> np.ndarray:
        """(..., 2) world points at Frenet (s, d)."""
        h = self.heading_at(s)
        normal = np.stack([-np.sin(h), np.cos(h)], axis=-1)
        return self.point(s) + np.asarray(d)[..., None] * normal

    def project(self, xy: np.ndarray, s_guess: float, window: float = 30.0) -> tuple[float, float]:
        """Frenet (s, d) of one world point, searching `window` metres around `s_guess`."""
        lo = max(0, int((s_guess - window) / self.step))
        hi = min(len(self.xy) - 1, int((s_guess + window) / self.step) + 1)
        i = lo + int(np.argmin(np.sum((self.xy[lo:hi + 1] - xy) ** 2, axis=1)))
        h = self.heading[i]
        tangent, normal = np.array([np.cos(h), np.sin(h)]), np.array([-np.sin(h), np.cos(h)])
        rel = xy - self.xy[i]
        return i * self.step + float(rel @ tangent), float(rel @ normal)


@dataclass
class JunctionSite:
    """A junction placed on the route.

    s_entry / s_exit: arc length where the route enters / leaves the box; centre: (2,) box centre;
    heading_in: route heading on entry; half_size: box half-size (m); arm_headings: outward
    headings of the side arms that are not on the route; stop_s: own stop line (route s).
    """

    spec: Junction
    s_entry: float
    s_exit: float
    centre: np.ndarray
    heading_in: float
    half_size: float
    arm_headings: list[float]
    stop_s: float
    stop_s_oncoming: float

    @property
    def has_cross_traffic(self) -> bool:
        """Cross traffic runs only through straight four-way junctions (both side arms present)."""
        return self.spec.kind == "four_way" and self.spec.turn == "straight"


@dataclass
class RoadLayout:
    """The whole road of one clip: centreline path, cross-section, junctions, crossings."""

    path: Path
    geometry: LaneGeometry
    junctions: list[JunctionSite] = field(default_factory=list)
    crossings: list[float] = field(default_factory=list)
    """Route s of each zebra crossing centre."""

    def in_junction(self, s: np.ndarray) -> np.ndarray:
        """Boolean mask: route s inside a junction box."""
        s = np.asarray(s)
        inside = np.zeros(s.shape, dtype=bool)
        for j in self.junctions:
            inside |= (s >= j.s_entry) & (s <= j.s_exit)
        return inside

    def gaps(self, with_crossings: bool) -> list[tuple[float, float]]:
        """Route s-intervals where lane markings and sidewalks stop (boxes, optionally crossings)."""
        out = [(j.s_entry, j.s_exit) for j in self.junctions]
        if with_crossings:
            out += [(c - CROSSING_HALF_LENGTH, c + CROSSING_HALF_LENGTH) for c in self.crossings]
        return sorted(out)

    def runs(self, with_crossings: bool) -> list[tuple[float, float]]:
        """Complement of `gaps` over [0, length]: where markings are painted."""
        runs, start = [], 0.0
        for lo, hi in self.gaps(with_crossings):
            if lo > start:
                runs.append((start, lo))
            start = max(start, hi)
        if start < self.path.length:
            runs.append((start, self.path.length))
        return runs


def _turn_sign(turn: str) -> float:
    return {"straight": 0.0, "left": 1.0, "right": -1.0}[turn]


def _side_arms(spec: Junction, heading_in: float, rng_side: int) -> list[float]:
    """Outward headings of the arms that are not the route's entry or exit."""
    forward, left, right = heading_in, heading_in + np.pi / 2, heading_in - np.pi / 2
    if spec.turn == "straight":
        arms = [left, right] if spec.kind == "four_way" else [left if rng_side > 0 else right]
    else:
        exit_heading = left if spec.turn == "left" else right
        other = right if spec.turn == "left" else left
        arms = [forward, other] if spec.kind == "four_way" else [other]
        arms = [a for a in arms if a != exit_heading]
    return arms


def build_layout(segments: list[Segment], geometry: LaneGeometry, side_choices: np.ndarray | None = None) -> RoadLayout:
    """Integrate `segments` into a RoadLayout starting at the origin heading +x.

    side_choices: one ±1 per junction choosing the side arm of straight T-junctions.
    """
    half = geometry.edge + geometry.shoulder + CORNER_MARGIN
    curv_parts: list[np.ndarray] = []
    pending: list[tuple[float, float, Junction]] = []  # (s_entry, s_exit, spec)
    crossings: list[float] = []
    s = 0.0
    for seg in segments:
        if isinstance(seg, Junction):
            length = 2 * half if seg.turn == "straight" else np.pi / 2 * half
            k = _turn_sign(seg.turn) / half
            pending.append((s, s + length, seg))
        elif isinstance(seg, Curve):
            length, k = seg.length, seg.curvature
        elif isinstance(seg, Straight):
            length, k = seg.length, 0.0
            if seg.crossing:
                crossings.append(s + length / 2)
        else:
            raise ValueError(f"segments: expected Straight, Curve or Junction, got {seg!r}")
        if length <= 0:
            raise ValueError(f"segments: every piece needs a positive length, got {seg!r}")
        n = max(1, int(round(length / PATH_STEP)))
        curv_parts.append(np.full(n, k))
        s += n * PATH_STEP
    path = Path.integrate(np.zeros(2), 0.0, np.concatenate(curv_parts))
    sides = side_choices if side_choices is not None else np.ones(len(pending))
    junctions = [_site(path, s0, s1, spec, half, int(side)) for (s0, s1, spec), side in zip(pending, sides)]
    for j in junctions:
        if j.spec.crossing:
            crossings.append(j.s_entry - CROSSING_HALF_LENGTH - 1.0)
    return RoadLayout(path, geometry, junctions, sorted(crossings))


def _site(path: Path, s_entry: float, s_exit: float, spec: Junction, half: float, side: int) -> JunctionSite:
    heading_in = float(path.heading_at(s_entry))
    forward = np.array([np.cos(heading_in), np.sin(heading_in)])
    centre = path.point(s_entry) + half * forward
    setback = 2 * CROSSING_HALF_LENGTH + 2.0 if spec.crossing else 1.0
    return JunctionSite(spec, s_entry, s_exit, centre, heading_in, half, _side_arms(spec, heading_in, side),
                        stop_s=s_entry - setback, stop_s_oncoming=s_exit + 1.0)
