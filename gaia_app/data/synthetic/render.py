"""OpenCV rasteriser for one camera: painter's algorithm over depth-sorted convex polygons.

Pixel convention: pixel (i, j) covers [j, j+1] × [i, i+1] in the coordinates of the camera
intrinsics, so the principal point (w/2, h/2) is the image centre. Draw order per frame:
background (sky, distant ground) → sky objects → ground polygons → per-pixel ground lighting and
fog (precomputed maps, the rig is fixed and the ground flat) → solids, decals and spheres from
far to near with per-face shading and fog → weather overlay. Polygons are clipped at the near
plane (Sutherland–Hodgman) before projection, so nothing behind the camera wraps around.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from gaia_app.data.clip import CameraSpec
from gaia_app.data.synthetic.appearance import Appearance, headlight_intensity
from gaia_app.data.synthetic.geometry import FACES, Mesh

NEAR = 0.1
"""Near clipping plane (m)."""
SHIFT = 4
"""Fixed-point fractional bits for OpenCV drawing (1/16 pixel)."""
MIN_AREA = 0.35
"""Faces smaller than this (pixels²) are skipped: they would change no pixel visibly."""
MIN_DECAL_AREA = 1.0
"""Decals (windows, lights, wheels) smaller than this (pixels²) are skipped: sub-pixel detail."""
MIN_DISC_RADIUS = 0.4
"""Spheres whose disc radius is below this (pixels) are skipped."""
COORD_LIMIT = 1e6
"""Clamp (pixels) for projected coordinates; only reached by points within millimetres of the near plane."""


def clip_near(poly: np.ndarray, near: float = NEAR) -> np.ndarray:
    """Sutherland–Hodgman clip of a (k, 3) camera-frame polygon to z >= near; (m, 3), m may be 0."""
    z = poly[:, 2]
    inside = z >= near
    if inside.all():
        return poly
    if not inside.any():
        return poly[:0]
    following = np.roll(poly, -1, axis=0)
    crosses = inside != np.roll(inside, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (near - z) / (following[:, 2] - z)
    hit = poly + np.where(crosses, t, 0.0)[:, None] * (following - poly)
    keep = np.stack([inside, crosses], axis=1)
    return np.stack([poly, hit], axis=1)[keep]


def transform(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) rigid transform to (..., 3) points."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


@dataclass
class FrameGeometry:
    """Camera-independent drawables of one frame.

    ego_from_world: (4, 4); ground: (polygons, albedo) groups in draw order, each a list of
    non-overlapping (k, 3) world polygons with one (3,) colour in 0..1; mesh: solids/decals/spheres
    with shaded colours face_colour (B, 6, 3), decal_colour (D, 3), sphere_colour (S, 3) in 0..1; face_normal /
    face_centre (B, 6, 3) world; decal_quads (D, 4, 3) world.
    """

    ego_from_world: np.ndarray
    ground: list[tuple[list[np.ndarray], np.ndarray]]
    mesh: Mesh
    face_colour: np.ndarray
    face_normal: np.ndarray
    face_centre: np.ndarray
    decal_quads: np.ndarray
    decal_colour: np.ndarray
    sphere_colour: np.ndarray
    light_pools: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    """Ground lit by street lamps: (k, 3) world polygons, innermost last, with their light (3,)."""


def face_frames(verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outward unit normals and centres (B, 6, 3) of hexahedra faces (robust to degenerate faces)."""
    corners = verts[:, FACES]  # (B, 6, 4, 3)
    normal = np.cross(corners[:, :, 2] - corners[:, :, 0], corners[:, :, 3] - corners[:, :, 1])
    centre = corners.mean(axis=2)
    outward = np.sum(normal * (centre - verts.mean(axis=1, keepdims=True)), axis=-1, keepdims=True)
    normal = np.where(outward < 0, -normal, normal)
    return normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-9), centre


