"""Drawable primitives of the synthetic world, in world coordinates (metres, z up).

* `Solids`: convex hexahedra (boxes, tapered cabins, pitched roofs) with a colour per face.
  Vertices 0–3 are the bottom ring, 4–7 the top ring, both ordered (-x,-y), (+x,-y), (+x,+y),
  (-x,+y) in the solid's own frame. `FACES` lists each face's corners so that corner 0→1 is the
  face's u axis and 0→3 its v axis (v points up on side faces).
* `Decals`: flat quads painted on a solid face (windows, wheels, lights) at face coordinates
  (u0, v0)–(u1, v1) in 0..1; drawn right after their face, only when that face is visible.
* `Spheres`: round things (tree crowns, heads, lamp globes), drawn as discs.
* `GroundPolys`: flat polygons on the ground, drawn first in list order.
Colours are RGB floats in 0..1; `emissive` parts glow (no shading, full brightness at night).
`instance` holds the agent track id (−1 for scenery), for instance masks.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

FACES = np.array([[0, 1, 2, 3], [4, 5, 6, 7], [1, 2, 6, 5], [0, 3, 7, 4], [3, 2, 6, 7], [0, 1, 5, 4]])
BOTTOM, TOP, FRONT, BACK, LEFT, RIGHT = range(6)


def _concat_fields(cls, parts):
    return cls(**{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)})


@dataclass
class Solids:
    """B convex hexahedra: verts (B, 8, 3); colour (B, 6, 3); emissive (B, 6) bool; instance (B,)."""

    verts: np.ndarray
    colour: np.ndarray
    emissive: np.ndarray
    instance: np.ndarray

    def __len__(self) -> int:
        return len(self.verts)

    @classmethod
    def empty(cls) -> "Solids":
        return cls(np.zeros((0, 8, 3)), np.zeros((0, 6, 3)), np.zeros((0, 6), bool), np.zeros(0, np.int64))

    def take(self, index: np.ndarray) -> "Solids":
        return Solids(self.verts[index], self.colour[index], self.emissive[index], self.instance[index])


@dataclass
class Decals:
    """D quads on solid faces: parent (D,) solid index; face (D,); uv (D, 4) u0 v0 u1 v1;
    colour (D, 3); emissive (D,) bool."""

    parent: np.ndarray
    face: np.ndarray
    uv: np.ndarray
    colour: np.ndarray
    emissive: np.ndarray

    def __len__(self) -> int:
        return len(self.parent)

    @classmethod
    def empty(cls) -> "Decals":
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0, bool))

    @classmethod
    def concat(cls, parts: list["Decals"]) -> "Decals":
        """Decals of the same solids, concatenated (parent indices unchanged)."""
        return _concat_fields(cls, parts or [cls.empty()])

    def quads(self, solids: Solids) -> np.ndarray:
        """(D, 4, 3) world corners, by bilinear interpolation of the parent face corners."""
        corners = solids.verts[self.parent[:, None], FACES[self.face]]  # (D, 4, 3)
        u0, v0, u1, v1 = (self.uv[:, k:k + 1, None] for k in range(4))
        u = np.concatenate([u0, u1, u1, u0], axis=1)
        v = np.concatenate([v0, v0, v1, v1], axis=1)
        c0, c1, c2, c3 = (corners[:, k:k + 1] for k in range(4))
        return (1 - u) * (1 - v) * c0 + u * (1 - v) * c1 + u * v * c2 + (1 - u) * v * c3


@dataclass
class Spheres:
    """S spheres: centre (S, 3); radius (S,); colour (S, 3); emissive (S,); instance (S,)."""

    centre: np.ndarray
    radius: np.ndarray
    colour: np.ndarray
    emissive: np.ndarray
    instance: np.ndarray

    def __len__(self) -> int:
        return len(self.centre)

    @classmethod
    def empty(cls) -> "Spheres":
        return cls(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0, np.int64))

    def take(self, index: np.ndarray) -> "Spheres":
        return Spheres(self.centre[index], self.radius[index], self.colour[index], self.emissive[index],
                       self.instance[index])


@dataclass
class Mesh:
    """Solids with their decals, plus spheres: one group of drawables."""

    solids: Solids
    decals: Decals = None  # type: ignore[assignment]
    spheres: Spheres = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        self.decals = Decals.empty() if self.decals is None else self.decals
        self.spheres = Spheres.empty() if self.spheres is None else self.spheres

    @classmethod
    def empty(cls) -> "Mesh":
        return cls(Solids.empty())

    @classmethod
    def concat(cls, parts: list["Mesh"]) -> "Mesh":
        parts = [p for p in parts if len(p.solids) or len(p.spheres)] or [cls.empty()]
        offsets = np.cumsum([0] + [len(p.solids) for p in parts[:-1]])
        decals = [Decals(p.decals.parent + o, p.decals.face, p.decals.uv, p.decals.colour, p.decals.emissive)
                  for p, o in zip(parts, offsets)]
        return cls(_concat_fields(Solids, [p.solids for p in parts]), _concat_fields(Decals, decals),
                   _concat_fields(Spheres, [p.spheres for p in parts]))

    def select(self, keep_solids: np.ndarray, keep_spheres: np.ndarray) -> "Mesh":
        """The drawables whose masks are true; decals follow their solids."""
        new_index = np.cumsum(keep_solids) - 1
        keep_decals = keep_solids[self.decals.parent]
        d = self.decals
        decals = Decals(new_index[d.parent[keep_decals]], d.face[keep_decals], d.uv[keep_decals],
                        d.colour[keep_decals], d.emissive[keep_decals])
        return Mesh(self.solids.take(keep_solids), decals, self.spheres.take(keep_spheres))


@dataclass
class GroundPolys:
    """Flat polygons drawn in order before everything else: points list of (k, 3); colour (n, 3)."""

    points: list[np.ndarray]
    colour: np.ndarray

    @classmethod
    def concat(cls, parts: list["GroundPolys"]) -> "GroundPolys":
        pts = [p for part in parts for p in part.points]
        cols = [part.colour for part in parts if len(part.points)]
        return cls(pts, np.concatenate(cols) if cols else np.zeros((0, 3)))


def box_vertices(centre: np.ndarray, yaw: np.ndarray, size: np.ndarray, top_scale: np.ndarray | None = None,
                 top_shift: np.ndarray | None = None) -> np.ndarray:
    """(B, 8, 3) hexahedra standing on z = centre[:, 2].

    centre: (B, 3) bottom-centre; yaw: (B,) rad; size: (B, 3) length, width, height;
    top_scale: (B, 2) top ring length/width relative to the bottom (tapered cabins, roofs);
    top_shift: (B,) forward shift of the top ring (m).
    """
    b = len(centre)
    top_scale = np.ones((b, 2)) if top_scale is None else top_scale
    top_shift = np.zeros(b) if top_shift is None else top_shift
    sx = np.array([-1, 1, 1, -1]) / 2
    sy = np.array([-1, -1, 1, 1]) / 2
    lx = np.concatenate([sx * size[:, :1], sx * size[:, :1] * top_scale[:, :1] + top_shift[:, None]], axis=1)
    ly = np.concatenate([sy * size[:, 1:2], sy * size[:, 1:2] * top_scale[:, 1:2]], axis=1)
    lz = np.concatenate([np.zeros((b, 4)), np.repeat(size[:, 2:3], 4, axis=1)], axis=1)
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    return np.stack([centre[:, :1] + c * lx - s * ly, centre[:, 1:2] + s * lx + c * ly, centre[:, 2:3] + lz], axis=-1)


def solids(verts: np.ndarray, colour: np.ndarray, emissive: np.ndarray | None = None,
           instance: np.ndarray | None = None) -> Solids:
    """Solids with one colour per solid ((B, 3), broadcast to faces) or per face ((B, 6, 3))."""
    b = len(verts)
    colour = np.asarray(colour, dtype=np.float64)
    if colour.ndim == 2:
        colour = np.repeat(colour[:, None], 6, axis=1)
    emissive = np.zeros((b, 6), bool) if emissive is None else emissive
    instance = np.full(b, -1, np.int64) if instance is None else instance
    return Solids(verts, colour, emissive, instance)


def decals(parent: np.ndarray, face: int | np.ndarray, uv: np.ndarray, colour: np.ndarray,
           emissive: np.ndarray | bool = False) -> Decals:
    """Decals on faces of solids `parent` (D,) with uv (D, 4) or one (4,) broadcast."""
    parent = np.asarray(parent, np.int64)
    d = len(parent)
    return Decals(parent, np.broadcast_to(np.asarray(face, np.int64), (d,)).copy(),
                  np.broadcast_to(np.asarray(uv, np.float64), (d, 4)).copy(),
                  np.broadcast_to(np.asarray(colour, np.float64), (d, 3)).copy(),
                  np.broadcast_to(np.asarray(emissive, bool), (d,)).copy())


def spheres(centre: np.ndarray, radius: np.ndarray, colour: np.ndarray, emissive: np.ndarray | bool = False,
            instance: np.ndarray | None = None) -> Spheres:
    n = len(centre)
    return Spheres(np.asarray(centre, np.float64), np.broadcast_to(np.asarray(radius, np.float64), (n,)).copy(),
                   np.broadcast_to(np.asarray(colour, np.float64), (n, 3)).copy(),
                   np.broadcast_to(np.asarray(emissive, bool), (n,)).copy(),
                   np.full(n, -1, np.int64) if instance is None else np.asarray(instance, np.int64))
