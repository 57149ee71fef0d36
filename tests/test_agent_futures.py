"""Futures with moving agents (issue 49 item 3): the lead-gap reader, its scores, the re-simulated scenes and the
benchmark end to end on the shipped weights."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from gaia_app.data.synthetic.rig import camera_spec, project_points
from gaia_app.data.transforms import resample_indices
from gaia_app.eval.agent_fidelity import VEHICLES, fidelity_frames
from gaia_app.eval.lead_gap import (
    EGO_FRONT,
    LanePose,
    closer_under,
    commanded_pose,
    following,
    gap_error,
    ground_plane,
    labelled_gaps,
    lead_gaps,
    persistence,
    spread,
)
from gaia_app.protocols.agent_futures import at_rate
from gaia_app.protocols.controllability import driven_clip, world, world_samples

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.usefixtures("one_thread")


def test_the_ground_plane_inverts_the_camera_projection() -> None:
    """A road point projected into the front camera lands on a pixel whose lower edge maps back to it (within the
    pixel's footprint); rays above the horizon meet no road."""
    camera = camera_spec("front", 64, 112)
    ground = ground_plane(camera)
    for forward, left in ((8.0, 0.0), (15.0, -1.0), (25.0, 1.2)):
        (u, v), _ = project_points(camera, np.array([[forward, left, 0.0]]))[0][0], None
        row, col = int(np.floor(v - 0.5)), int(np.floor(u))  # the pixel whose lower edge is nearest the point
        assert abs(ground.forward[row, col] - forward) < 0.2 * forward
        assert abs(ground.left[row, col] - left) < 0.5
    assert np.isnan(ground.forward[0]).all() and np.isfinite(ground.forward[-1]).all()
    assert (np.diff(ground.forward[40:, 56]) < 0).all()  # lower rows are nearer


def test_a_masked_vehicle_in_the_lane_reads_its_gap_and_one_beside_it_does_not() -> None:
    camera = camera_spec("front", 64, 112)
    ground = ground_plane(camera)
    masks = torch.zeros(1, 3, 64, 112, dtype=torch.bool)
    masks[0, 0, 36:44, 50:62] = True  # ahead in the lane, lowest row 43
    masks[0, 1, 36:44, 0:6] = True  # far to the side: another lane or the kerb
    gaps = lead_gaps(masks, following(torch.zeros(1, 3)), ground)
    assert gaps[0, 0] == pytest.approx(ground.forward[43, 50:62].min() - EGO_FRONT, abs=1e-4)
    assert np.isnan(gaps[0, 1]) and np.isnan(gaps[0, 2])
    bent = lead_gaps(masks[:, :1], following(torch.full((1, 1), 0.2)), ground)  # a sharp bend: lane off the car
    assert np.isnan(bent[0, 0])


def test_a_command_that_turns_off_the_road_moves_the_lane_it_reads() -> None:
    """Steering left on a straight road turns the ego across it: the band along the road then lies to the ego's
    right, so a car ahead on the road is found there and not straight ahead; keeping the road's curvature leaves
    the heading at zero."""
    actions = torch.tensor([[[10.0, 0.02]] * 6, [[10.0, 0.0]] * 6])
    pose = commanded_pose(actions, torch.zeros(2), rate=6.25)
    assert (torch.diff(pose.heading[0]) > 0).all() and (pose.heading[1] == 0).all()
    assert pose.heading[0, -1] == pytest.approx(6 * 10 * 0.02 / 6.25)
    camera = camera_spec("front", 64, 112)
    ground = ground_plane(camera)
    heading = float(pose.heading[0, -1])
    (u, v), _ = project_points(camera, np.array([[15.0 + EGO_FRONT, -heading * (15.0 + EGO_FRONT), 0.0]]))[0][0], None
    masks = torch.zeros(1, 1, 64, 112, dtype=torch.bool)
    masks[0, 0, int(v) - 4:int(v), int(u) - 2:int(u) + 3] = True  # a car on the road, 15 m ahead
    turned = LanePose(pose.heading[:1, -1:], pose.curvature[:1, -1:])
    assert np.isfinite(lead_gaps(masks, turned, ground)).all()
    assert np.isnan(lead_gaps(masks, following(torch.zeros(1, 1)), ground)).all()


def test_scores_pool_frames_and_count_missing_readings_as_out_of_range() -> None:
    found = np.array([[True, True, False], [False, False, False]])
    present = np.array([[True, True, True], [True, False, False]])
    share = persistence(found, present, resamples=200)
    assert share.mean == pytest.approx(2 / 4) and share.low <= share.mean <= share.high and share.n == 2
    with pytest.raises(ValueError, match="no frame has a lead vehicle"):
        persistence(found, np.zeros_like(present))
    nan = float("nan")
    assert closer_under(np.array([5.0, nan, 7.0, nan]), np.array([9.0, 4.0, nan, nan])).tolist() == \
        [True, False, True, False]
    assert spread(np.array([10.0, 10.0, nan])) == 0 and spread(np.array([10.0, nan])) is None
    assert spread(np.array([8.0, 12.0])) == pytest.approx(2.0)
    assert gap_error(np.array([1.0, nan]), np.array([nan, 2.0])) is None


def test_the_reader_finds_labelled_lead_vehicles_from_true_masks() -> None:
    """On real frames with the world's own agent masks the reader finds every lead vehicle the labels give within
    30 m and reads its gap within a few metres (one pixel row is several metres near 30 m)."""
    rate, frames = 6.25, 8
    samples = world_samples(7777, 12, 64, 112, frames, rate)
    masks = fidelity_frames(samples, rate, frames).agents
    labels, curvature = [], []
    for sample in samples:
        picked = resample_indices(sample.clip.timestamps, rate)[:frames]
        labels.append(labelled_gaps([sample.clip.frame_meta[p] for p in picked], VEHICLES))
        curvature.append(sample.clip.actions[picked, 1])
    labels = np.stack(labels)
    read = lead_gaps(masks, following(torch.tensor(np.stack(curvature))), ground_plane(samples[0].clip.cameras[0]))
    present = np.isfinite(labels)
    assert present.sum() >= 8
    assert np.isfinite(read[present]).mean() >= 0.9
    assert gap_error(read, labels).mean < 4.0


def test_a_resimulated_follow_scene_keeps_its_lead_vehicle() -> None:
    """Driving a clip's scene with the clip's own actions gives back its lead vehicle and gaps: the re-simulation of
    the ceiling is the same scene, traffic included (a follow clip's lead used to vanish when actions were given)."""
    rate, total = 6.25, 8
    clips = world(4950, 40, 64, 112, total, rate, every_frame=False)
    follow = [i for i in range(40) if clips[i].meta["behaviour"] == "follow"]
    index = next(i for i in follow if np.isfinite(at_rate(clips[i], rate, total)[2]).all())
    own_frames, own_actions, own_gaps = at_rate(clips[index], rate, total)
    again = at_rate(driven_clip(4950, index, 64, 112, own_actions.numpy(), 0, rate, every_frame=False), rate, total)
    np.testing.assert_allclose(again[2], own_gaps, atol=0.05)


def load_benchmark():
    spec = importlib.util.spec_from_file_location("agent_futures_bench", ROOT / "benchmarks" / "agent_futures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_benchmark_scores_the_shipped_weights_and_draws_the_strip(tmp_path: Path) -> None:
    bench = load_benchmark()
    out = tmp_path / "out"
    results = bench.main(["--contexts", "2", "--futures", "2", "--spread-contexts", "2", "--out", str(out),
                          "--json", str(tmp_path / "r.json"), "--", "seconds=0.48"])  # 3 future frames
    stored = json.loads((tmp_path / "r.json").read_text())
    assert stored["contexts"] == 2 and len(stored["clip_indices"]) == 2 and stored["future_frames"] == 3
    assert set(stored["persistence"]) == {"real", "tokenized", "model"}
    assert set(stored["persistence_where_read_in_real"]) == {"tokenized", "model"}
    assert set(stored["interaction"]) == {"labels", "real", "tokenized", "model"}
    assert stored["interaction"]["labels"]["share"]["mean"] == 1.0  # the world: accelerating closes in on the lead
    assert 0 <= results["persistence"]["model"]["mean"] <= 1
    spread_table = stored["multiple_futures"]
    assert len(spread_table["model_spread_m"]) == 2 and len(spread_table["model_found"]) == 2
    assert (out / "futures_strip.png").stat().st_size > 0 and (out / "agent_futures.rrd").stat().st_size > 0
    assert "| model |" in (tmp_path / "r.md").read_text()
    with pytest.raises(SystemExit):
        bench.main(["--contexts", "1"])