def shade_mesh(mesh: Mesh, appearance: Appearance, ego_from_world: np.ndarray) -> tuple[np.ndarray, ...]:
    """Shaded colours of faces (B, 6, 3), decals (D, 3), spheres (S, 3), plus face normals,
    centres and decal quads, for the frame's ego pose (headlights)."""
    s = mesh.solids
    normal, centre = face_frames(s.verts)
    flat_n, flat_c = normal.reshape(-1, 3), centre.reshape(-1, 3)
    lamp = _headlight_on_faces(flat_c, flat_n, appearance, ego_from_world)
    lit = appearance.shade(s.colour.reshape(-1, 3), flat_n, lamp).reshape(s.colour.shape)
    face_colour = np.where(s.emissive[..., None], s.colour, lit)
    d = mesh.decals
    quads = d.quads(s)
    parent_light = np.divide(lit[d.parent, d.face], np.maximum(s.colour[d.parent, d.face], 1e-3))
    decal_colour = np.where(d.emissive[:, None], d.colour, d.colour * parent_light)
    sp = mesh.spheres
    up = np.tile([0.0, 0.0, 1.0], (len(sp), 1))
    sphere_lamp = headlight_intensity(transform(ego_from_world, sp.centre), appearance.headlights) * 0.6
    sphere_lit = appearance.shade(sp.colour, up, sphere_lamp) * 0.9
    sphere_colour = np.where(sp.emissive[:, None], sp.colour, sphere_lit)
    return face_colour, normal, centre, quads, decal_colour, sphere_colour


def _headlight_on_faces(centre: np.ndarray, normal: np.ndarray, appearance: Appearance,
                        ego_from_world: np.ndarray) -> np.ndarray:
    if appearance.headlights <= 0 or len(centre) == 0:
        return np.zeros(len(centre))
    p = transform(ego_from_world, centre)
    n = normal @ ego_from_world[:3, :3].T
    to_lamp = np.array([2.0, 0.0, 0.7]) - p
    facing = np.clip(np.sum(n * to_lamp, axis=1) / np.maximum(np.linalg.norm(to_lamp, axis=1), 1e-6), 0.0, 1.0)
    return headlight_intensity(p, appearance.headlights) * facing


