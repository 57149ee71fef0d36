"""Controllability probes and metrics (gaia_app/eval/controllability.py, gaia_app/models/probes.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.eval.controllability import (
    action_error,
    action_errors,
    attribute_shares,
    augment_pairs,
    contrast_errors,
    contrast_pairs,
    jitter,
    load_probes,
    phase_clips,
    probe_clips,
    probed_actions,
    realised_contrasts,
    save_probes,
    strided_actions,
    train_probes,
)
from gaia_app.eval.intervals import (
    mean_interval,
    ratio_interval,
    share_interval,
    t_quantile,
)
from gaia_app.models.probes import ATTRIBUTES, InverseDynamicsProbe, SceneAttributeProbe
from gaia_app.protocols.controllability import (
    drive,
    error_row,
    probe_training_data,
    random_command,
    resimulate,
    world_clips,
)


@pytest.fixture(scope="module")
def clips():
    world = SyntheticClipDataset(num_clips=4, seed=5, height=32, width=48, clip_len=13)
    return probe_clips([world[i] for i in range(4)], rate=6.25, frames=4)


def test_probe_clips_carry_frames_actions_and_labels(clips) -> None:
    assert clips.frames.shape == (4, 4, 3, 32, 48) and clips.actions.shape == (4, 4, 2)
    assert set(clips.labels) == set(ATTRIBUTES) and all(v.shape == (4, 4) for v in clips.labels.values())
    assert clips.frames.min() >= -1 and clips.frames.max() <= 1


def test_probes_learn_a_tiny_batch(clips) -> None:
    _, _, fit = train_probes(clips, steps=120, batch=8, lr=3e-3, progress=False)
    assert fit["last_loss"] < fit["first_loss"] / 3, fit


def test_strided_probe_learns_a_tiny_batch_and_refuses_a_stride_the_clips_cannot_hold(clips) -> None:
    _, _, fit = train_probes(clips, steps=120, batch=8, lr=3e-3, progress=False, stride=2)
    assert fit["last_loss"] < fit["first_loss"] / 3, fit
    with pytest.raises(ValueError, match=r"probe stride 4: expected 1 ≤ stride < 4"):
        train_probes(clips, steps=1, progress=False, stride=4)


@pytest.fixture(scope="module")
def rig_clips():
    world = SyntheticClipDataset(num_clips=4, seed=5, height=32, width=48, clip_len=13,
                                 cameras=["front", "front_left", "front_right"])
    return [world[i] for i in range(4)]


def test_rig_probe_clips_keep_the_cameras_in_the_order_asked(rig_clips) -> None:
    rig = probe_clips(rig_clips, rate=6.25, frames=4, cameras=[0, 2])
    assert rig.frames.shape == (4, 4, 2, 3, 32, 48)
    front = probe_clips(rig_clips, rate=6.25, frames=4)
    right = probe_clips([clip.select_views(["front_right"]) for clip in rig_clips], rate=6.25, frames=4)
    assert torch.equal(rig.frames[:, :, 0], front.frames) and torch.equal(rig.frames[:, :, 1], right.frames)
    with pytest.raises(ValueError, match=r"camera indices \[0, 3\], the clip has 3"):
        probe_clips(rig_clips, rate=6.25, frames=4, cameras=[0, 3])


def test_a_mirrored_rig_pair_flips_every_view_swaps_left_and_right_and_negates_curvature() -> None:
    pair, actions = torch.randn(64, 2, 3, 3, 4, 6), torch.tensor([[5.0, 0.02]]).repeat(64, 1)
    mirrored, turned = augment_pairs(pair, actions, torch.Generator().manual_seed(0), mirror=[0, 2, 1])
    flipped = turned[:, 1] < 0
    assert 0 < flipped.sum() < 64 and torch.equal(turned[:, 0], actions[:, 0])
    assert torch.equal(mirrored[~flipped], pair[~flipped])
    assert torch.equal(mirrored[flipped], pair[flipped].flip(-1)[:, :, [0, 2, 1]])
    with pytest.raises(ValueError, match="a rig of 3 cameras needs its mirror order"):
        augment_pairs(pair, actions, torch.Generator(), mirror=[0, 1, 1])


def test_rig_probe_learns_a_tiny_batch_and_jitters_every_camera_of_a_pair_alike(rig_clips) -> None:
    rig = probe_clips(rig_clips, rate=6.25, frames=4, cameras=[0, 1, 2])
    dynamics, _, fit = train_probes(rig, steps=120, batch=8, lr=3e-3, progress=False, mirror=[0, 2, 1])
    assert dynamics.cameras == 3 and fit["last_loss"] < fit["first_loss"] / 3, fit
    pair = torch.zeros(2, 2, 3, 3, 4, 4)
    shifted = jitter(pair, torch.Generator().manual_seed(1))
    assert torch.equal(shifted[0], shifted[0, 0, 0, 0, 0, 0].expand_as(shifted[0]))  # one gain and offset per pair
    pair = rig.frames[:2, :2].clone()  # (2, 2, 3 cameras, 3, H, W)
    moved = pair.clone()
    moved[:, 1, 2] = moved[:, 1, 2].roll(3, dims=-1)  # only the right camera's second frame changes
    assert not torch.allclose(dynamics(pair), dynamics(moved))  # every camera reaches the head
    with pytest.raises(ValueError, match=r"InverseDynamicsProbe\(3 camera\(s\)\): expected pairs \(b, 2, 3, 3, H, W\)"):
        dynamics(torch.zeros(1, 2, 2, 3, 32, 48))


class FrameGap(InverseDynamicsProbe):
    """'Speed' = value of the second frame minus the first's, 'curvature' = the first frame's value."""

    def forward(self, pair: torch.Tensor) -> torch.Tensor:
        first, second = pair[:, 0].mean(dim=(1, 2, 3)), pair[:, 1].mean(dim=(1, 2, 3))
        return torch.stack([second - first, first], dim=1)


def test_a_strided_probe_reads_frames_stride_apart_against_the_mean_action_between_them() -> None:
    frames = torch.arange(6.0)[None, :, None, None, None].expand(1, 6, 3, 4, 4)  # frame i holds the value i
    probed = probed_actions(FrameGap(), frames, start=3, stride=2)  # pairs (1, 3), (2, 4), (3, 5)
    torch.testing.assert_close(probed[0], torch.tensor([[2.0, 1.0], [2.0, 2.0], [2.0, 3.0]]))
    with pytest.raises(ValueError, match=r"start 1 must lie in \[stride 2, frames 6\)"):
        probed_actions(FrameGap(), frames, start=1, stride=2)
    actions = torch.arange(12.0).view(1, 6, 2)  # a_i = (2i, 2i + 1)
    strided = strided_actions(actions, 2)
    torch.testing.assert_close(strided[0, 2], (actions[0, 1] + actions[0, 2]) / 2)  # a_1, a_2 move frame 1 to 3
    torch.testing.assert_close(strided[0, :1], actions[0, :1])  # no pair ends at frame 1
    assert strided_actions(actions, 1) is actions
    # error_row compares each probed pair with the mean action it spans: a probe that reads the mean exactly scores 0
    commanded = torch.tensor([[5.0, 0.0]]).repeat(4, 6, 1)  # 2 commands × 2 contexts, command-major
    commanded[2:] = torch.tensor([9.0, 0.02])
    commanded[..., 0] += torch.arange(6.0)  # speeds that change every step: the mean over the pair matters

    class Exact(InverseDynamicsProbe):
        def forward(self, pair: torch.Tensor) -> torch.Tensor:
            return pair[:, 1, :2, 0, 0]  # the frame carries its (speed, curvature) in two channels

    video = torch.zeros(4, 6, 3, 2, 2)
    video[:, :, :2] = strided_actions(commanded, 2)[:, :, :, None, None].roll(1, dims=1)  # frame i: the mean into i
    row = error_row(Exact(), video, commanded, start=3, commands=2, stride=2)
    assert row["speed_mae"]["mean"] == pytest.approx(0.0) and row["curvature_mae"]["mean"] == pytest.approx(0.0)


def test_error_row_scores_each_context_by_the_mean_over_its_draws() -> None:
    """draws futures per context: a context's contrast error is the mean of its draws' errors, and the intervals
    stay over contexts (N of them), not over N·draws."""
    commanded = torch.zeros(4, 5, 2)  # 2 commands (brake, accelerate) × 2 contexts, command-major
    commanded[:2, :, 0], commanded[2:, :, 0] = 5.0, 9.0
    commanded[2:, :, 1] = 0.01  # the curvature contrast needs two commands that differ too

    class ReadsChannel(InverseDynamicsProbe):
        def forward(self, pair: torch.Tensor) -> torch.Tensor:
            return pair[:, 1, :2, 0, 0]

    speeds = torch.tensor([[5.0, 7.0], [5.0, 5.0],    # brake: context 0 draws, context 1 draws
                           [9.0, 9.0], [6.0, 8.0]])  # accelerate
    video = torch.zeros(8, 5, 3, 2, 2)
    video[:, :, 0] = speeds.flatten()[:, None, None, None]
    row = error_row(ReadsChannel(), video, commanded, start=1, commands=2, draws=2)
    # realised speed contrasts per draw: context 0: 9−5 = 4, 9−7 = 2 → errors 0, 2; context 1: 6−5 = 1, 8−5 = 3 → 3, 1
    assert row["speed_contrast"]["mean"] == pytest.approx(1.5) and row["speed_contrast"]["n"] == 2
    assert row["realised"]["speed_contrast"]["per_context"] == pytest.approx([3.0, 2.0]) and row["draws"] == 2
    one_draw = error_row(ReadsChannel(), video[::2], commanded, start=1, commands=2)
    assert one_draw["speed_contrast"]["mean"] == pytest.approx(1.5) and one_draw["draws"] == 1  # errors 0 and 3
    with pytest.raises(ValueError, match="8 videos for 4 commanded futures × 3 draws"):
        error_row(ReadsChannel(), video, commanded, start=1, commands=2, draws=3)


class ConstantDynamics(InverseDynamicsProbe):
    def forward(self, pair: torch.Tensor) -> torch.Tensor:
        return torch.tensor([[10.0, 0.01]]).expand(pair.shape[0], 2)


def test_action_error_scores_only_the_steps_into_generated_frames() -> None:
    frames = torch.zeros(2, 5, 3, 8, 8)
    commanded = torch.tensor([10.0, 0.01]).repeat(2, 5, 1)
    commanded[:, :2] = 99.0  # a_0, a_1 lead into frames 1, 2: not scored from start = 3
    commanded[:, 4] = 99.0  # a_4 leads past the last frame: never scored
    commanded[:, 3, 0] = 12.0  # a_3 → frame 4: speed off by 2 on one of the two scored steps
    assert action_error(ConstantDynamics(), frames, commanded, start=3) == pytest.approx(
        {"speed_mae": 1.0, "curvature_mae": 0.0})
    commanded[1, 3, 1] = 0.03  # the second sequence's curvature is off by 0.02 on one of two steps
    per_sequence = action_errors(ConstantDynamics(), frames, commanded, start=3)
    torch.testing.assert_close(per_sequence, torch.tensor([[1.0, 0.0], [1.0, 0.01]]))


def test_contrast_cancels_a_per_scene_bias_and_charges_ignored_commands_the_commanded_difference() -> None:
    # 3 commands (brake, keep left, accelerate) × 2 contexts × 4 steps; speed and curvature per step
    commanded = torch.zeros(3, 2, 4, 2)
    commanded[0, :, :, 0] = torch.tensor([8.0, 7.0, 6.0, 5.0])  # brake
    commanded[1, :, :, 0], commanded[1, :, :, 1] = 9.0, 0.02  # keep speed, turn left
    commanded[2, :, :, 0] = torch.tensor([10.0, 11.0, 12.0, 13.0])  # accelerate
    commanded[2, :, :, 1] = -0.02  # and turn right
    assert contrast_pairs(commanded) == [(2, 0), (1, 2)]
    bias = torch.tensor([[3.0, 0.01], [-2.0, -0.005]])[None, :, None]  # each context's own probe error
    torch.testing.assert_close(contrast_errors(commanded + bias, commanded), torch.zeros(2, 2))
    ignored = commanded[1:2].expand(3, -1, -1, -1) + bias  # every future looks the same
    torch.testing.assert_close(contrast_errors(ignored, commanded), torch.tensor([[5.0, 0.04], [5.0, 0.04]]))
    # signed: a future that shows half of each command realises half of the commanded difference
    realised, wanted = realised_contrasts(commanded * 0.5 + bias, commanded)
    torch.testing.assert_close(wanted, torch.tensor([[5.0, 0.04], [5.0, 0.04]]))
    torch.testing.assert_close(realised, wanted * 0.5)
    realised_ignored, _ = realised_contrasts(ignored, commanded)
    torch.testing.assert_close(realised_ignored, torch.zeros(2, 2))
    with pytest.raises(ValueError, match="every command has the same speed"):
        contrast_pairs(commanded[[0, 0]])


class FixedScene(SceneAttributeProbe):
    def forward(self, frames: torch.Tensor) -> dict[str, torch.Tensor]:
        logits = torch.zeros(frames.shape[0], len(ATTRIBUTES["time_of_day"]))
        logits[::2, 2] = 1.0  # every other frame looks like night, the others like day
        return {"time_of_day": logits}


def test_attribute_shares_are_per_sequence_shares_of_frames_on_target() -> None:
    frames = torch.zeros(2, 3, 3, 8, 8)  # 6 frames: night, day, night | day, night, day
    night = ATTRIBUTES["time_of_day"].index("night")
    shares = attribute_shares(FixedScene(), frames, {"time_of_day": torch.full((2,), night)})
    torch.testing.assert_close(shares["time_of_day"], torch.tensor([2 / 3, 1 / 3]))


def test_intervals_match_known_values() -> None:
    assert t_quantile(1000) == pytest.approx(1.9623, abs=1e-3) and t_quantile(9) == pytest.approx(2.2622, abs=2e-3)
    assert t_quantile(31) == pytest.approx(2.0395, abs=1e-3)
    # exact where an interval over 2–4 training runs needs it (tables: 12.706, 4.303, 3.182)
    assert [round(t_quantile(df), 3) for df in (1, 2, 3)] == [12.706, 4.303, 3.182]
    est = mean_interval([1.0, 2.0, 3.0, 4.0])  # sd 1.291, t(3) = 3.182
    assert est.mean == 2.5 and est.half_width == pytest.approx(3.182 * 1.2910 / 2, rel=1e-2)
    wilson = share_interval(8, 10)  # textbook Wilson interval: [0.490, 0.943]
    assert (wilson.low, wilson.high) == pytest.approx((0.490, 0.943), abs=2e-3)
    assert share_interval(0, 16).low == 0.0 and 0 < share_interval(0, 16).high < 0.25
    with pytest.raises(ValueError):
        share_interval(3, 2)


def test_probes_round_trip_through_safetensors_and_refuse_another_size(tmp_path) -> None:
    torch.manual_seed(0)
    dynamics, scene = InverseDynamicsProbe(), SceneAttributeProbe()
    save_probes(tmp_path, dynamics, scene, {"image_size": [32, 48], "rate": 6.25})
    loaded, loaded_scene, info = load_probes(tmp_path, (32, 48), 6.25)
    pair, frames = torch.randn(2, 2, 3, 32, 48), torch.randn(2, 3, 32, 48)
    torch.testing.assert_close(loaded(pair), dynamics.eval()(pair))
    torch.testing.assert_close(loaded_scene(frames)["weather"], scene.eval()(frames)["weather"])
    with pytest.raises(ValueError, match=r"probes trained for image size \[32, 48\] at 6.25 Hz"):
        load_probes(tmp_path, (64, 112), 6.25)
    (tmp_path / "probes.safetensors").write_bytes(b"not a tensor file")
    with pytest.raises(ValueError, match="probes.safetensors: not a readable safetensors file"):
        load_probes(tmp_path, (32, 48), 6.25)
    with pytest.raises(FileNotFoundError, match="probes.safetensors is missing"):
        load_probes(tmp_path / "nowhere", (32, 48), 6.25)


def test_drive_switches_to_the_commanded_actions_at_step_t0() -> None:
    source = np.stack([np.arange(13.0), np.zeros(13)], axis=1)  # 25 Hz: 13 source frames = steps 0..3 at 6.25 Hz
    per_step = np.array([[0.0, 0.0], [0.0, 0.0], [20.0, 0.01], [30.0, 0.02]])
    driven = drive(source, per_step, t0=2, rate=6.25)
    np.testing.assert_array_equal(driven[:8], source[:8])  # steps 0 and 1 keep the source's own actions
    np.testing.assert_array_equal(driven[8:12], np.tile([20.0, 0.01], (4, 1)))
    np.testing.assert_array_equal(driven[12], [30.0, 0.02])


def test_random_commands_cover_the_presets_and_keep_the_past() -> None:
    rng = np.random.default_rng(0)
    source = np.stack([np.linspace(8, 9, 33), np.full(33, 0.001)], axis=1)
    commands = [random_command(rng, source, 3, 9, 6.25) for _ in range(200)]
    for cmd in commands:
        np.testing.assert_allclose(cmd[:3], source[[0, 4, 8]])
        assert cmd.shape == (9, 2) and (cmd[:, 0] >= 0).all() and len(set(cmd[3:, 1])) == 1
    curvatures = np.array([c[3, 1] for c in commands])
    accelerations = np.array([(c[4, 0] - c[3, 0]) * 6.25 for c in commands])
    assert curvatures.min() < -0.02 and curvatures.max() > 0.02 and (curvatures == 0).mean() > 0.2
    assert accelerations.min() < -4 and accelerations.max() > 2


def test_driven_probe_clips_follow_their_commands() -> None:
    data = probe_training_data(seed=3, count=4, height=32, width=48, frames=5, rate=6.25, driven_share=1.0)
    assert data.frames.shape == (16, 5, 3, 32, 48)  # 4 clips × their 4 phases at 6.25 Hz
    # each clip leaves its policy for one constant curvature, which all its phases end on
    last = data.actions.view(4, 4, 5, 2)[:, :, -1, 1]
    assert torch.equal(last, last[:, :1].expand(4, 4))
    weathers = probe_training_data(seed=3, count=24, height=16, width=16, frames=2, rate=6.25, driven_share=0.0)
    assert len(set(weathers.labels["weather"][:, 0].tolist())) == 4  # uniform mix: snow and fog appear too


def test_phase_clips_label_each_step_with_the_mean_action_it_spans() -> None:
    world = SyntheticClipDataset(num_clips=1, seed=2, height=16, width=16, clip_len=12)
    clip = world[0]
    phases = phase_clips(clip, rate=6.25, frames=3)
    assert phases.frames.shape == (4, 3, 3, 16, 16)
    torch.testing.assert_close(phases.frames[1, 2], probe_clips([clip.select_frames([9])], 6.25, 1).frames[0, 0])
    torch.testing.assert_close(phases.actions[2, 1], torch.from_numpy(clip.actions[6:10]).mean(dim=0))
    with pytest.raises(ValueError, match="needs actions and 16 frames"):
        phase_clips(clip, rate=6.25, frames=4)


def test_pooled_ratio_interval_resamples_units_and_pairs_differences() -> None:
    """IoU pooled over scenes: Σ intersections / Σ unions, a bootstrap interval around it; the paired difference of
    two ratios on the same scenes is exactly 0 for identical counts and excludes 0 for one better on every scene."""
    intersections, unions = [10, 20, 30, 40], [100, 100, 100, 100]
    pooled = ratio_interval(intersections, unions)
    assert pooled.mean == pytest.approx(0.25) and pooled.low < 0.25 < pooled.high and pooled.n == 4
    assert ratio_interval(intersections, unions) == pooled  # a fixed seed: reproducible tables
    same = ratio_interval(intersections, unions, minus=(intersections, unions))
    assert same.mean == same.low == same.high == 0.0
    better = ratio_interval([i + 5 for i in intersections], unions, minus=(intersections, unions))
    assert better.mean == pytest.approx(0.05) and better.low > 0
    with pytest.raises(ValueError, match="equal non-empty"):
        ratio_interval([1, 2], [3])


def test_clips_read_at_the_model_rate_render_only_those_frames() -> None:
    """world_clips and resimulate hand the probes 6.25 Hz clips rendered at 6.25 Hz (SyntheticClipDataset.render_rate),
    not 25 Hz clips resampled afterwards: 4 steps are 13 simulation steps but 4 rendered frames."""
    clip = world_clips(seed=3, count=1, height=32, width=48, frames=4, rate=6.25)[0]
    assert clip.frames.shape[1] == 4 and np.allclose(clip.timestamps, np.arange(4) / 6.25)
    actions = np.tile(np.array([[8.0, 0.0]]), (4, 1))
    assert resimulate(3, 0, 32, 48, actions, 2, 6.25).frames.shape == (1, 4, 3, 32, 48)
