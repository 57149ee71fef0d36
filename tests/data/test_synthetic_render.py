"""Rendering of the synthetic world measured on the images: projection geometry, motion,
near-plane clipping, masks against 2D boxes, lighting, and the multi-camera rig."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gaia_app.data.synthetic import AgentSpec, Scenario, Straight, generate_clip, generate_sample
from gaia_app.data.synthetic.appearance import make_appearance
from gaia_app.data.synthetic.geometry import Mesh
from gaia_app.data.synthetic.render import CameraRenderer, FrameGeometry
from gaia_app.data.synthetic.rig import build_rig, camera_spec, project_points

T = 8
EMPTY_ROAD = dict(environment="rural", country="DE", weather="clear", time_of_day="day", road=(Straight(700.0),),
                  roadside=False)
"""A straight, empty rural road in clear daylight, without roadside objects (add agents=() for no traffic)."""


def open_loop(speed: float, curvature: float, frames: int = T) -> np.ndarray:
    return np.tile([speed, curvature], (frames, 1))


def luma(img: np.ndarray) -> np.ndarray:
    return img.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


# ---------------------------------------------------------------- geometry on a straight road


@pytest.fixture(scope="module")
def straight_clip():
    scenario = Scenario(**EMPTY_ROAD, agents=(), lanes=3, ego_lane=1, ego_actions=open_loop(10.0, 0.0))
    return generate_clip(seed=4, height=128, width=224, clip_len=T, scenario=scenario)


def lane_marking_columns(img: np.ndarray, expected: dict[str, np.ndarray], rows: np.ndarray) -> dict[str, list]:
    """Per row, the centroid (intrinsics convention: pixel j spans [j, j+1]) of the white run
    nearest to each expected lane-line column, when one lies within 25 % of its distance to the
    image centre."""
    white = img.min(axis=2) > 150
    centre = img.shape[1] / 2
    found = {"left": [], "right": []}
    for v in rows:
        cols = np.flatnonzero(white[v]) + 0.5
        for side, u_expected in expected.items():
            near = cols[np.abs(cols - u_expected[v]) < 0.25 * abs(u_expected[v] - centre) + 1.0]
            if len(near):
                found[side].append((v + 0.5, near.mean()))
    return found


def expected_lines(camera, half_lane: float, height: int) -> dict[str, np.ndarray]:
    """Column of each ego-lane line per image row, from projecting ground points at ±half_lane."""
    x = np.linspace(4.0, 300.0, 4000)
    out = {}
    for side, y in (("left", half_lane), ("right", -half_lane)):
        uv, _ = project_points(camera, np.c_[x, np.full_like(x, y), np.zeros_like(x)])
        order = np.argsort(uv[:, 1])
        out[side] = np.interp(np.arange(height) + 0.5, uv[order, 1], uv[order, 0])
    return out


def vanishing_point(found: dict[str, list]) -> np.ndarray:
    """Intersection of the lines u = a + b v fitted to the left and right markings."""
    (bl, al), (br, ar) = (np.polyfit(*np.array(found[s]).T, 1) for s in ("left", "right"))
    v = (ar - al) / (bl - br)
    return np.array([al + bl * v, v])


def test_straight_road_keeps_vanishing_point_still_and_lines_symmetric(straight_clip) -> None:
    cam = straight_clip.cameras[0]
    half_lane = straight_clip.meta["lane_width"] / 2
    expected = expected_lines(cam, half_lane, cam.height)
    horizon = cam.intrinsics[1, 2] - cam.intrinsics[1, 1] * np.tan(np.radians(3.0))
    rows = np.arange(int(horizon) + 12, cam.height)
    points = []
    for t in range(T):
        found = lane_marking_columns(straight_clip.frames[0, t].transpose(1, 2, 0), expected, rows)
        assert len(found["left"]) > 10 and len(found["right"]) > 10
        for side in ("left", "right"):
            v, u = np.array(found[side]).T
            assert np.abs(u - np.interp(v, np.arange(cam.height) + 0.5, expected[side])).mean() < 1.0
        left, right = dict(found["left"]), dict(found["right"])
        both = sorted(set(left) & set(right))
        # Mirror symmetry about the principal point: equal distances left and right.
        assert np.abs([(left[v] + right[v]) / 2 - cam.width / 2 for v in both]).mean() < 0.6
        points.append(vanishing_point(found))
    points = np.array(points)
    assert np.allclose(points[:, 0], cam.width / 2, atol=1.5)
    assert np.allclose(points[:, 1], horizon, atol=2.0)
    # The vanishing point does not move; its row is less precise (dashes come and go at the far end).
    assert np.ptp(points[:, 0]) < 0.5 and np.ptp(points[:, 1]) < 2.0


@pytest.mark.parametrize("curvature", [0.04, -0.04, 0.0])
def test_turning_left_moves_the_scene_right(curvature: float) -> None:
    """Content near the horizon (far hills, the far road) shifts by fx · Δyaw, right when the ego
    turns left; translation barely moves it."""
    speed = 8.0
    clip = generate_clip(seed=2, height=96, width=168, clip_len=T,
                         scenario=Scenario(**EMPTY_ROAD, agents=(), lanes=1, ego_actions=open_loop(speed, curvature)))
    cam = clip.cameras[0]
    horizon = int(cam.intrinsics[1, 2] - cam.intrinsics[1, 1] * np.tan(np.radians(3.0)))
    sky = [luma(clip.frames[0, t].transpose(1, 2, 0))[horizon - 10:horizon + 3] for t in (0, T - 1)]
    first, last = (np.float32(s - s.mean(axis=1, keepdims=True)) for s in sky)  # keep horizontal structure only
    (dx, _), _ = cv2.phaseCorrelate(first, last)
    expected = cam.intrinsics[0, 0] * speed * curvature * (T - 1) / clip.fps
    assert abs(dx - expected) < 1.5, (dx, expected)
    if curvature:
        assert np.sign(dx) == np.sign(curvature)


# ---------------------------------------------------------------- clipping at the near plane


def render_ground(points_ego: np.ndarray, camera) -> np.ndarray:
    """Fill one white ground polygon given in the ego frame on a black image; (h, w) bool."""
    app = make_appearance(np.random.default_rng(0), "clear", "day", "rural")
    renderer = CameraRenderer(camera, app, np.zeros(3))
    geo = FrameGeometry(np.eye(4), [([points_ego], np.ones(3))], Mesh.empty(), *([np.zeros((0, 6, 3))] * 3),
                        np.zeros((0, 4, 3)), np.zeros((0, 3)), np.zeros((0, 3)))
    img = np.zeros((camera.height, camera.width, 3), np.uint8)
    renderer.draw_ground(img, geo, renderer.cam_from_ego)
    return img[..., 0] > 127


def ground_truth_mask(camera, inside) -> np.ndarray:
    """Pixels whose centre ray hits the ground (z = 0, ego frame) at a point where inside(x, y)."""
    j, i = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    k = camera.intrinsics
    rays = (np.stack([(j - k[0, 2]) / k[0, 0], (i - k[1, 2]) / k[1, 1], np.ones_like(j)], -1)
            @ camera.extrinsics[:3, :3].T)
    origin = camera.extrinsics[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -origin[2] / rays[..., 2]
    hit = origin + t[..., None] * rays
    return (t > 0) & inside(hit[..., 0], hit[..., 1])


@pytest.mark.parametrize("name", ["front", "rear_left"])
def test_polygon_crossing_behind_the_camera_renders_without_wrap_around(name: str) -> None:
    """A ground quad from 15 m behind to 40 m ahead of the ego: near-plane clipping keeps exactly
    the visible part; without it, vertices behind the camera would project mirrored above."""
    camera = camera_spec(name, 96, 168)
    quad = np.array([[-15.0, -1.5, 0.0], [40.0, -1.5, 0.0], [40.0, 3.0, 0.0], [-15.0, 3.0, 0.0]])
    drawn = render_ground(quad, camera)
    truth = ground_truth_mask(camera, lambda x, y: (x > -15) & (x < 40) & (y > -1.5) & (y < 3.0))

    def grow(mask: np.ndarray) -> np.ndarray:
        return cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)

    def shrink(mask: np.ndarray) -> np.ndarray:
        return cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)

    assert truth.sum() > 500
    assert not (drawn & ~grow(grow(truth))).any()  # no stray pixels anywhere (wrap-around would fill the sky)
    assert not (shrink(truth) & ~drawn).any()  # and nothing visible is missing
    assert (drawn != truth).sum() < 0.08 * truth.sum()  # they differ by anti-aliased edge pixels only


# ---------------------------------------------------------------- masks, boxes, lighting, rig


def test_agent_2d_box_matches_its_mask() -> None:
    scenario = Scenario(**EMPTY_ROAD, lanes=2, ego_lane=1, ego_actions=open_loop(5.0, 0.0, 4),
                        agents=(AgentSpec("car", gap=9.0, lane=0, parked=True),
                                AgentSpec("bus", gap=30.0, lane=1, speed=5.0),
                                AgentSpec("pedestrian", gap=14.0, d=-9.5, parked=True)))
    sample = generate_sample(seed=8, height=128, width=224, clip_len=4, scenario=scenario)
    for t in (0, 3):
        ids = sample.instance_ids(t, "front")
        boxes = sample.clip.frame_meta[t]["boxes_2d"]["front"]
        assert {b["category"] for b in boxes} == {"car", "bus", "pedestrian"}
        for b in boxes:
            rows, cols = np.nonzero(ids == b["track_id"])
            mask_box = np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1])
            x0, y0, x1, y1 = b["box"]
            inter = (max(0, min(x1, mask_box[2]) - max(x0, mask_box[0]))
                     * max(0, min(y1, mask_box[3]) - max(y0, mask_box[1])))
            union = (x1 - x0) * (y1 - y0) + np.prod(mask_box[2:] - mask_box[:2]) - inter
            assert np.abs(mask_box - np.array(b["box"])).max() <= 1.5, (b, mask_box)
            if b["category"] != "pedestrian":  # a pedestrian is 7 px wide: one pixel of rasterisation costs 15 %
                assert inter / union > 0.9, (b, mask_box)


def test_night_frames_are_much_darker_than_day_frames() -> None:
    """Same scene and seed: night mean luminance is below 35 % of day (headlights keep it above 0)."""
    means = {}
    for tod in ("day", "night"):
        scenario = Scenario(environment="urban", country="DE", weather="clear", time_of_day=tod)
        frames = generate_clip(seed=21, clip_len=2, cameras=2, scenario=scenario).frames
        means[tod] = luma(frames.transpose(0, 1, 3, 4, 2)).mean()
    assert 0.0 < means["night"] < 0.35 * means["day"]


def test_adjacent_cameras_overlap() -> None:
    """Every pair of adjacent default cameras sees a common ground point, and a car placed in the
    front / front_left overlap appears in both views with the same colour."""
    rig = {c.name: c for c in build_rig(5, 64, 112)}

    def yaw_of(cam) -> float:  # optical axis in the ego frame
        return np.arctan2(cam.extrinsics[1, 2], cam.extrinsics[0, 2])

    for a, b in (("front", "front_left"), ("front", "front_right"), ("front_left", "rear_left"),
                 ("front_right", "rear_right")):
        yaw = (yaw_of(rig[a]) + yaw_of(rig[b])) / 2  # the bisector lies in both fields of view
        point = np.array([[30 * np.cos(yaw), 30 * np.sin(yaw), 0.0]])
        for cam in (rig[a], rig[b]):
            uv, depth = project_points(cam, point)
            assert depth[0] > 0 and 0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height, (a, b, cam.name)
    scenario = Scenario(**EMPTY_ROAD, lanes=1, ego_actions=open_loop(0.0, 0.0, 1),
                        agents=(AgentSpec("car", gap=14.0, d=9.0, parked=True),))
    sample = generate_sample(seed=3, height=96, width=168, cameras=["front", "front_left"], clip_len=1,
                             scenario=scenario)
    colours = []
    for k in range(2):
        seen = sample.instance_ids(0, k) == 0
        assert seen.sum() > 30
        colours.append(sample.clip.frames[k, 0].transpose(1, 2, 0)[seen].mean(axis=0))
    assert np.abs(colours[0] - colours[1]).max() < 30
