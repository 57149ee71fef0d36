"""Flow matching (GAIA-2 report, world model): path and target arithmetic, τ schedules, Euler/Heun steps, and a
sampler that recovers a known 2-D Gaussian mixture from its exact velocity field."""

from __future__ import annotations

import pytest
import torch

from gaia_app.diffusion.flow_matching import (
    FlowSampler,
    linear_quadratic_taus,
    noisy_sample,
    sample_tau,
    velocity_target,
)


def test_path_ends_and_target_is_its_derivative() -> None:
    g = torch.Generator().manual_seed(0)
    x, noise = torch.randn(3, 4, 5, generator=g), torch.randn(3, 4, 5, generator=g)
    assert torch.equal(noisy_sample(x, noise, torch.zeros(3)), noise)
    assert torch.equal(noisy_sample(x, noise, torch.ones(3)), x)
    tau, h = torch.tensor([0.2, 0.5, 0.9]), 1e-3
    slope = (noisy_sample(x, noise, tau + h) - noisy_sample(x, noise, tau)) / h
    torch.testing.assert_close(slope, velocity_target(x, noise), atol=1e-3, rtol=1e-3)
    torch.testing.assert_close(noisy_sample(x, noise, tau)[1], 0.5 * x[1] + 0.5 * noise[1])


def test_tau_sampling_stays_inside_the_unit_interval() -> None:
    g = torch.Generator().manual_seed(0)
    for distribution in ("uniform", "logit_normal"):
        tau = sample_tau(10_000, distribution, generator=g)
        assert tau.min() > 0 and tau.max() < 1
    assert sample_tau(10_000, "logit_normal", generator=g).median() == pytest.approx(0.5, abs=0.02)
    with pytest.raises(ValueError, match="'uniform' or 'logit_normal'"):
        sample_tau(3, "beta")


def test_linear_quadratic_schedule() -> None:
    taus = linear_quadratic_taus(50, threshold=0.025)
    steps = taus[1:] - taus[:-1]
    assert taus.shape == (51,) and taus[0] == 0 and taus[-1] == 1
    torch.testing.assert_close(steps[:25], torch.full((25,), 0.001))  # 25 even steps up to τ = 0.025
    assert taus[25] == pytest.approx(0.025)
    assert bool((steps[25:] >= steps[24:-1] - 1e-7).all())  # then ever larger steps
    with pytest.raises(ValueError, match="too steep"):
        linear_quadratic_taus(10, threshold=0.6)


def test_euler_step_arithmetic() -> None:
    """A constant velocity moves noise by exactly that velocity; v = x compounds (1 + dτ) per step."""
    noise = torch.randn(2, 3)
    sampler = FlowSampler(steps=50)
    torch.testing.assert_close(sampler(lambda x, t: torch.full_like(x, 0.7), noise), noise + 0.7)
    growth = torch.prod(1 + (sampler.taus()[1:] - sampler.taus()[:-1]).double()).float()
    torch.testing.assert_close(sampler(lambda x, t: x, noise), noise * growth)
    calls = []
    sampler(lambda x, t: calls.append(t) or torch.zeros_like(x), noise)
    assert len(calls) == sampler.evaluations() == 50 and calls[0].shape == (2,)


def test_heun_is_exact_for_velocities_linear_in_tau_but_its_euler_last_step() -> None:
    """v = 1 + 2τ: the trapezoid integrates each step exactly; Heun's last step is Euler (as in EDM)."""
    sampler = FlowSampler(steps=10, schedule="uniform", solver="heun")
    out = sampler(lambda x, t: (1 + 2 * t)[:, None].expand_as(x), torch.zeros(1, 1))
    exact_to_09 = 0.9 + 0.81  # ∫0^0.9 (1 + 2τ) dτ
    assert float(out) == pytest.approx(exact_to_09 + 0.1 * (1 + 2 * 0.9))
    assert sampler.evaluations() == 19


def test_partial_start_continues_from_a_noised_sample() -> None:
    sampler = FlowSampler(steps=10, schedule="uniform")
    out = sampler(lambda x, t: torch.ones_like(x), torch.zeros(1, 2), start=6)
    torch.testing.assert_close(out, torch.full((1, 2), 0.4))


MEANS = torch.tensor([[-2.0, 0.0], [2.0, 1.0], [0.0, -2.5]])
COVS = torch.stack([torch.tensor([[0.3, 0.1], [0.1, 0.2]]), torch.tensor([[0.2, 0.0], [0.0, 0.5]]),
                    0.15 * torch.eye(2)])
WEIGHTS = torch.tensor([0.5, 0.3, 0.2])


def mixture_velocity(x: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
    """The exact marginal velocity E[x₁ − ε | x_τ] of the straight path when x₁ follows the mixture:
    per component, x_τ ~ N(τμ, τ²Σ + (1 − τ)²I), and E[x₁ − ε | x_τ] = μ + (τΣ − (1 − τ)I) S⁻¹ (x_τ − τμ)."""
    t = tau[:, None, None, None]  # (b, 1, 1, 1) against components k and 2×2 matrices
    eye = torch.eye(2)
    cov = t**2 * COVS[None] + (1 - t) ** 2 * eye  # (b, k, 2, 2)
    diff = x[:, None, :] - tau[:, None, None] * MEANS[None]  # (b, k, 2)
    solved = torch.linalg.solve(cov, diff.unsqueeze(-1)).squeeze(-1)
    logp = -0.5 * (diff * solved).sum(-1) - 0.5 * torch.logdet(cov) + WEIGHTS.log()[None]
    post = torch.softmax(logp, dim=1)  # (b, k)
    gain = t * COVS[None] - (1 - t) * eye
    per_component = MEANS[None] + (gain @ solved.unsqueeze(-1)).squeeze(-1)
    return (post[..., None] * per_component).sum(1)


@pytest.mark.parametrize("solver, cov_rtol", [("euler", 0.08), ("heun", 0.02)])
def test_sampler_recovers_a_known_gaussian_mixture(solver: str, cov_rtol: float) -> None:
    """50 linear-quadratic steps: Euler (first order) shrinks the covariance by ≈ 6 %, Heun is within 1 %."""
    noise = torch.randn(20_000, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64).float()
    samples = FlowSampler(steps=50, solver=solver)(mixture_velocity, noise)
    mean = (WEIGHTS[:, None] * MEANS).sum(0)
    second = (WEIGHTS[:, None, None] * (COVS + MEANS[:, :, None] * MEANS[:, None, :])).sum(0)
    cov = second - mean[:, None] * mean[None, :]
    torch.testing.assert_close(samples.mean(0), mean, atol=0.05, rtol=0)
    torch.testing.assert_close(torch.cov(samples.T), cov, atol=0.02, rtol=cov_rtol)
    nearest = torch.cdist(samples, MEANS).argmin(1)
    shares = torch.bincount(nearest, minlength=3).float() / len(samples)
    torch.testing.assert_close(shares, WEIGHTS, atol=0.03, rtol=0)
