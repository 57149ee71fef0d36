"""The contrast trace (protocols/gaia2_contrast_trace.py): the sampler's estimate of the clean future, projected on the
real re-simulated latent contrast."""

from __future__ import annotations

import pytest
import torch

from gaia_app.diffusion.flow_matching import FlowSampler
from gaia_app.protocols.gaia2_contrast_trace import (
    TracingSampler,
    coarse_energy,
    nearest_steps,
    pooled,
    projections,
    uniform_share,
)
from tests.test_eval_latent_world_model import BENCHMARK_SCRIPT, load_benchmark

pytestmark = pytest.mark.usefixtures("one_thread")


def test_projections_read_all_none_and_anything_else_of_the_real_contrast() -> None:
    real = torch.randn(3, 2, 4, 5, 6)
    other = torch.randn_like(real)
    other -= (other * real).sum() / real.square().sum() * real  # orthogonal to the real contrast
    values = projections(torch.stack([real, torch.zeros_like(real), 0.5 * real + other, other]), real)
    torch.testing.assert_close(values["share"], torch.tensor([1.0, 0.0, 0.5, 0.0], dtype=torch.float64))
    assert values["cosine"][0] == pytest.approx(1.0) and values["cosine"][3] == pytest.approx(0.0, abs=1e-5)
    assert values["norm"][0] == pytest.approx(1.0) and values["norm"][3] > 0.5  # a contrast elsewhere still shows
    with pytest.raises(ValueError, match="identical latents: no contrast to trace"):
        projections(real[None], torch.zeros_like(real))


def test_the_uniform_share_is_the_energy_of_the_change_common_to_every_grid_position() -> None:
    """A per-channel offset, the same at every position (what an AdaLN shift writes), is all uniform; a pattern that
    averages to zero over the grid (a displacement of a scene's texture) is none; a sum of equal energies is half."""
    offset = torch.randn(1, 3, 2, 4, 1, 1).expand(1, 3, 2, 4, 6, 8)
    pattern = torch.randn(1, 3, 2, 4, 6, 8)
    pattern -= pattern.mean(dim=(-2, -1), keepdim=True)
    pattern *= offset.norm() / pattern.norm()
    torch.testing.assert_close(uniform_share(torch.cat([offset, pattern, offset + pattern])),
                               torch.tensor([1.0, 0.0, 0.5], dtype=torch.float64), atol=1e-5, rtol=0)


def test_a_blurred_but_right_future_scores_low_on_share_and_fully_on_the_coarse_share() -> None:
    """The real contrast's block means spread back over each block (a future that moves the scene right but draws it
    blurred): `share` is the real energy left after pooling, `share_pool4` is 1; a cell-level checkerboard has no
    energy left after pooling by 2."""
    real = torch.randn(3, 2, 4, 8, 12)
    blurred = pooled(real, 4).repeat_interleave(4, dim=-2).repeat_interleave(4, dim=-1)
    values = projections(blurred[None], real)
    assert values["share"][0] == pytest.approx(coarse_energy(real, 4), rel=1e-6) and values["share"][0] < 0.5
    assert values["share_pool4"][0] == pytest.approx(1.0, rel=1e-6) and coarse_energy(blurred, 4) == pytest.approx(1.0)
    checkerboard = (torch.arange(8)[:, None] + torch.arange(12)).remainder(2).double() * 2 - 1
    assert coarse_energy(checkerboard.expand(3, 2, 4, 8, 12), 2) == pytest.approx(0.0, abs=1e-12)


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


def test_the_table_columns_are_the_solver_steps_nearest_a_few_flow_times() -> None:
    assert nearest_steps([0.0, 0.02, 0.3, 0.6, 0.95]) == [0, 1, 2, 3, 4]
    assert nearest_steps([0.0, 0.5]) == [0, 1]


@BENCHMARK_SCRIPT
def test_the_trace_reads_the_guided_velocity_and_its_samples_are_the_rollouts(tmp_path) -> None:
    """benchmarks/gaia2_contrast_trace.py on the shipped weights: at the first solver step both futures of a pair
    share their noise, so guidance ×4 multiplies the conditional contrast by exactly 4; the trace's last entry is the
    finished samples' contrast, which the last solver step's estimate equals (Euler); the files carry the tables."""
    module = load_benchmark("gaia2_contrast_trace")
    tiny = ["model.evaluate.contexts=2", "model.sampler.steps=3", "model.guidance.conditions=[action]",
            "model.steps=3"]
    result = module.main(["--weights", "gaia2", "--scales", "1", "4", "--out", str(tmp_path), "--", *tiny])
    plain, guided = (result["traces"][f"gaia2, guidance ×{s}"] for s in (1, 4))
    for metric in ("speed_contrast", "curvature_contrast"):
        for one, four in zip(plain["per_scene"][metric]["share"], guided["per_scene"][metric]["share"]):
            assert len(one) == 3 + 1 and four[0] == pytest.approx(4 * one[0], rel=1e-4, abs=1e-6)
            assert one[-1] == pytest.approx(one[-2], rel=1e-4, abs=1e-6)
        assert plain["per_scene"][metric]["cosine"][0][0] == pytest.approx(guided["per_scene"][metric]["cosine"][0][0],
                                                                           rel=1e-4)
    text = (tmp_path / "contrast_trace.md").read_text()
    assert text.count("| speed contrast (accelerate/straight − brake/straight) | share |") == 2