class CameraRenderer:
    """Renders frames for one camera of the rig with one appearance."""

    def __init__(self, camera: CameraSpec, appearance: Appearance, ground_albedo: np.ndarray):
        self.camera, self.appearance = camera, appearance
        self.h, self.w = camera.height, camera.width
        self.cam_from_ego = np.linalg.inv(camera.extrinsics)
        k = camera.intrinsics
        self.fx, self.fy, self.cx, self.cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        # Frustum planes through the camera centre (inward normals) plus the near plane, 1 px margin.
        w, h, cx, cy = self.w + 1, self.h + 1, self.cx, self.cy
        self.planes = np.array([[self.fx, 0, cx + 1], [-self.fx, 0, w - cx], [0, self.fy, cy + 1],
                                [0, -self.fy, h - cy], [0, 0, 1.0]])
        self.plane_offset = np.array([0, 0, 0, 0, -NEAR])
        self.rays_ego = self._pixel_rays()
        self.horizon_row = self._horizon_row()
        self.background, self.ground_gain, self.ground_add = self._ground_maps(ground_albedo)

    # ------------------------------------------------------------ precomputation

    def _pixel_rays(self) -> np.ndarray:
        """(h, w, 3) unit ray directions of pixel centres in the ego frame."""
        j, i = np.meshgrid(np.arange(self.w) + 0.5, np.arange(self.h) + 0.5)
        rays = np.stack([(j - self.cx) / self.fx, (i - self.cy) / self.fy, np.ones_like(j)], axis=-1)
        rays = rays @ self.camera.extrinsics[:3, :3].T
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    def _horizon_row(self) -> int:
        """First image row whose centre ray points below the horizon anywhere."""
        below = (self.rays_ego[..., 2] < 0).any(axis=1)
        return int(np.argmax(below)) if below.any() else self.h

    def _ground_maps(self, ground_albedo: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Background image (sky gradient, ground albedo) and per-pixel ground gain/add maps."""
        app = self.appearance
        rays = self.rays_ego
        elevation = np.arcsin(np.clip(rays[..., 2], -1, 1))
        u = np.clip(elevation / np.radians(35.0), 0.0, 1.0)[..., None] ** 0.6
        sky = app.sky_horizon * (1 - u) + app.sky_top * u
        if app.visibility < 100:  # thick fog: the sky itself is mostly fog
            sky = sky * (1 - app.fog_factor(1500.0)) + app.fog_colour * app.fog_factor(1500.0)
        ground = rays[..., 2] < -1e-4
        height = self.camera.extrinsics[2, 3]
        t = np.where(ground, height / np.maximum(-rays[..., 2], 1e-4), 0.0)
        points = self.camera.extrinsics[:3, 3] + t[..., None] * rays
        lamp = headlight_intensity(points.reshape(-1, 3), app.headlights).reshape(self.h, self.w)
        light = app.ambient + app.sun_colour * max(0.0, app.sun_dir[2]) + lamp[..., None] * np.array([1.0, 0.95, 0.85])
        fog = app.fog_factor(t)[..., None]
        gain = np.where(ground[..., None], light * (1 - fog), 1.0).astype(np.float32)
        add = np.where(ground[..., None], app.fog_colour * fog * 255.0, 0.0).astype(np.float32)
        background = np.where(ground[..., None], ground_albedo, sky)
        return np.clip(background * 255.0, 0, 255).astype(np.uint8), gain, add

    # ------------------------------------------------------------ projection

    def _outside(self, cam: np.ndarray) -> np.ndarray:
        """(..., 5) True where camera-frame points are outside each frustum plane."""
        return cam @ self.planes.T + self.plane_offset < 0

    def project(self, cam: np.ndarray) -> np.ndarray:
        """(..., 2) fixed-point OpenCV coordinates of camera-frame points (z >= NEAR assumed)."""
        z = np.maximum(cam[..., 2], 1e-6)
        u = self.fx * cam[..., 0] / z + self.cx - 0.5
        v = self.fy * cam[..., 1] / z + self.cy - 0.5
        uv = np.clip(np.stack([u, v], axis=-1), -COORD_LIMIT, COORD_LIMIT)
        return np.round(uv * (1 << SHIFT)).astype(np.int32)

    # ------------------------------------------------------------ drawing

    def light_ground(self, img: np.ndarray, geo: FrameGeometry | None = None,
                     cam_from_world: np.ndarray | None = None) -> None:
        """Apply per-pixel ground shading and fog below the horizon (in place), plus the frame's
        street-lamp pools when given."""
        r = self.horizon_row
        if r >= self.h:
            return
        gain = self.ground_gain[r:]
        if geo is not None and geo.light_pools:
            gain = gain + self._pool_light(geo, cam_from_world, r)
        region = img[r:].astype(np.float32)
        region *= gain
        region += self.ground_add[r:]
        np.clip(region, 0, 255, out=region)
        img[r:] = region.astype(np.uint8)

    def _pool_light(self, geo: FrameGeometry, cam_from_world: np.ndarray, row0: int) -> np.ndarray:
        """(h - row0, w, 3) extra ground gain from street-lamp pools, seen through the fog; rings
        are drawn outermost first, so each pixel keeps the light of the innermost ring over it."""
        extra = np.zeros((self.h - row0, self.w, 3), np.float32)
        for poly, light in geo.light_pools:
            cam = clip_near(transform(cam_from_world, poly))
            if len(cam) < 3 or self._outside(cam).all(axis=0).any():
                continue
            value = light * (1 - self.appearance.fog_factor(np.linalg.norm(cam.mean(axis=0))))
            pts = self.project(cam) - np.array([0, row0 << SHIFT], np.int32)
            cv2.fillPoly(extra, [pts], value.tolist(), cv2.LINE_AA, SHIFT)
        return extra

    def draw_ground(self, img: np.ndarray, geo: FrameGeometry, cam_from_world: np.ndarray) -> None:
        """Fill the frame's ground polygons (albedo colours), clipped at the near plane; one fill
        call per group."""
        polys = [p for group, _ in geo.ground for p in group]
        if not polys:
            return
        sizes = np.array([len(p) for p in polys])
        starts = np.r_[0, np.cumsum(sizes)[:-1]]
        cam = transform(cam_from_world, np.concatenate(polys))
        outside = np.logical_and.reduceat(self._outside(cam), starts, axis=0).any(axis=1)
        behind = np.logical_or.reduceat(cam[:, 2] < NEAR, starts)
        pixels = self.project(cam)
        k = 0
        for group, colour in geo.ground:
            contours = []
            for _ in group:
                a, b = starts[k], starts[k] + sizes[k]
                if not outside[k]:
                    contours.append(self.project(clip_near(cam[a:b])) if behind[k] else pixels[a:b])
                k += 1
            contours = [c for c in contours if len(c) >= 3]
            if contours:
                cv2.fillPoly(img, contours, (np.clip(colour, 0, 1) * 255).tolist(), cv2.LINE_AA, SHIFT)

    def draw_objects(self, img: np.ndarray, geo: FrameGeometry, cam_from_world: np.ndarray,
                     instance: bool = False) -> None:
        """Solids (faces, then their decals) and spheres from far to near.

        instance=True fills track id + 1 (0 for scenery) into a single-channel int32 image,
        without anti-aliasing and without decals (they lie on their faces).
        """
        faces, decal_items, discs, order = self._draw_items(geo, cam_from_world, instance)
        line = cv2.LINE_8 if instance else cv2.LINE_AA
        tables = (faces, decal_items)
        for kind, i in order:
            if kind == 2:
                centre, radius, colour = discs[i]
                cv2.circle(img, centre, radius, colour, -1, line, SHIFT)
            else:
                pts, colour = tables[kind][0][i], tables[kind][1][i]
                cv2.fillConvexPoly(img, pts, colour, line, SHIFT)

    def _draw_items(self, geo: FrameGeometry, cam_from_world: np.ndarray, instance: bool):
        """Faces (polygons, colours), decals (polygons, colours), discs (centre, radius, colour),
        and the draw order as (kind 0 face / 1 decal / 2 disc, index) pairs, farthest first."""
        s = geo.mesh.solids
        cam_verts = transform(cam_from_world, s.verts)
        culled = self._outside(cam_verts).all(axis=1).any(axis=1)
        centre_cam = transform(cam_from_world, geo.face_centre)
        normal_cam = geo.face_normal @ cam_from_world[:3, :3].T
        face_z = cam_verts[:, FACES, 2]  # (B, 6, 4)
        visible = (np.sum(normal_cam * centre_cam, axis=-1) < 0) & ~culled[:, None] & (face_z >= NEAR).any(-1)
        needs_clip = visible & (face_z < NEAR).any(-1)
        face_px = np.ascontiguousarray(self.project(cam_verts)[:, FACES])  # (B, 6, 4, 2)
        visible &= needs_clip | (_polygon_area(face_px / (1 << SHIFT)) > MIN_AREA)
        fb, ff = np.nonzero(visible)
        polys = list(face_px[fb, ff])
        for k in np.flatnonzero(needs_clip[fb, ff]):
            polys[k] = self.project(clip_near(cam_verts[fb[k], FACES[ff[k]]]))
        if instance:
            face_colours = [(float(v),) for v in (s.instance[fb] + 1).tolist()]
        else:
            face_colours = self._fogged(geo.face_colour[fb, ff], np.linalg.norm(centre_cam[fb, ff], axis=-1))
        disc_dist, discs = self._discs(geo, cam_from_world, instance)
        solid_dist = np.linalg.norm(transform(cam_from_world, s.verts.mean(axis=1)), axis=-1)
        drawn = np.unique(fb)
        rank = np.empty(len(drawn) + len(discs), np.int64)
        rank[np.argsort(-np.r_[solid_dist[drawn], disc_dist], kind="stable")] = np.arange(len(rank))
        solid_rank = np.zeros(len(s), np.int64)
        solid_rank[drawn] = rank[:len(drawn)]
        decal_polys, decal_colours, decal_idx = self._decals(geo, cam_from_world, visible, instance)
        keys = np.r_[solid_rank[fb] * 2, solid_rank[geo.mesh.decals.parent[decal_idx]] * 2 + 1, rank[len(drawn):] * 2]
        kinds = np.r_[np.zeros(len(fb), np.int64), np.ones(len(decal_idx), np.int64), np.full(len(discs), 2)]
        index = np.r_[np.arange(len(fb)), np.arange(len(decal_idx)), np.arange(len(discs))]
        order = np.argsort(keys, kind="stable")
        return ((polys, face_colours), (decal_polys, decal_colours), discs,
                zip(kinds[order].tolist(), index[order].tolist()))

    def _fogged(self, colour: np.ndarray, distance: np.ndarray) -> list:
        """Colours (n, 3) seen through fog at (n,) metres, as OpenCV 0..255 lists."""
        return (np.clip(self.appearance.fog(colour, distance), 0, 1) * 255).tolist()

    def _decals(self, geo: FrameGeometry, cam_from_world: np.ndarray, visible: np.ndarray, instance: bool):
        """Projected decals on visible faces, large enough to matter: polygons, colours, indices."""
        d = geo.mesh.decals
        if instance or len(d) == 0:
            return [], [], np.zeros(0, np.int64)
        cam = transform(cam_from_world, geo.decal_quads)
        ok = visible[d.parent, d.face] & (cam[:, :, 2] >= NEAR).all(axis=1)
        idx = np.flatnonzero(ok)
        px = self.project(cam[idx])
        big = _polygon_area(px / (1 << SHIFT)) > MIN_DECAL_AREA
        idx, px = idx[big], px[big]
        return list(px), self._fogged(geo.decal_colour[idx], np.linalg.norm(cam[idx].mean(axis=1), axis=-1)), idx

    def _discs(self, geo: FrameGeometry, cam_from_world: np.ndarray, instance: bool) -> tuple[np.ndarray, list]:
        """Spheres in view as discs: distances (n,) and (centre, radius, colour) fixed-point tuples."""
        sp = geo.mesh.spheres
        if len(sp) == 0:
            return np.zeros(0), []
        cam = transform(cam_from_world, sp.centre)
        side = self.planes[:4]
        inside = cam @ side.T / np.linalg.norm(side, axis=1)  # metres inside each side plane
        radius_px = self.fx * sp.radius / np.maximum(cam[:, 2], 1e-6)
        in_view = (cam[:, 2] > sp.radius + NEAR) & (inside > -sp.radius[:, None]).all(axis=1)
        ok = np.flatnonzero(in_view & (radius_px > MIN_DISC_RADIUS))
        centre = self.project(cam[ok]).tolist()
        radius = np.round(radius_px[ok] * (1 << SHIFT)).astype(np.int64).tolist()
        dist = np.linalg.norm(cam[ok], axis=1)
        if instance:
            colours = [(float(v),) for v in (sp.instance[ok] + 1).tolist()]
        else:
            colours = self._fogged(geo.sphere_colour[ok], dist)
        return dist, [(tuple(c), r, col) for c, r, col in zip(centre, radius, colours)]


def _polygon_area(pts: np.ndarray) -> np.ndarray:
    """(n,) absolute shoelace areas of (n, k, 2) polygons."""
    x, y = pts[..., 0], pts[..., 1]
    return 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=-1) - y * np.roll(x, -1, axis=-1), axis=-1))
