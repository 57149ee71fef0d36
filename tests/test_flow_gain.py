"""Teacher-forced condition gains of the GAIA-2 world model (gaia_app/eval/flow_gain.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from gaia_app.data.clip import ClipError
from gaia_app.data.latent_cache import LatentClip, write_latent_clip
from gaia_app.data.synthetic.labels import AgentBoxes
from gaia_app.data.synthetic.rig import CameraSpec, build_rig
from gaia_app.diffusion.flow_matching import velocity_target
from gaia_app.eval.flow_gain import (
    TAUS,
    condition_gain_report,
    every_window,
    flow_losses,
    swapped_actions,
)
from gaia_app.models.gaia2.conditioning import batch_conditions
from gaia_app.models.gaia2.latent_world_model import LatentWorldModel

META = {"weather": 6, "time_of_day": 5}


def cache(root: Path, clips: int = 3, steps: int = 5) -> Path:
    """A latent cache split of `clips` 3-camera clips, each driving at its own speed and curvature."""
    rig = [CameraSpec(c.name, c.intrinsics, c.extrinsics, c.width, c.height) for c in build_rig(3, 64, 112)]
    rng = np.random.default_rng(0)
    frames = steps * 4
    for i in range(clips):
        write_latent_clip(root, LatentClip(
            clip_id=f"clip_{i}", mean=rng.normal(size=(3, steps, 8, 8, 14)).astype(np.float32),
            logvar=np.full((3, steps, 8, 8, 14), -6, np.float32), temporal_downsampling=4, fps=12.5,
            image_size=(64, 112), timestamps=np.arange(frames) / 12.5, cameras=rig,
            meta={"weather": "rain", "time_of_day": "day", **({"open_loop": True} if i == 0 else {})},
            actions=np.tile(np.float32([5 + 3 * i, 0.02 * (i - 1)]), (frames, 1)),
            agents=[AgentBoxes([[12.0, 0.5, 0.8]], [[4.5, 1.8, 1.6]], [0.0], [0], [1]) for _ in range(frames)]))
    return root


def net() -> LatentWorldModel:
    """A small model with every weight perturbed (no zero-initialised path hides a condition)."""
    torch.manual_seed(0)
    model = LatentWorldModel(latent_channels=8, dim=32, depth=1, heads=4, metadata_fields=META, agent_raster=True,
                             action_raster=True)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return model.eval()


def test_every_window_takes_every_start_of_every_clip(tmp_path: Path) -> None:
    batch = every_window(cache(tmp_path / "val"), 4, list(META))
    assert batch["mean"].shape == (3 * 2, 3, 4, 8, 8, 14)  # 5 steps → starts 0 and 1, three clips
    assert batch["open_loop"].tolist() == [True, True, False, False, False, False]  # clip 0 leaves its policy
    with pytest.raises(ClipError, match="no finished clip folders"):
        every_window(tmp_path / "empty", 4, list(META))


def test_flow_losses_are_the_velocity_error_of_the_generated_steps_under_shared_noise(tmp_path: Path) -> None:
    batch = every_window(cache(tmp_path / "val"), 4, list(META))
    x, cond, model = batch["mean"], batch_conditions(batch), net()
    losses = flow_losses(model, x, {"a": cond, "b": cond, "dropped": cond.without("action")}, context=2,
                         taus=(0.5,), draws=1, seed=3)
    torch.testing.assert_close(losses["a"], losses["b"])  # the same noise for every variant
    noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(3))
    times = torch.full((x.shape[0], 4), 0.5)
    times[:, :2] = 1.0
    step = times[:, None, :, None, None, None]
    with torch.no_grad():
        direct = (model(step * x + (1 - step) * noise, times, cond) - velocity_target(x, noise))[:, :, 2:].pow(2)
    torch.testing.assert_close(losses["a"], direct.mean(dim=(1, 2, 3, 4, 5)))
    assert not torch.allclose(losses["a"], losses["dropped"])  # the actions reach the loss
    with pytest.raises(ValueError, match="context"):
        flow_losses(model, x, {"a": cond}, context=4)


def test_report_gives_gains_and_discrimination_with_intervals(tmp_path: Path) -> None:
    batch = every_window(cache(tmp_path / "val"), 4, list(META))
    report = condition_gain_report(net(), batch, latent_scale=0.5, context=2)
    assert report["windows"] == 6
    assert report["gain_over_neither"]["neither"]["mean"] == 0
    for row in [*report["gain_over_neither"].values(), *report["action_discrimination"].values()]:
        assert row["low"] <= row["mean"] <= row["high"] and row["n"] == 6
    assert report["action_discrimination"]["with agents"]["mean"] != 0  # swapped actions change the loss
    with pytest.raises(ValueError, match="two windows"):
        swapped_actions(batch_conditions(every_window(cache(tmp_path / "one", clips=1, steps=4), 4, list(META))))


def test_one_action_component_is_swapped_at_a_time(tmp_path: Path) -> None:
    cond = batch_conditions(every_window(cache(tmp_path / "val"), 4, list(META)))
    both = swapped_actions(cond)
    curvature = swapped_actions(cond, ("curvature",))
    torch.testing.assert_close(curvature.actions[..., 0], cond.actions[..., 0])  # speed stays the window's own
    torch.testing.assert_close(curvature.actions[..., 1], both.actions[..., 1])
    assert not torch.equal(curvature.actions[..., 1], cond.actions[..., 1])
    speed = swapped_actions(cond, ("speed",))
    torch.testing.assert_close(speed.actions[..., 0], both.actions[..., 0])
    torch.testing.assert_close(speed.actions[..., 1], cond.actions[..., 1])
    with pytest.raises(ValueError, match="speed.*curvature.*yaw"):
        swapped_actions(cond, ("yaw",))


def test_report_reads_speed_and_curvature_apart(tmp_path: Path) -> None:
    report = condition_gain_report(net(), every_window(cache(tmp_path / "val"), 4, list(META)), 0.5, context=2)
    assert set(report["component_discrimination"]) == {"speed", "curvature"}
    for row in report["component_discrimination"].values():
        assert row["low"] <= row["mean"] <= row["high"] and row["n"] == 6 and row["mean"] != 0


def test_component_discrimination_breaks_down_by_flow_time_and_step(tmp_path: Path) -> None:
    report = condition_gain_report(net(), every_window(cache(tmp_path / "val", steps=6), 5, list(META)), 0.5,
                                   context=2)
    for name in ("speed", "curvature"):
        by_tau = report["component_discrimination_by_tau"][name]
        by_step = report["component_discrimination_by_step"][name]
        assert list(by_tau) == ["0.25", "0.5", "0.75"] and list(by_step) == ["2", "3", "4"]
        overall = report["component_discrimination"][name]["mean"]
        # equal counts in every cell: the overall mean is the mean of either breakdown
        assert sum(e["mean"] for e in by_tau.values()) / 3 == pytest.approx(overall, rel=1e-5, abs=1e-9)
        assert sum(e["mean"] for e in by_step.values()) / 3 == pytest.approx(overall, rel=1e-5, abs=1e-9)


def test_component_discrimination_splits_open_loop_from_policy_windows(tmp_path: Path) -> None:
    report = condition_gain_report(net(), every_window(cache(tmp_path / "val"), 4, list(META)), 0.5, context=2)
    for name in ("speed", "curvature"):
        kinds = report["component_discrimination_by_clip"][name]
        assert kinds["open-loop clips"]["n"] == 2 and kinds["policy clips"]["n"] == 4
        overall = report["component_discrimination"][name]["mean"]
        pooled = (2 * kinds["open-loop clips"]["mean"] + 4 * kinds["policy clips"]["mean"]) / 6
        assert pooled == pytest.approx(overall, rel=1e-5, abs=1e-9)


def test_each_flow_time_column_is_that_flow_time_scored_alone(tmp_path: Path) -> None:
    """The per-τ breakdown against a direct computation at each τ with the noise the report draws for it (two draws
    per τ, in TAUS order, from seed 0): a breakdown whose columns were swapped or mislabelled fails here."""
    batch = every_window(cache(tmp_path / "val"), 4, list(META))
    model, x, cond = net(), batch["mean"] * 0.5, batch_conditions(batch)
    report = condition_gain_report(model, batch, 0.5, context=2)["component_discrimination_by_tau"]["curvature"]
    generator = torch.Generator().manual_seed(0)
    noises = [torch.randn(x.shape, generator=generator) for _ in range(2 * len(TAUS))]
    swapped = swapped_actions(cond, ("curvature",))
    for i, tau in enumerate(TAUS):
        times = torch.full((x.shape[0], 4), tau)
        times[:, :2] = 1.0
        step = times[:, None, :, None, None, None]
        gap = torch.zeros(x.shape[0])
        for noise in noises[2 * i: 2 * i + 2]:
            noisy, target = step * x + (1 - step) * noise, velocity_target(x, noise)
            with torch.no_grad():
                own, other = ((model(noisy, times, c) - target)[:, :, 2:].pow(2).mean(dim=(1, 2, 3, 4, 5))
                              for c in (cond, swapped))
            gap += (other - own) / 2
        assert report[str(tau)]["mean"] == pytest.approx(float(gap.mean()), rel=1e-4, abs=1e-9), f"τ = {tau}"


def test_the_flow_times_scored_can_be_chosen(tmp_path: Path) -> None:
    """taus: near pure noise (where a rollout lays out its frames) as well as TAUS; refused outside [0, 1)."""
    batch = every_window(cache(tmp_path / "val"), 4, list(META))
    report = condition_gain_report(net(), batch, 0.5, context=2, taus=(0.05, 0.1))
    assert report["taus"] == [0.05, 0.1]
    assert list(report["component_discrimination_by_tau"]["curvature"]) == ["0.05", "0.1"]
    default = condition_gain_report(net(), batch, 0.5, context=2)
    assert default["taus"] == list(TAUS)
    assert report["component_discrimination"]["curvature"] != default["component_discrimination"]["curvature"]
    with pytest.raises(ValueError, match=r"flow times to score: expected values in \[0, 1\)"):
        condition_gain_report(net(), batch, 0.5, context=2, taus=(1.0,))
