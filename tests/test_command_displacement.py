"""The image displacement of the GAIA-2 action table's commanded contrasts (protocols/command_displacement.py)."""

import numpy as np
import pytest
import torch

from gaia_app.data.synthetic.dataset import SyntheticClipDataset
from gaia_app.models.gaia2.ego_flow import LIMIT, pose_flow
from gaia_app.protocols.command_displacement import displacement_table, ego_poses, markdown, scene_positions
from tests.conftest import load_benchmark

COMMANDS = [("brake", "straight"), ("accelerate", "straight"), ("keep", "left"), ("keep", "right")]


@pytest.fixture(scope="module")
def rig_scenes():
    world = SyntheticClipDataset(num_clips=3, seed=5, height=32, width=56, clip_len=12, fps=12.5,
                                 cameras=["front", "front_left", "front_right"])
    return [world.sample(i) for i in range(3)]


def test_ego_poses_integrate_the_arcs_from_the_last_context_frame():
    straight = np.array([[10.0, 0.0]] * 5)
    move, yaw = ego_poses(straight, first=2, rate=10.0)
    assert torch.allclose(move[:, 0], torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    assert move[:, 1].abs().max() == 0 and yaw.abs().max() == 0
    # constant curvature: the heading grows by distance · curvature per frame, the ego drifts left
    move, yaw = ego_poses(np.array([[10.0, 0.05]] * 5), first=2, rate=10.0)
    assert torch.allclose(yaw, torch.tensor([0.05, 0.10, 0.15], dtype=torch.float64))
    assert (move[:, 1] > 0).all()


def test_pose_flow_clips_only_when_asked():
    intrinsics = torch.tensor([[[[28.0, 0, 28], [0, 28, 16], [0, 0, 1]]]], dtype=torch.float64)
    extrinsics = torch.eye(4, dtype=torch.float64)
    extrinsics[:3, :3] = torch.tensor([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=torch.float64)  # camera → ego
    extrinsics[2, 3] = 1.5
    move, yaw = torch.tensor([[[4.0, 0, 0]]], dtype=torch.float64), torch.zeros(1, 1, dtype=torch.float64)
    clipped = pose_flow(move, yaw, intrinsics, extrinsics[None, None], (32, 56), (32, 56))
    free = pose_flow(move, yaw, intrinsics, extrinsics[None, None], (32, 56), (32, 56), limit=None)
    assert clipped.abs().max() <= LIMIT and free.abs().max() > LIMIT
    inside = free.abs().amax(-1) < LIMIT
    assert torch.equal(clipped[inside], free[inside])


def test_a_standing_ego_moves_nothing(rig_scenes):
    still = np.zeros((12, 2))
    assert scene_positions(rig_scenes[0], still, first=4, rate=12.5).abs().max() < 1e-9


def test_curvature_moves_the_picture_far_more_than_speed(rig_scenes):
    table = displacement_table(rig_scenes, COMMANDS, first=4, frames=12, cell_px=2.0, token_px=4.0)
    speed, curvature = table["summary"]["speed_contrast"], table["summary"]["curvature_contrast"]
    assert table["contrasts"]["speed_contrast"] == ["accelerate/straight", "brake/straight"]
    assert 0 < speed["last"]["mean"] < curvature["last"]["mean"] / 5
    assert speed["horizon"]["mean"] < speed["last"]["mean"]  # the contrast grows over the horizon
    assert 0 <= speed["share_token"]["mean"] <= speed["share_cell"]["mean"] <= 1
    assert len(table["per_scene"]["curvature_contrast"]["last"]) == 3
    assert "| curvature_contrast |" in markdown(table)


def test_bad_context_length_is_named(rig_scenes):
    with pytest.raises(ValueError, match="context frames 12"):
        displacement_table(rig_scenes, COMMANDS, first=12, frames=12, cell_px=2.0, token_px=4.0)


def test_the_benchmark_reads_the_grid_from_the_weights_and_writes_its_table(tmp_path):
    bench = load_benchmark("command_displacement")
    result = bench.main(["--weights", "gaia2", "--out", str(tmp_path), "--", "context.seed=5111",
                         "model.evaluate.contexts=2"])
    assert result["scenes"] == 2 and result["cell_px"] > 0 and result["token_px"] >= result["cell_px"]
    speed, curvature = (result["summary"][m]["last"]["mean"] for m in ("speed_contrast", "curvature_contrast"))
    assert 0 < speed < curvature
    assert "| speed_contrast |" in (tmp_path / "command_displacement.md").read_text()
    assert (tmp_path / "command_displacement.json").stat().st_size > 0
