"""Everything flat on the ground, in draw order: verge texture, sidewalks and kerbs, asphalt
(route, junction boxes and side arms), asphalt texture, lane markings, stop lines, zebra crossings.

Bands along the route (`Ribbon`) become one polygon per frame covering the visible stretch, so
there are no seams; small items come in `PolyGroup`s of one colour drawn with one fill call.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gaia_app.data.synthetic.planning import KERB_WIDTH, SIDEWALK_WIDTH
from gaia_app.data.synthetic.road import CROSSING_HALF_LENGTH, JunctionSite, Path, RoadLayout
from gaia_app.data.synthetic.scenario import COUNTRIES, Setting

ARM_LENGTH = 90.0
"""How far (m) side roads extend from a junction box."""
LINE_WIDTH = 0.15


@dataclass
class Ribbon:
    """A band along the route between lateral offsets, where `runs` (route s-intervals) allow;
    edges sampled every RIBBON_STEP m: low_edge / high_edge (n, 3) world points (z = 0) at s (n,)."""

    s: np.ndarray
    low_edge: np.ndarray
    high_edge: np.ndarray
    runs: list[tuple[float, float]]
    colour: str

    def polygons(self, s_from: float, s_to: float) -> list[np.ndarray]:
        """One (k, 2) polygon per run inside the route window [s_from, s_to]."""
        out = []
        for a, b in self.runs:
            i0 = int(np.searchsorted(self.s, max(a, s_from)))
            i1 = int(np.searchsorted(self.s, min(b, s_to), side="right"))
            if i1 - i0 >= 2:
                out.append(np.concatenate([self.low_edge[i0:i1], self.high_edge[i0:i1][::-1]]))
        return out


@dataclass
class PolyGroup:
    """Polygons of one colour that never overlap, so one fill call draws them all (OpenCV fills
    multi-contour polygons with the even-odd rule). points: list of (k, 2) world xy, stored as
    (k, 3) with z = 0."""

    points: list[np.ndarray]
    colour: str

    def __post_init__(self) -> None:
        self.points = [_on_ground(p) for p in self.points]
        lo = np.array([p[:, :2].min(0) for p in self.points]).reshape(-1, 2)
        hi = np.array([p[:, :2].max(0) for p in self.points]).reshape(-1, 2)
        self.centre, self.radius = (lo + hi) / 2, np.linalg.norm(hi - lo, axis=1) / 2

    def near(self, xy: np.ndarray, radius: float) -> list[np.ndarray]:
        keep = np.linalg.norm(self.centre - xy, axis=1) < radius + self.radius
        return [self.points[k] for k in np.flatnonzero(keep)]


@dataclass
class GroundPlan:
    """Ground items in draw order."""

    items: list[Ribbon | PolyGroup]

    def frame_groups(self, xy: np.ndarray, s: float, radius: float) -> list[tuple[list[np.ndarray], str]]:
        """(polygons, colour) groups to draw around route position s / world point xy."""
        out = []
        for item in self.items:
            polys = item.polygons(s - 150.0, s + radius) if isinstance(item, Ribbon) else item.near(xy, radius)
            if polys:
                out.append((polys, item.colour))
        return out


RIBBON_STEP = 1.0


def _on_ground(xy: np.ndarray) -> np.ndarray:
    xy = np.asarray(xy, dtype=np.float64)
    return xy if xy.shape[1] == 3 else np.c_[xy, np.zeros(len(xy))]


def ribbon(path: Path, runs: list[tuple[float, float]], d_lo: float, d_hi: float, colour: str) -> Ribbon:
    s = np.arange(0.0, path.length + RIBBON_STEP / 2, RIBBON_STEP)
    low, high = path.offset(s, np.full_like(s, d_lo)), path.offset(s, np.full_like(s, d_hi))
    return Ribbon(s, _on_ground(low), _on_ground(high), runs, colour)


def band(path: Path, s0: float, s1: float, d_lo: float, d_hi: float, step: float = 1.0) -> np.ndarray:
    """(k, 2) polygon covering Frenet [s0, s1] × [d_lo, d_hi]."""
    s = np.linspace(s0, s1, max(2, int(np.ceil((s1 - s0) / step)) + 1))
    return np.concatenate([path.offset(s, np.full_like(s, d_lo)), path.offset(s[::-1], np.full_like(s, d_hi))])


def quads(path: Path, s0, s1, d_lo, d_hi) -> list[np.ndarray]:
    """(4, 2) quads with corners at Frenet (s0|s1, d_lo|d_hi), vectorised over arrays of equal
    length; for short pieces (markings, patches) where the road's bend within a piece is negligible."""
    s0, s1, d_lo, d_hi = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (s0, s1, d_lo, d_hi)))
    corners = [path.offset(s0, d_lo), path.offset(s1, d_lo), path.offset(s1, d_hi), path.offset(s0, d_hi)]
    return list(np.stack(corners, axis=1))


