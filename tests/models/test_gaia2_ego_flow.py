"""Ego-motion flow of the GAIA-2 action raster (models/gaia2/ego_flow.py): the geometry a commanded action implies."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gaia_app.data.synthetic.rig import build_rig
from gaia_app.models.gaia2.ego_flow import ego_motion_flow, step_seconds

GRID = (8, 14)


def flows(actions: list[list[float]], cameras: int = 3) -> torch.Tensor:
    """(t, v, gh, gw, 2) flow of the default rig at 64×112 for per-step (speed, curvature), 0.32 s per step."""
    specs = build_rig(cameras, 64, 112)
    k = torch.from_numpy(np.stack([c.intrinsics for c in specs])).float()[None]
    e = torch.from_numpy(np.stack([c.extrinsics for c in specs])).float()[None]
    a = torch.tensor([actions])
    return ego_motion_flow(a, torch.full(a.shape[:2], 0.32), k, e, (64, 112), GRID)[0]


def test_driving_straight_expands_the_front_view_about_its_centre_and_faster_expands_more() -> None:
    slow, fast, still = flows([[8.0, 0.0], [12.0, 0.0], [0.0, 0.0]])[:, 0]  # front camera
    x = slow[..., 0]
    torch.testing.assert_close(x, -x.flip(-1), atol=1e-4, rtol=0)  # left half moves left, right half right
    assert (x[:, GRID[1] // 2:] >= 0).all() and x[:, -1].max() > 0.2
    ground = slice(4, 7)  # rows below the horizon, before the clip at the image edge
    assert fast[ground].abs().sum() > 1.3 * slow[ground].abs().sum()
    assert still.abs().max() < 1e-5  # standing still moves nothing (float round-off of the projection)


def test_turning_left_moves_distant_scene_right_in_every_camera_and_right_turns_mirror_it() -> None:
    left, straight, right = flows([[10.0, 0.02], [10.0, 0.0], [10.0, -0.02]])
    sky = slice(0, 3)  # rows above the horizon, FAR away: the turn's flow dominates the drive's
    assert (left[:, sky, :, 0] - straight[:, sky, :, 0] > 0.3).all()
    assert (right[:, sky, :, 0] - straight[:, sky, :, 0] < -0.3).all()
    assert (left[0, sky, :, 0] > 0.3).all()  # the front camera: the whole distant view slides right
    torch.testing.assert_close(left[0, sky, :, 0], -right[0, sky, :, 0].flip(-1), atol=1e-3, rtol=0)


def test_points_that_pass_behind_the_camera_get_no_flow_and_flows_are_clipped() -> None:
    flow = flows([[30.0, 0.0]])[0, 0]  # 9.6 m in one step: the nearest ground leaves the view
    assert flow.abs().max() <= 8.0
    assert (flow[-1] == 0).all()


def test_step_seconds_come_from_timestamps_and_missing_ones_are_named() -> None:
    seconds = step_seconds(torch.tensor([[0.0, 0.32, 0.64]]), 3)
    torch.testing.assert_close(seconds, torch.tensor([[0.32, 0.32, 0.32]]))
    with pytest.raises(ValueError, match="action_raster.*timestamps"):
        step_seconds(None, 3)
    with pytest.raises(ValueError, match="increase"):
        step_seconds(torch.tensor([[0.0, 0.0]]), 2)
