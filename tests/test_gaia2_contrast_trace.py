"""The contrast trace (protocols/gaia2_contrast_trace.py): the sampler's estimate of the clean future, projected on the
real re-simulated latent contrast."""

from __future__ import annotations

import pytest
import torch
from hydra import compose, initialize_config_dir

from gaia_app.diffusion.flow_matching import FlowSampler
from gaia_app.protocols.gaia2_contrast_trace import (
    TracingSampler,
    block_coordinates,
    check_settings,
    coarse_energy,
    nearest_steps,
    projections,
    strong_cells,
    strong_energy,
    uniform_share,
)
from tests.test_configs import CONF_DIR
from tests.test_eval_latent_world_model import BENCHMARK_SCRIPT, load_benchmark

pytestmark = pytest.mark.usefixtures("one_thread")


def test_projections_read_all_none_and_anything_else_of_the_real_contrast() -> None:
    real = torch.randn(3, 2, 4, 6, 8, dtype=torch.float64)
    other = torch.randn_like(real)
    other -= (other * real).sum() / real.square().sum() * real  # orthogonal to the real contrast
    mixed = 0.5 * real + other
    values = projections(torch.stack([real, torch.zeros_like(real), mixed, other]), real)
    torch.testing.assert_close(values["share"], torch.tensor([1.0, 0.0, 0.5, 0.0], dtype=torch.float64))
    expected_cosine = 0.5 * real.norm() / mixed.norm()
    torch.testing.assert_close(values["cosine"][[0, 2, 3]], torch.stack([torch.tensor(1.0, dtype=torch.float64),
                                                                          expected_cosine, torch.tensor(0.0).double()]))
    torch.testing.assert_close(values["norm"][[0, 3]],
                               torch.stack([torch.tensor(1.0).double(), other.norm() / real.norm()]))
    with pytest.raises(ValueError, match="identical latents: no contrast to trace"):
        projections(real[None], torch.zeros_like(real))


def test_the_uniform_share_is_the_energy_of_a_change_common_to_every_token() -> None:
    """A per-channel offset, the same at every position, is all uniform; a pattern that averages to zero over the grid
    (a displacement of a scene's texture) is none; a sum of equal energies is half. With 2 × 2 patches, a change the
    same for every token repeats every 2 cells: uniform at patch 2, not at patch 1."""
    offset = torch.randn(1, 3, 2, 4, 1, 1).expand(1, 3, 2, 4, 6, 8)
    pattern = torch.randn(1, 3, 2, 4, 6, 8)
    pattern -= pattern.mean(dim=(-2, -1), keepdim=True)
    pattern *= offset.norm() / pattern.norm()
    torch.testing.assert_close(uniform_share(torch.cat([offset, pattern, offset + pattern])),
                               torch.tensor([1.0, 0.0, 0.5], dtype=torch.float64), atol=1e-5, rtol=0)
    per_token = torch.randn(1, 3, 2, 4, 2, 2).repeat(1, 1, 1, 1, 3, 4)  # (…, 6, 8): one 2 × 2 patch, tiled
    assert uniform_share(per_token, 2)[0] == pytest.approx(1.0) and uniform_share(per_token, 1)[0] < 0.9
    with pytest.raises(ValueError, match="not a whole number of 4×4 patches"):
        uniform_share(per_token, 4)


