"""Per-frame assembly of drawables and rendering of all cameras of a clip.

`ClipRenderer` builds the static world once (ground polygons, roadside objects, sky) and, for
each simulated `FrameState`, adds agents, their shadows and traffic lights, shades everything,
and renders every camera. It also renders instance-id images (masks) and 2D boxes.
"""

from __future__ import annotations

import cv2
import numpy as np

from gaia_app.data.clip import CameraSpec
from gaia_app.data.synthetic.actors import AgentMeshes, traffic_lights
from gaia_app.data.synthetic.appearance import Appearance
from gaia_app.data.synthetic.geometry import Mesh
from gaia_app.data.synthetic.ground import build_ground
from gaia_app.data.synthetic.labels import boxes_2d
from gaia_app.data.synthetic.planning import ScenePlan
from gaia_app.data.synthetic.render import CameraRenderer, FrameGeometry, shade_mesh
from gaia_app.data.synthetic.scenery import build_scenery
from gaia_app.data.synthetic.simulate import FrameState
from gaia_app.data.synthetic.sky import draw_sky, make_sky
from gaia_app.data.synthetic.world import PEDESTRIAN

POOL_RINGS = ((8.0, 0.05), (6.0, 0.09), (4.0, 0.14), (2.5, 0.2))
"""(radius m, light) of the rings of light under a street lamp, outermost first."""
LAMP_LIGHT = np.array([1.0, 0.85, 0.6])
VIEW_RADIUS = 320.0
"""Metres around the ego beyond which nothing is drawn (haze hides it)."""


def world_from_ego(state: FrameState) -> np.ndarray:
    """(4, 4) ego → world transform of a frame."""
    c, s = np.cos(state.ego.yaw), np.sin(state.ego.yaw)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:2, 3] = state.ego.x, state.ego.y
    return m


def _mesh_bounds(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bounding circles on the ground: solid centres (B, 2) and radii (B,), sphere centres (S, 2) and radii (S,)."""
    verts = mesh.solids.verts[..., :2].reshape(-1, 8, 2)
    lo, hi = verts.min(axis=1, initial=np.inf), verts.max(axis=1, initial=-np.inf)
    return (lo + hi) / 2, np.linalg.norm(hi - lo, axis=1) / 2, mesh.spheres.centre[:, :2], mesh.spheres.radius


class ClipRenderer:
    """Renders the frames of one planned clip for a camera rig."""

    def __init__(self, plan: ScenePlan, cameras: list[CameraSpec], appearance: Appearance):
        self.plan, self.appearance = plan, appearance
        rng = np.random.default_rng(plan.appearance_seed)
        self.ground = build_ground(rng, plan.setting, plan.layout)
        self.scenery = (build_scenery(rng, plan.setting, plan.layout, appearance.lights_on) if plan.roadside
                        else Mesh.empty())
        self.solid_centre, self.solid_radius, self.sphere_centre, self.sphere_radius = _mesh_bounds(self.scenery)
        self.sky = make_sky(rng, appearance, plan.setting.environment)
        self.agent_meshes = AgentMeshes(plan.world.agents, appearance.lights_on)
        glowing = self.scenery.spheres.emissive
        self.lamp_xy = self.scenery.spheres.centre[glowing, :2] if appearance.lights_on else np.zeros((0, 2))
        self.cameras = [CameraRenderer(c, appearance, appearance.palette["ground"]) for c in cameras]

    # ------------------------------------------------------------ per-frame drawables

    def geometry(self, state: FrameState) -> FrameGeometry:
        """Shaded drawables near the ego at one frame."""
        ego_xy = np.array([state.ego.x, state.ego.y])

        def near(centre: np.ndarray, radius: np.ndarray) -> np.ndarray:
            return np.linalg.norm(centre - ego_xy, axis=1) < VIEW_RADIUS + radius

        world = self.plan.world
        agents_near = near(state.agents.xy, np.zeros(len(world.agents)))
        junctions = [j for j, site in enumerate(world.layout.junctions)
                     if np.linalg.norm(site.centre - ego_xy) < VIEW_RADIUS]
        mesh = Mesh.concat([
            self.scenery.select(near(self.solid_centre, self.solid_radius),
                                near(self.sphere_centre, self.sphere_radius)),
            self.agent_meshes.posed(state.agents, state.t, agents_near),
            traffic_lights(world.layout, state, junctions)])
        ego_from_world = np.linalg.inv(world_from_ego(state))
        palette = self.appearance.palette
        ground = [(polys, palette[colour])
                  for polys, colour in self.ground.frame_groups(ego_xy, state.ego.s, VIEW_RADIUS)]
        shadows = self._shadows(state, agents_near)
        if shadows:
            ground.append((shadows, palette["asphalt"] * 0.55))
        face_colour, normal, centre, quads, decal_colour, sphere_colour = shade_mesh(mesh, self.appearance,
                                                                                     ego_from_world)
        return FrameGeometry(ego_from_world, ground, mesh, face_colour, normal, centre, quads, decal_colour,
                             sphere_colour, self._light_pools(ego_xy))

    def _light_pools(self, ego_xy: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Three rings of light on the ground under each street lamp within 90 m."""
        near = self.lamp_xy[np.linalg.norm(self.lamp_xy - ego_xy, axis=1) < 90.0]
        angles = np.linspace(0, 2 * np.pi, 17)[:-1]
        circle = np.c_[np.cos(angles), np.sin(angles), np.zeros_like(angles)]
        pools = []
        for xy in near:
            for radius, strength in POOL_RINGS:
                pools.append((np.r_[xy, 0.0] + radius * circle, strength * LAMP_LIGHT))
        return pools

    def _shadows(self, state: FrameState, near: np.ndarray) -> list[np.ndarray]:
        """Dark footprints under vehicles (contact shadows), (4, 3) world polygons."""
        a = self.plan.world.agents
        idx = np.flatnonzero(near & (a.category != PEDESTRIAN))
        half = a.size[idx, :2] / 2 + 0.1
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])[None] * half[:, None]
        yaw = state.agents.yaw[idx][:, None]
        x = state.agents.xy[idx, :1] + np.cos(yaw) * corners[..., 0] - np.sin(yaw) * corners[..., 1]
        y = state.agents.xy[idx, 1:] + np.sin(yaw) * corners[..., 0] + np.cos(yaw) * corners[..., 1]
        return list(np.stack([x, y, np.zeros_like(x)], axis=-1))

    # ------------------------------------------------------------ rendering

    def render(self, state: FrameState, frame: int) -> np.ndarray:
        """(v, h, w, 3) uint8 RGB images of every camera at one frame."""
        geo = self.geometry(state)
        return np.stack([self.render_camera(geo, k, frame, state.speed) for k in range(len(self.cameras))])

    def render_camera(self, geo: FrameGeometry, k: int, frame: int, ego_speed: float) -> np.ndarray:
        cam = self.cameras[k]
        cam_from_world = cam.cam_from_ego @ geo.ego_from_world
        img = cam.background.copy()
        draw_sky(img, cam, self.sky, cam_from_world)
        cam.draw_ground(img, geo, cam_from_world)
        cam.light_ground(img, geo, cam_from_world)
        cam.draw_objects(img, geo, cam_from_world)
        rng = np.random.default_rng([self.appearance.seed, frame, k])
        draw_precipitation(img, self.appearance, rng, ego_speed, cam.camera)
        return img

    def boxes_2d(self, state: FrameState, max_range: float) -> dict[str, list[dict]]:
        """Camera name → 2D boxes of agents within `max_range` m (see labels.boxes_2d)."""
        agents_near = np.linalg.norm(state.agents.xy - [state.ego.x, state.ego.y], axis=1) < max_range
        mesh = self.agent_meshes.posed(state.agents, state.t, agents_near)
        ego_from_world = np.linalg.inv(world_from_ego(state))
        out = {}
        for cam in self.cameras:
            out[cam.camera.name] = boxes_2d(cam, self.plan.world, cam.cam_from_ego @ ego_from_world, mesh.solids.verts,
                                            mesh.solids.instance, mesh.spheres.centre, mesh.spheres.radius,
                                            mesh.spheres.instance)
        return out

    def instance_ids(self, state: FrameState, k: int) -> np.ndarray:
        """(h, w) int64 image of agent track ids (−1 where no agent is visible) for camera k;
        scenery and nearer agents occlude farther ones."""
        geo = self.geometry(state)
        cam = self.cameras[k]
        ids = np.zeros((cam.h, cam.w), np.int32)
        cam.draw_objects(ids, geo, cam.cam_from_ego @ geo.ego_from_world, instance=True)
        return ids.astype(np.int64) - 1


