"""GAIA-1 video-decoder diffusion: cosine schedule (§4.3), v-param (eq. 2), DDIM / DPM-Solver++ (§5.2), eq. 4."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from gaia_app.diffusion.noise_schedule import CosineNoiseSchedule, eps_from_v, expand, v_from_x0, v_target, x0_from_v
from gaia_app.diffusion.samplers import (
    DDIMSampler,
    DPMSolverSampler,
    ImageVideoBlend,
    OneStepMeanSampler,
    trailing_timesteps,
)

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
SCHEDULE = CosineNoiseSchedule()


def oracle(x0: torch.Tensor, schedule: CosineNoiseSchedule = SCHEDULE):
    """Denoiser that knows the clean sample: the exact v for x0 at any x_t."""
    def denoise(x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        alpha, sigma = schedule.alpha_sigma(t)
        return v_from_x0(x_t, x0, alpha, sigma)
    return denoise


def gaussian(mu: float, s: float, schedule: CosineNoiseSchedule = SCHEDULE):
    """Optimal denoiser for data x0 ~ N(μ, s²) per element: E[x0 | x_t] = μ + α s² / (α² s² + σ²) · (x_t − α μ)."""
    def denoise(x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        alpha, sigma = schedule.alpha_sigma(t)
        a, sg = expand(alpha, x_t), expand(sigma, x_t)
        return v_from_x0(x_t, mu + a * s**2 / (a**2 * s**2 + sg**2) * (x_t - a * mu), alpha, sigma)
    return denoise


def standard_noise(shape: tuple[int, ...], seed: int = 0) -> torch.Tensor:
    """Float64 noise standardised to mean 0, std 1 exactly: a deterministic sampler is affine in x_T for
    Gaussian data, so its samples' mean and std are then the sampler's, free of Monte-Carlo error."""
    noise = torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return (noise - noise.mean()) / noise.std()


def test_cosine_schedule_shape() -> None:
    abar, betas = SCHEDULE.alphas_cumprod, SCHEDULE.betas
    assert abar.shape == (1000,) and abar.dtype == torch.float64 and SCHEDULE.timesteps == 1000
    assert (abar.diff() < 0).all() and (abar > 0).all() and (abar <= 1).all()
    assert abar[0] == pytest.approx(1.0, abs=1e-4) and abar[-1] < 1e-6
    assert (betas <= 0.999).all() and betas[-1] == pytest.approx(0.999)
    assert (CosineNoiseSchedule(100, max_beta=0.5).betas <= 0.5).all()
    alpha, sigma = SCHEDULE.alpha_sigma(torch.tensor([0, 500, 999]))
    assert alpha.dtype == sigma.dtype == torch.float32 and alpha.shape == (3,)
    torch.testing.assert_close(alpha**2 + sigma**2, torch.ones(3))
    assert sigma[0] == pytest.approx(0.0064, abs=1e-4)  # the offset s = 0.008 keeps σ_0 away from 0


def test_sample_timesteps_uniform_and_seeded() -> None:
    t = SCHEDULE.sample_timesteps(20_000, "cpu", torch.Generator().manual_seed(0))
    assert t.dtype == torch.long and t.shape == (20_000,) and t.min() >= 0 and t.max() <= 999
    assert t.float().mean().item() == pytest.approx(499.5, abs=10)
    assert torch.equal(t, SCHEDULE.sample_timesteps(20_000, "cpu", torch.Generator().manual_seed(0)))


def test_v_parameterisation_round_trips() -> None:
    g = torch.Generator().manual_seed(0)
    x0, eps = torch.randn(6, 3, 4, 8, 8, generator=g), torch.randn(6, 3, 4, 8, 8, generator=g)
    t = torch.randint(0, 1000, (6,), generator=g)
    alpha, sigma = SCHEDULE.alpha_sigma(t)
    x_t, v = SCHEDULE.add_noise(x0, eps, t), v_target(x0, eps, alpha, sigma)
    torch.testing.assert_close(x0_from_v(x_t, v, alpha, sigma), x0, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(eps_from_v(x_t, v, alpha, sigma), eps, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(v_from_x0(x_t, x0, alpha, sigma), v, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(v_from_x0(x_t, x0_from_v(x_t, v, alpha, sigma), alpha, sigma), v, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("shape", [(3, 3, 8, 8), (3, 1, 4, 3, 8, 8)], ids=["4d_image", "6d_video"])
def test_add_noise_broadcasts_per_sample(shape: tuple[int, ...]) -> None:
    x0, eps, t = torch.randn(shape), torch.randn(shape), torch.tensor([0, 400, 999])
    x_t = SCHEDULE.add_noise(x0, eps, t)
    alpha, sigma = SCHEDULE.alpha_sigma(t)
    assert x_t.shape == shape
    for i in range(3):
        torch.testing.assert_close(x_t[i], alpha[i] * x0[i] + sigma[i] * eps[i])
    assert expand(alpha, torch.zeros(3, 2, 2, 2, 2)).shape == (3, 1, 1, 1, 1)  # 5D


def test_add_noise_keeps_dtype() -> None:
    x0 = torch.randn(2, 3, 4, 4, dtype=torch.bfloat16)
    assert SCHEDULE.add_noise(x0, torch.randn_like(x0), torch.tensor([3, 7])).dtype == torch.bfloat16


def test_trailing_timesteps() -> None:
    assert trailing_timesteps(1000, 10) == [999, 899, 799, 699, 599, 499, 399, 299, 199, 99]
    assert trailing_timesteps(1000, 50)[:2] == [999, 979] and trailing_timesteps(1000, 50)[-1] == 19
    assert trailing_timesteps(10, 10) == list(range(9, -1, -1))
    with pytest.raises(ValueError):
        trailing_timesteps(10, 11)


SAMPLERS = {"ddim": lambda steps: DDIMSampler(SCHEDULE, steps),
            "dpm_solver": lambda steps: DPMSolverSampler(SCHEDULE, steps)}


@pytest.mark.parametrize("kind", SAMPLERS)
def test_oracle_recovers_x0_and_stays_on_the_forward_path(kind: str) -> None:
    """With the true x0 every update lands on x_s = α_s x0 + σ_s ε exactly: this checks each coefficient."""
    g = torch.Generator().manual_seed(1)
    x0, eps = torch.rand(2, 3, 2, 8, 8, generator=g) * 2 - 1, torch.randn(2, 3, 2, 8, 8, generator=g)
    start = SCHEDULE.add_noise(x0, eps, torch.full((2,), 999))
    seen: list[tuple[int, int]] = []

    def on_path(i: int, t: int, x_t: torch.Tensor, x0_pred: torch.Tensor) -> None:
        seen.append((i, t))
        torch.testing.assert_close(x_t, SCHEDULE.add_noise(x0, eps, torch.full((2,), t)), atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(x0_pred, x0, atol=1e-4, rtol=1e-4)

    out = SAMPLERS[kind](10)(oracle(x0), start, callback=on_path)
    torch.testing.assert_close(out, x0, atol=1e-4, rtol=1e-4)
    assert [i for i, _ in seen] == list(range(10)) and [t for _, t in seen] == trailing_timesteps(1000, 10)


@pytest.mark.parametrize("kind", SAMPLERS)
def test_oracle_from_pure_noise(kind: str) -> None:
    x0 = torch.rand(2, 1, 3, 3, 8, 8, generator=torch.Generator().manual_seed(2)) * 2 - 1
    torch.testing.assert_close(SAMPLERS[kind](10)(oracle(x0), torch.randn_like(x0)), x0, atol=1e-4, rtol=1e-4)


def test_ddim_eta0_is_deterministic() -> None:
    sampler, denoise = DDIMSampler(SCHEDULE, steps=10), gaussian(0.1, 0.3)
    noise = torch.randn(2, 3, 8, 8, generator=torch.Generator().manual_seed(0))
    first = sampler(denoise, noise, generator=torch.Generator().manual_seed(1))
    assert torch.equal(first, sampler(denoise, noise, generator=torch.Generator().manual_seed(2)))
    assert not torch.allclose(first, sampler(denoise, torch.randn_like(noise)))


def test_ddim_eta1_draws_from_the_generator() -> None:
    sampler, denoise = DDIMSampler(SCHEDULE, steps=10, eta=1.0), gaussian(0.1, 0.3)
    noise = torch.randn(2, 3, 8, 8, generator=torch.Generator().manual_seed(0))
    run = lambda seed: sampler(denoise, noise, generator=torch.Generator().manual_seed(seed))  # noqa: E731
    assert torch.equal(run(1), run(1)) and not torch.allclose(run(1), run(2))


# std(sample)/s after the sampler, for x0 ~ N(0.1, 0.5²) and no clipping (Gaussian data leaves [−1, 1]).
# Few steps shrink the spread (the last step jumps to x̂0 = E[x0 | x_t], a posterior mean): that is the
# first-order discretisation error, which vanishes with more steps and is smaller for the second-order solver.
MU, S = 0.1, 0.5


# Measured: DDIM-200 0.992, DDIM-50 0.969, DDIM-10 0.854, DPM-Solver-10 0.951, DPM-Solver-20 0.997.
@pytest.mark.parametrize("kind,steps,tolerance", [("ddim", 200, 0.015), ("ddim", 50, 0.05), ("ddim", 10, 0.2),
                                                  ("dpm_solver", 10, 0.07), ("dpm_solver", 20, 0.015)])
def test_gaussian_data_statistics(kind: str, steps: int, tolerance: float) -> None:
    sampler = SAMPLERS[kind](steps)
    sampler.clip_x0 = False
    out = sampler(gaussian(MU, S), standard_noise((1, 4096)))
    assert out.mean().item() == pytest.approx(MU, abs=1e-3)
    assert out.std().item() / S == pytest.approx(1.0, abs=tolerance)


def test_second_order_beats_first_order_at_equal_steps() -> None:
    noise = standard_noise((1, 1024))
    ddim, dpm = DDIMSampler(SCHEDULE, 10, clip_x0=False), DPMSolverSampler(SCHEDULE, 10, clip_x0=False)
    assert abs(dpm(gaussian(MU, S), noise).std() / S - 1) < 0.5 * abs(ddim(gaussian(MU, S), noise).std() / S - 1)


def test_ddim_eta1_step_has_the_ddpm_posterior_variance() -> None:
    """Over consecutive timesteps t → t − 1, η = 1 adds noise of variance β̃_t = (1 − ᾱ_{t−1}) / (1 − ᾱ_t) · β_t."""
    schedule = CosineNoiseSchedule(timesteps=10)
    x0, noise = torch.zeros(1, 50_000, dtype=torch.float64), standard_noise((1, 50_000))
    states: dict[int, torch.Tensor] = {}
    DDIMSampler(schedule, steps=10, eta=1.0)(oracle(x0, schedule), noise, torch.Generator().manual_seed(0),
                                            callback=lambda i, t, x, x0_pred: states.setdefault(t, x))
    abar, betas = schedule.alphas_cumprod, schedule.betas
    posterior = (1 - abar[7]) / (1 - abar[8]) * betas[8]
    # x0 = 0, so ε̂ = x_8 / σ_8 and the deterministic part of x_7 is sqrt(σ_7² − β̃) ε̂
    fresh = states[7] - ((1 - abar[7] - posterior).sqrt() / (1 - abar[8]).sqrt()) * states[8]
    assert fresh.var().item() == pytest.approx(posterior.item(), rel=0.03)


def test_ddim_eta1_gaussian_statistics() -> None:
    """The ancestral (η = 1) sampler reaches the data distribution too, given enough steps."""
    sampler = DDIMSampler(SCHEDULE, steps=200, eta=1.0, clip_x0=False)
    out = sampler(gaussian(MU, S), standard_noise((1, 20_000)), generator=torch.Generator().manual_seed(3))
    assert out.mean().item() == pytest.approx(MU, abs=0.015)  # Monte-Carlo error s / sqrt(n) ≈ 0.0035
    assert out.std().item() / S == pytest.approx(1.0, abs=0.03)


def test_clip_x0_bounds_predictions() -> None:
    def wild(x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return v_from_x0(x_t, torch.full_like(x_t, 3.0), *SCHEDULE.alpha_sigma(t))

    x0s: list[torch.Tensor] = []
    out = DDIMSampler(SCHEDULE, 5)(wild, torch.randn(2, 4), callback=lambda i, t, x, x0: x0s.append(x0))
    assert all(x0.abs().max() <= 1.0 for x0 in x0s) and torch.allclose(out, torch.ones(2, 4))
    assert torch.allclose(DDIMSampler(SCHEDULE, 5, clip_x0=False)(wild, torch.randn(2, 4)), torch.full((2, 4), 3.0))


def test_callback_sees_decreasing_timesteps_and_progress_bar_runs() -> None:
    calls: list[int] = []
    sampler = DPMSolverSampler(SCHEDULE, steps=7, progress=True)
    sampler(gaussian(0.0, 0.5), torch.randn(1, 3, 4, 4), callback=lambda i, t, x, x0: calls.append(t))
    assert len(calls) == 7 and calls[0] == 999 and all(a > b for a, b in zip(calls, calls[1:]))


def test_blend_probability_zero_calls_video_only() -> None:
    counts = {"video": 0, "image": 0}

    def net(name: str, value: float):
        def denoise(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            counts[name] += 1
            return torch.full_like(x, value)
        return denoise

    blended = ImageVideoBlend(probability=0.0).denoiser(net("video", 1.0), net("image", 3.0))
    out = DDIMSampler(SCHEDULE, 10)(blended, torch.randn(2, 3))
    assert counts == {"video": 10, "image": 0} and blended.calls == 10 and blended.blended == 0
    assert out.shape == (2, 3)


def test_blend_probability_one_is_the_eq4_average() -> None:
    x, t = torch.randn(2, 3, 4), torch.tensor([5, 9])
    video, image = (lambda x, t: x * 2.0), (lambda x, t: x - 1.0)
    blended = ImageVideoBlend(probability=1.0, weight=0.3).denoiser(video, image)
    torch.testing.assert_close(blended(x, t), 0.3 * (x - 1.0) + 0.7 * (x * 2.0))
    assert blended.blended == blended.calls == 1


def test_blend_rate_matches_probability_and_is_seeded() -> None:
    video, image = (lambda x, t: x), (lambda x, t: -x)
    blend = ImageVideoBlend(probability=0.25, weight=0.5)
    x, t = torch.ones(1, 2), torch.zeros(1, dtype=torch.long)
    runs = []
    for _ in range(2):
        blended = blend.denoiser(video, image, torch.Generator().manual_seed(0))
        runs.append([blended(x, t)[0, 0].item() for _ in range(2000)])
        assert blended.calls == 2000 and blended.blended / 2000 == pytest.approx(0.25, abs=0.04)
    assert runs[0] == runs[1]  # blended steps return 0.5·(−x) + 0.5·x = 0


def test_blend_of_v_is_blend_of_eps() -> None:
    """Eq. 4 is written for ε; blending v at fixed x_t gives the same ε."""
    g = torch.Generator().manual_seed(4)
    x_t, v_img, v_vid = (torch.randn(3, 2, 4, 4, generator=g) for _ in range(3))
    t = torch.tensor([10, 500, 990])
    alpha, sigma = SCHEDULE.alpha_sigma(t)
    blended = ImageVideoBlend(1.0, 0.5).denoiser(lambda x, t: v_vid, lambda x, t: v_img)(x_t, t)
    expected = 0.5 * eps_from_v(x_t, v_img, alpha, sigma) + 0.5 * eps_from_v(x_t, v_vid, alpha, sigma)
    torch.testing.assert_close(eps_from_v(x_t, blended, alpha, sigma), expected)


@pytest.mark.parametrize("name,kind,steps", [("ddim", DDIMSampler, 50), ("dpm_solver", DPMSolverSampler, 20)])
def test_sampler_configs_instantiate(name: str, kind: type, steps: int) -> None:
    """conf/sampler/*.yaml are partials: the schedule is bound in code (the group is not in test_configs' list)."""
    sampler = instantiate(OmegaConf.load(CONF_DIR / "sampler" / f"{name}.yaml"))(schedule=SCHEDULE)
    assert isinstance(sampler, kind) and sampler.steps == steps and sampler.clip_x0


def test_one_step_mean_averages_the_noise_out_of_x0() -> None:
    """A denoiser whose x̂0 at the noisiest step is the mean plus an error carried by its noise input: one draw keeps
    the error, 64 draws shrink it ≈ 8× (1/√draws), and an exact denoiser returns the mean at any draws."""
    mean = torch.linspace(-0.5, 0.5, 64).reshape(1, 64)
    t = torch.tensor([SCHEDULE.timesteps - 1])
    alpha, sigma = SCHEDULE.alpha_sigma(t)

    def noisy(x, step):  # x̂0 = mean + 0.3·x_T, returned as v
        return v_from_x0(x, mean + 0.3 * x, alpha, sigma)

    def error(draws: int) -> float:
        noise = torch.randn(1, 64, generator=torch.Generator().manual_seed(1))
        out = OneStepMeanSampler(SCHEDULE, draws=draws)(noisy, noise, torch.Generator().manual_seed(2))
        return float((out - mean).pow(2).mean().sqrt())

    assert 0.2 < error(1) < 0.4 and error(64) < error(1) / 5
    exact = OneStepMeanSampler(SCHEDULE, draws=3)(lambda x, step: v_from_x0(x, mean, alpha, sigma), torch.randn(1, 64))
    torch.testing.assert_close(exact, mean, atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match="draws ≥ 1"):
        OneStepMeanSampler(SCHEDULE, draws=0)


def test_antithetic_mean_cancels_the_error_linear_in_the_noise() -> None:
    """Pairs (x_T, −x_T): an x̂0 error linear in the noise cancels exactly within each pair, where independent draws
    only shrink it as 1/√draws; the first draw is still the noise passed in, and pairs need an even count."""
    mean = torch.linspace(-0.5, 0.5, 64).reshape(1, 64)
    t = torch.tensor([SCHEDULE.timesteps - 1])
    alpha, sigma = SCHEDULE.alpha_sigma(t)
    seen = []

    def noisy(x, step):  # x̂0 = mean + 0.3·x_T
        return v_from_x0(x, mean + 0.3 * x, alpha, sigma)

    def error(antithetic: bool) -> float:
        noise = torch.randn(1, 64, generator=torch.Generator().manual_seed(1))
        sampler = OneStepMeanSampler(SCHEDULE, draws=4, antithetic=antithetic, clip_x0=False)
        out = sampler(noisy, noise, torch.Generator().manual_seed(2), callback=lambda i, t, x, m: seen.append(x))
        assert torch.equal(seen[-4], noise)
        return float((out - mean).pow(2).mean().sqrt())

    assert error(antithetic=True) < 1e-3 < error(antithetic=False)
    assert torch.equal(seen[1], -seen[0]) and not torch.equal(seen[2], -seen[1])
    with pytest.raises(ValueError, match="pairs"):
        OneStepMeanSampler(SCHEDULE, draws=3, antithetic=True)