@pytest.mark.parametrize("grid", [(8, 12), (8, 14)])  # 8 × 14 at 4 × 4: the shipped tokenizer's grid, edge blocks
def test_a_blurred_but_right_future_scores_low_on_share_and_fully_on_the_coarse_share(grid) -> None:
    """The real contrast's block means spread back over each block (a future that moves the scene right but draws it
    blurred): its `share` is the real energy the projection keeps, its `share_pool4` is 1, blocks at the edges
    included; a cell-level checkerboard keeps no energy after pooling by 2."""
    h, w = grid
    real = torch.randn(3, 2, 4, h, w, dtype=torch.float64)
    sizes = [torch.tensor([min(4, n - i) for i in range(0, n, 4)]) for n in (h, w)]
    means = torch.nn.functional.avg_pool2d(real.reshape(-1, 1, h, w), 4, ceil_mode=True, count_include_pad=False)
    blurred = means.repeat_interleave(sizes[0], dim=-2).repeat_interleave(sizes[1], dim=-1).reshape(real.shape)
    values = projections(blurred[None], real)
    assert values["share"][0] == pytest.approx(coarse_energy(real, 4), rel=1e-9) and values["share"][0] < 0.5
    assert values["share_pool4"][0] == pytest.approx(1.0, rel=1e-9) and coarse_energy(blurred, 4) == pytest.approx(1.0)
    assert block_coordinates(real, 4).shape[-2:] == (2, 3 if w == 12 else 4)
    checkerboard = (torch.arange(h)[:, None] + torch.arange(w)).remainder(2).double() * 2 - 1
    assert coarse_energy(checkerboard.expand(3, 2, 4, h, w), 2) == pytest.approx(0.0, abs=1e-12)