def draw_precipitation(img: np.ndarray, appearance: Appearance, rng: np.random.Generator, ego_speed: float,
                       camera: CameraSpec) -> None:
    """Rain streaks or snow flakes blended over the image (in place); slant grows with speed."""
    if appearance.precipitation == "none":
        return
    h, w = img.shape[:2]
    overlay = img.copy()
    if appearance.precipitation == "rain":
        n = int(0.0012 * h * w) + 4
        x, y = rng.uniform(0, w, n), rng.uniform(-0.1 * h, h, n)
        length = rng.uniform(0.04, 0.09, n) * h
        slant = 0.15 + 0.01 * ego_speed * np.sign(camera.extrinsics[1, 2] + 1e-9)
        lines = np.stack([np.c_[x, y], np.c_[x + slant * length, y + length]], axis=1)
        colour = (np.clip(appearance.sky_horizon * 1.25 + 0.1, 0, 1) * 255).tolist()
        cv2.polylines(overlay, list(np.round(lines * 16).astype(np.int32)), False, colour, max(1, h // 320),
                      cv2.LINE_AA, 4)
        alpha = 0.3
    else:
        n = int(0.0015 * h * w) + 4
        centres = np.round(np.c_[rng.uniform(0, w, n), rng.uniform(0, h, n)] * 16).astype(np.int32)
        radii = np.round(rng.uniform(0.4, 1.6, n) * max(1.0, h / 160) * 16).astype(np.int32)
        colour = (np.clip(appearance.ambient * 1.8 + 0.2, 0, 1) * 255).tolist()
        for c, r in zip(centres, radii):
            cv2.circle(overlay, (int(c[0]), int(c[1])), int(r), colour, -1, cv2.LINE_AA, 4)
        alpha = 0.8
    cv2.addWeighted(overlay, alpha, img, 1 - alpha, 0, dst=img)