def rectangle(centre: np.ndarray, heading: float, x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    """(4, 2) rectangle [x0, x1] × [y0, y1] in a frame at `centre` rotated by `heading`."""
    c, s = np.cos(heading), np.sin(heading)
    local = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    return centre + local @ np.array([[c, s], [-s, c]])


def _sides(layout: RoadLayout) -> tuple[float, float]:
    geo = layout.geometry
    inner = geo.edge + geo.shoulder
    return inner, inner + KERB_WIDTH


def verge_texture(rng: np.random.Generator, layout: RoadLayout, start: float) -> list[PolyGroup]:
    """Irregular darker/lighter blobs beside the road; one per 12 m slot per side, so none overlap."""
    path = layout.path
    groups: dict[str, list[np.ndarray]] = {"grass_dark": [], "grass": [], "dirt": []}
    for s in np.arange(0.0, path.length - 12.0, 12.0):
        for side in (-1, 1):
            radius = rng.uniform(1.0, 3.0)
            centre = path.offset(np.array(s + 6.0), np.array(side * (start + radius + rng.uniform(0.3, 20.0))))
            angles = np.sort(rng.uniform(0, 2 * np.pi, 7))
            radii = radius * rng.uniform(0.6, 1.0, 7)
            blob = centre + np.stack([np.cos(angles) * radii * 1.8, np.sin(angles) * radii], axis=1)
            groups[str(rng.choice(list(groups), p=[0.5, 0.3, 0.2]))].append(blob)
    return [PolyGroup(points, colour) for colour, points in groups.items() if points]


def sidewalks(layout: RoadLayout) -> list[Ribbon]:
    inner, kerb = _sides(layout)
    runs = layout.runs(with_crossings=False)
    out = []
    for side in (-1, 1):
        out.append(ribbon(layout.path, runs, *sorted([side * kerb, side * (kerb + SIDEWALK_WIDTH)]), "sidewalk"))
        out.append(ribbon(layout.path, runs, *sorted([side * inner, side * kerb]), "kerb"))
    return out


def junction_surfaces(site: JunctionSite, layout: RoadLayout, with_sidewalks: bool) -> list[PolyGroup]:
    """Side-arm sidewalks, sidewalk squares at the box corners, then the box and arms (asphalt)."""
    inner, kerb = _sides(layout)
    h = site.half_size
    groups = []
    if with_sidewalks:
        walks = [rectangle(site.centre, arm, h, h + ARM_LENGTH, *sorted([side * kerb, side * (kerb + SIDEWALK_WIDTH)]))
                 for arm in site.arm_headings for side in (-1, 1)]
        corner = h + SIDEWALK_WIDTH + KERB_WIDTH
        corners = [rectangle(site.centre, site.heading_in + k * np.pi / 2, h, corner, h, corner) for k in range(4)]
        groups += [PolyGroup(walks, "sidewalk"), PolyGroup(corners, "sidewalk")]
    surface = [rectangle(site.centre, site.heading_in, -h, h, -h, h)]
    surface += [rectangle(site.centre, arm, h, h + ARM_LENGTH, -inner, inner) for arm in site.arm_headings]
    return groups + [PolyGroup(surface, "asphalt")]


def asphalt_texture(rng: np.random.Generator, layout: RoadLayout) -> list[PolyGroup]:
    """Repair patches, cracks and manhole covers: at most one per 9 m slot, so none overlap."""
    path, edge = layout.path, layout.geometry.edge
    slots = np.arange(0.0, path.length - 9.0, 9.0)
    n = len(slots)
    s, d, kind = slots + rng.uniform(0, 3, n), rng.uniform(-edge, edge - 0.6, n), rng.random(n)
    length, width = rng.uniform(1.0, 5.5, n), np.where(kind < 0.4, rng.uniform(0.5, 2.0, n), rng.uniform(0.04, 0.08, n))
    pieces = quads(path, s, s + length, d, d + width)
    angles = np.linspace(0, 2 * np.pi, 9)[:-1]
    manholes = [path.offset(np.array(s[i]), np.array(d[i])) + 0.35 * np.stack([np.cos(angles), np.sin(angles)], 1)
                for i in np.flatnonzero((kind >= 0.75) & (kind < 0.85))]
    groups = {"patch": [pieces[i] for i in np.flatnonzero(kind < 0.4)],
              "crack": [pieces[i] for i in np.flatnonzero((kind >= 0.4) & (kind < 0.75))] + manholes}
    return [PolyGroup(points, colour) for colour, points in groups.items() if points]


def lane_line(layout: RoadLayout, d: float, kind: str, colour: str,
              dash: tuple[float, float]) -> list[Ribbon | PolyGroup]:
    """A lane boundary at offset d: solid ribbon(s), or dashes."""
    runs = layout.runs(with_crossings=True)
    path = layout.path
    if kind in ("solid", "double_solid"):
        offsets = [d] if kind == "solid" else [d - 0.12, d + 0.12]
        return [ribbon(path, runs, off - LINE_WIDTH / 2, off + LINE_WIDTH / 2, colour) for off in offsets]
    if kind == "dashed":
        starts = np.concatenate([np.arange(a + 1.0, b - dash[0], dash[0] + dash[1]) for a, b in runs] or [np.zeros(0)])
        dashes = quads(path, starts, starts + dash[0], d - LINE_WIDTH / 2, d + LINE_WIDTH / 2) if len(starts) else []
        return [PolyGroup(dashes, colour)] if dashes else []
    return []


def markings(setting: Setting, layout: RoadLayout) -> list[Ribbon | PolyGroup]:
    """Lane lines (setting.lane_types, centre → kerb), stop lines and zebra crossings."""
    geo, path = layout.geometry, layout.path
    country = COUNTRIES[setting.country]
    dash = (6.0, 12.0) if setting.environment == "highway" else (3.0, 6.0)
    centre_colour = "yellow" if country.centre_colour == "yellow" else "white"
    types, sign = setting.lane_types, geo.drive_sign
    items: list[Ribbon | PolyGroup] = []
    centre_offsets = [0.0] if geo.median == 0 else [sign * geo.boundary_offset(0), -sign * geo.boundary_offset(0)]
    for d in centre_offsets:
        items += lane_line(layout, d, types[0], centre_colour, dash)
    for b in range(1, geo.lanes + 1):
        inset = LINE_WIDTH if b == geo.lanes else 0.0  # the edge line sits inside the carriageway
        for side in (sign, -sign):
            items += lane_line(layout, side * (geo.boundary_offset(b) - inset), types[b], "white", dash)
    for site in layout.junctions:
        stops = [band(path, site.stop_s - 0.4, site.stop_s, *sorted([0.0, sign * geo.edge])),
                 band(path, site.stop_s_oncoming, site.stop_s_oncoming + 0.4, *sorted([0.0, -sign * geo.edge]))]
        items.append(PolyGroup(stops, "white"))
    stripe_d = np.arange(-geo.edge + 0.25, geo.edge - 0.2, 1.0)  # 0.5 m stripes, 0.5 m gaps
    stripes = [q for c in layout.crossings
               for q in quads(path, c - CROSSING_HALF_LENGTH + 0.25, c + CROSSING_HALF_LENGTH - 0.25, stripe_d,
                              stripe_d + 0.5)]
    if stripes:
        items.append(PolyGroup(stripes, "white"))
    return items


def build_ground(rng: np.random.Generator, setting: Setting, layout: RoadLayout) -> GroundPlan:
    """All ground items of a clip in draw order."""
    inner, kerb = _sides(layout)
    path = layout.path
    whole = [(0.0, path.length)]
    items: list[Ribbon | PolyGroup] = list(verge_texture(rng, layout,
                                                         kerb + (SIDEWALK_WIDTH if setting.sidewalk else 0.3)))
    if setting.sidewalk:
        items += sidewalks(layout)
    items.append(ribbon(path, whole, -inner, inner, "asphalt"))
    if layout.geometry.median > 0:
        m = layout.geometry.median / 2 - 0.4
        items.append(ribbon(path, whole, -m, m, "median"))
    for site in layout.junctions:
        items += junction_surfaces(site, layout, setting.sidewalk)
    items += asphalt_texture(rng, layout)
    items += markings(setting, layout)
    return GroundPlan(items)