def test_the_tracing_sampler_keeps_an_exact_estimate_and_samples_as_the_plain_sampler() -> None:
    """An oracle velocity toward a fixed clean target: at every solver step the estimate x + (1 − τ)·v is the target
    (of the steps after the clean ones); tracing changes nothing in what is sampled."""
    target = torch.randn(2, 3, 4, 2, 5, 5)  # (b, v, t, C, h, w)
    noise = torch.randn_like(target)

    def oracle(x: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
        return (target - x) / (1 - tau).clamp_min(1e-6).view(-1, 1, 1, 1, 1, 1)

    plain = FlowSampler(steps=6)
    tracer = TracingSampler(plain, clean_steps=1)
    out = tracer(oracle, noise)
    assert len(tracer.estimates) == 6
    for estimate in tracer.estimates:
        torch.testing.assert_close(estimate, target[:, :, 1:])
    torch.testing.assert_close(out, plain(oracle, noise))
    with pytest.raises(ValueError, match="use model.sampler.solver=euler"):
        TracingSampler(FlowSampler(steps=6, solver="heun"), clean_steps=1)


@pytest.mark.parametrize(("override", "message"), [
    ("model.evaluate.noise_draws=2", "set model.evaluate.noise_draws=1"),
    ("model.sampler.solver=heun", "model.sampler.solver='heun': the contrast trace reads one velocity"),
    ("model.evaluate.action_agents=some", "model.evaluate.action_agents='some'")])
def test_settings_the_trace_cannot_read_are_refused_by_name(override, message) -> None:
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("generate", overrides=["model=gaia2", "data=synthetic_rig", override])
    with pytest.raises(ValueError, match=message):
        check_settings(cfg)


def test_the_table_columns_are_the_solver_steps_nearest_a_few_flow_times() -> None:
    assert nearest_steps([0.0, 0.02, 0.3, 0.6, 0.95]) == [0, 1, 2, 3, 4]
    assert nearest_steps([0.0, 0.5]) == [0, 1]


@BENCHMARK_SCRIPT
def test_the_trace_reads_the_guided_velocity_and_its_samples_are_the_rollouts(tmp_path) -> None:
    """benchmarks/gaia2_contrast_trace.py on the shipped weights: at the first solver step both futures of a pair
    share their noise, so guidance ×4 multiplies the conditional contrast by exactly 4; the trace's last entry is the
    finished samples' contrast (the last solver step's estimate, Euler), and a traced rollout samples exactly what the
    untraced pipeline samples from the same noise; the files carry the tables."""
    from gaia_app.protocols.gaia2_contrast_trace import traced_rollout

    module = load_benchmark("gaia2_contrast_trace")
    tiny = ["model.evaluate.contexts=2", "model.sampler.steps=3", "model.guidance.conditions=[action]",
            "model.steps=3"]
    result = module.main(["--weights", "gaia2", "--scales", "1", "4", "--out", str(tmp_path), "--", *tiny])
    plain, guided = (result["traces"][f"gaia2, guidance ×{s}"] for s in (1, 4))
    assert (plain["guidance_scale"], guided["guidance_scale"]) == (1.0, 4.0)
    for metric in ("speed_contrast", "curvature_contrast"):
        for one, four in zip(plain["per_scene"][metric]["share"], guided["per_scene"][metric]["share"]):
            assert len(one) == 3 + 1 and four[0] == pytest.approx(4 * one[0], rel=1e-4, abs=1e-6)
            assert one[-1] == pytest.approx(one[-2], rel=1e-4, abs=1e-6)
        assert plain["per_scene"][metric]["cosine"][0][0] == pytest.approx(guided["per_scene"][metric]["cosine"][0][0],
                                                                           rel=1e-4)
    text = (tmp_path / "contrast_trace.md").read_text()
    assert text.count("| speed contrast (accelerate/straight − brake/straight) | share |") == 2

    cfg = module.compose_config("gaia2", tiny)
    pipeline = module.load_gaia2(module.with_weights(cfg, "gaia2", 4.0))
    clip = module.cut_steps(pipeline.encode(module.rig_samples(cfg, 5, 1, 12)[0].clip), 3)
    context, _ = pipeline.window(clip, 0, 2)
    _, cond = pipeline.window(clip, 0, 3)
    traced = traced_rollout(pipeline, context, cond, 1, seed=7)[-1]
    untraced = pipeline.world.rollout(context, [cond], 1, torch.Generator().manual_seed(7))[0, :, 2:].cpu()
    torch.testing.assert_close(traced, untraced)


def test_the_strong_and_weak_shares_split_the_real_contrast_by_where_it_is_large() -> None:
    """A real contrast with a quarter of its cells large (the ground near the ego) and the rest small: a future that
    draws only the large part carries all of the strong cells and none of the weak ones, and its overall share is the
    strong cells' energy; the strong cells are picked per cell over channels."""
    real = torch.randn(2, 2, 4, 4, 8, dtype=torch.float64) * 0.01
    real[..., 3, :] = torch.randn(2, 2, 4, 8, dtype=torch.float64)  # the bottom row of 4: a quarter of the cells
    only_strong = torch.zeros_like(real)
    only_strong[..., 3, :] = real[..., 3, :]
    values = projections(torch.stack([real, only_strong, real - only_strong]), real)
    torch.testing.assert_close(values["share_strong"], torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(values["share_weak"], torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64))
    assert strong_cells(real).shape == (2, 2, 1, 4, 8) and strong_cells(real)[..., 3, :].all()
    assert not strong_cells(real)[..., :3, :].any()
    assert values["share"][1] == pytest.approx(strong_energy(real), rel=1e-9) and strong_energy(real) > 0.99


def test_the_split_recomposes_the_share_and_picks_a_quarter_of_each_steps_cells_even_with_ties() -> None:
    """share = real_strong·share_strong + (1 − real_strong)·share_weak exactly; the strong cells are a quarter of every
    generated step's cells, so a step whose contrast is 100× smaller still has its own; all-zero ties pick a quarter."""
    real = torch.randn(3, 2, 4, 4, 8, dtype=torch.float64)
    real[:, 0] *= 0.01  # the first step's contrast far smaller than the second's (a speed command's t²)
    trace = torch.randn(5, *real.shape, dtype=torch.float64)
    values = projections(trace, real)
    fraction = strong_energy(real)
    torch.testing.assert_close(values["share"], fraction * values["share_strong"]
                               + (1 - fraction) * values["share_weak"])
    strong = strong_cells(real)
    assert strong[:, 0].sum() == strong[:, 1].sum() == 3 * 4 * 8 // 4
    ties = strong_cells(torch.zeros(1, 2, 4, 4, 8, dtype=torch.float64))
    assert ties.sum() == 2 * 4 * 8 // 4
