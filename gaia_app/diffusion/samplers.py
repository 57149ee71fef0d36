"""Samplers for the GAIA-1 video decoder: DDIM, DPM-Solver++(2M), and the image/video blend of eq. 4 (GAIA-1 §5.2).

Legend:
    b batch, `...` any trailing dims of a sample (video `v t c h w`, an image `c h w`, …), T the
    schedule's timesteps, N the sampler's steps (network evaluations).

Every sampler takes a `Denoiser`: (x_t (b, ...), t (b,) int64) → v prediction (b, ...), the
network with its conditioning (tokens, masks, context frames) already bound. Samplers keep no
state between calls, so validation and generation share one object.

Timesteps are evenly spaced, "trailing" (Lin et al. 2024, "Common diffusion noise schedules and
sample steps are flawed"): t_i = round(T − i·T/N) − 1, i = 0 … N − 1, e.g. 999, 979, …, 19 for
T = 1000, N = 50. It always starts at t = T − 1, the noisiest step, where x_T = pure noise is a
faithful start; the last step jumps from t_{N−1} to the clean sample (ᾱ = 1).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from tqdm.auto import tqdm

from gaia_app.diffusion.noise_schedule import CosineNoiseSchedule

Denoiser = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
Callback = Callable[[int, int, torch.Tensor, torch.Tensor], None]


def trailing_timesteps(timesteps: int, steps: int) -> list[int]:
    """N evenly spaced timesteps, decreasing from T − 1: round(T − i·T/N) − 1, i = 0 … N − 1."""
    if not 1 <= steps <= timesteps:
        raise ValueError(f"sampler steps must lie in [1, {timesteps}], got {steps}")
    return [round(timesteps - i * timesteps / steps) - 1 for i in range(steps)]


def alpha_sigma_of(schedule: CosineNoiseSchedule, t: int | None) -> tuple[float, float]:
    """Python-float α_t, σ_t from the float64 table; t = None is the clean end (α = 1, σ = 0)."""
    if t is None:
        return 1.0, 0.0
    alpha_bar = schedule.alphas_cumprod[t].item()
    return math.sqrt(alpha_bar), math.sqrt(1.0 - alpha_bar)


def predict_x0(denoise: Denoiser, x: torch.Tensor, t: int, alpha: float, sigma: float, clip: bool) -> torch.Tensor:
    """One network evaluation at timestep t: x_t (b, ...) → x0 = α x_t − σ v, (b, ...), clipped to [−1, 1] if asked."""
    v = denoise(x, torch.full((x.shape[0],), t, dtype=torch.long, device=x.device))
    x0 = alpha * x - sigma * v
    # pixels live in [−1, 1]; clipping stops an overshooting x0 estimate compounding over steps
    return x0.clamp(-1.0, 1.0) if clip else x0


def standard_normal(like: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """ε ~ N(0, I) shaped like `like`, drawn where the generator lives (a CPU generator seeds CUDA runs too)."""
    where = generator.device if generator is not None else like.device
    return torch.randn(like.shape, generator=generator, device=where, dtype=like.dtype).to(like.device)


class DDIMSampler:
    """DDIM (Song et al. 2021, GAIA-1 §5.2 ref. [48]: "DDIM sampler with 50 diffusion steps").

    Update from t to the next timestep s (ᾱ_s = 1 after the last step), with x̂0 and
    ε̂ = (x_t − α_t x̂0) / σ_t from the network:
        x_s = α_s x̂0 + sqrt(σ_s² − c²) ε̂ + c z,   c = η · sqrt((1 − ᾱ_s)/(1 − ᾱ_t)) · sqrt(1 − ᾱ_t/ᾱ_s)
    η = 0 is the deterministic probability-flow sampler; η = 1 matches the DDPM ancestral variance.
    ε̂ is recomputed from the clipped x̂0, so a clipped step stays consistent with x_t.

    Args:
        schedule: the noise schedule the denoiser was trained with.
        steps: network evaluations N (trailing spacing, see the module docstring).
        eta: η ≥ 0, the share of fresh noise per step.
        clip_x0: clip x̂0 to [−1, 1] (pixel data).
        progress: tqdm bar over the steps.
    """

    def __init__(self, schedule: CosineNoiseSchedule, steps: int = 50, eta: float = 0.0, clip_x0: bool = True,
                 progress: bool = False):
        if eta < 0:
            raise ValueError(f"DDIMSampler: eta ≥ 0, got {eta}")
        self.schedule, self.eta, self.clip_x0, self.progress = schedule, eta, clip_x0, progress
        self.timesteps = trailing_timesteps(schedule.timesteps, steps)
        self.steps = steps

    @torch.no_grad()
    def __call__(self, denoise: Denoiser, noise: torch.Tensor, generator: torch.Generator | None = None,
                 callback: Callback | None = None) -> torch.Tensor:
        """x_T = noise (b, ...) → x0 (b, ...). callback(i, t, x_t, x̂0) after step i denoised x_t at timestep t."""
        x = noise
        for i, t in enumerate(tqdm(self.timesteps, desc="DDIM", disable=not self.progress, leave=False)):
            s = self.timesteps[i + 1] if i + 1 < self.steps else None
            (alpha_t, sigma_t), (alpha_s, sigma_s) = alpha_sigma_of(self.schedule, t), alpha_sigma_of(self.schedule, s)
            x0 = predict_x0(denoise, x, t, alpha_t, sigma_t, self.clip_x0)
            eps = (x - alpha_t * x0) / sigma_t
            c = self.eta * sigma_s / sigma_t * math.sqrt(max(0.0, 1.0 - (alpha_t / alpha_s) ** 2))
            x_next = alpha_s * x0 + math.sqrt(max(0.0, sigma_s**2 - c**2)) * eps
            if c > 0:
                x_next = x_next + c * standard_normal(x, generator)
            if callback is not None:
                callback(i, t, x, x0)
            x = x_next
        return x


class DPMSolverSampler:
    """DPM-Solver++(2M) (Lu et al. 2022, Alg. 2): multistep second order in data-prediction form.

    With λ = log(α/σ), h_i = λ_{t_i} − λ_{t_{i−1}}, r_i = h_{i−1}/h_i and D_i the second-order
    combination of the last two x̂0 predictions,
        D_i = (1 + 1/(2 r_i)) x̂0(t_{i−1}) − 1/(2 r_i) x̂0(t_{i−2}),
        x_{t_i} = (σ_{t_i}/σ_{t_{i−1}}) x_{t_{i−1}} − α_{t_i} (e^{−h_i} − 1) D_i.
    The first step uses D = x̂0 (first order, identical to DDIM η = 0), and so does the last: the
    clean end has λ = ∞, where the step reduces to x0 = x̂0. A fewer-step alternative to DDIM-50.

    Args:
        schedule: the noise schedule the denoiser was trained with.
        steps: network evaluations N (trailing spacing, see the module docstring).
        clip_x0: clip x̂0 to [−1, 1] (pixel data).
        progress: tqdm bar over the steps.
    """

    def __init__(self, schedule: CosineNoiseSchedule, steps: int = 20, clip_x0: bool = True, progress: bool = False):
        self.schedule, self.clip_x0, self.progress = schedule, clip_x0, progress
        self.timesteps = trailing_timesteps(schedule.timesteps, steps)
        self.steps = steps

    @torch.no_grad()
    def __call__(self, denoise: Denoiser, noise: torch.Tensor, generator: torch.Generator | None = None,
                 callback: Callback | None = None) -> torch.Tensor:
        """x_T = noise (b, ...) → x0 (b, ...); deterministic, `generator` is accepted for a common signature."""
        x, previous, h_previous = noise, None, None
        for i, t in enumerate(tqdm(self.timesteps, desc="DPM-Solver++", disable=not self.progress, leave=False)):
            alpha_t, sigma_t = alpha_sigma_of(self.schedule, t)
            x0 = predict_x0(denoise, x, t, alpha_t, sigma_t, self.clip_x0)
            if i + 1 == self.steps:
                x_next = x0  # first-order step to σ = 0
            else:
                alpha_s, sigma_s = alpha_sigma_of(self.schedule, self.timesteps[i + 1])
                h = math.log(alpha_s / sigma_s) - math.log(alpha_t / sigma_t)
                d = x0
                if previous is not None:
                    half_r = 0.5 * h / h_previous  # 1 / (2 r)
                    d = (1.0 + half_r) * x0 - half_r * previous
                x_next = (sigma_s / sigma_t) * x - alpha_s * math.expm1(-h) * d
                previous, h_previous = x0, h
            if callback is not None:
                callback(i, t, x, x0)
            x = x_next
        return x


class OneStepMeanSampler:
    """The decoder's estimate of the conditional mean E[x0 | conditioning]: x̂0 at the noisiest step, averaged over
    `draws` pure-noise inputs (x_T carries no signal there, α_T ≈ 0.001, so every draw estimates the same mean and the
    average cancels what each adds from its noise). A fast deterministic-in-expectation alternative to DDIM-50:
    `draws` network evaluations, no sampled detail, hence the lowest distortion (PSNR) and temporal flicker an
    estimate of the mean can give (docs/video_decoder.md measures it against DDIM).

    Args:
        schedule: the noise schedule the denoiser was trained with.
        draws: noise inputs averaged (network evaluations); the first is the `noise` passed in.
        clip_x0: clip each x̂0 to [−1, 1] (pixel data).
        antithetic: every second draw is the previous draw negated (x_T, −x_T): the part of x̂0 that is linear in the
            noise cancels within each pair instead of shrinking as 1/√draws (a variance-reduction trick of Monte Carlo
            integration), so fewer evaluations reach the same steadiness (docs/video_decoder.md measures it).
    """

    def __init__(self, schedule: CosineNoiseSchedule, draws: int = 8, clip_x0: bool = True, antithetic: bool = False):
        if draws < 1:
            raise ValueError(f"OneStepMeanSampler: draws ≥ 1, got {draws}")
        if antithetic and draws % 2:
            raise ValueError(f"OneStepMeanSampler: antithetic draws come in pairs, got draws={draws} (odd)")
        self.schedule, self.draws, self.clip_x0, self.antithetic = schedule, draws, clip_x0, antithetic
        self.steps = draws

    @torch.no_grad()
    def __call__(self, denoise: Denoiser, noise: torch.Tensor, generator: torch.Generator | None = None,
                 callback: Callback | None = None) -> torch.Tensor:
        """x_T = noise (b, ...) → mean x̂0 (b, ...); callback(i, T − 1, x_T of draw i, running mean) per draw."""
        t = self.schedule.timesteps - 1
        alpha, sigma = alpha_sigma_of(self.schedule, t)
        total = torch.zeros_like(noise)
        x = noise
        for i in range(self.draws):
            if self.antithetic and i % 2:
                x = -x
            elif i > 0:
                x = standard_normal(noise, generator)
            total = total + predict_x0(denoise, x, t, alpha, sigma, self.clip_x0)
            if callback is not None:
                callback(i, t, x, total / (i + 1))
        return total / self.draws


class ImageVideoBlend:
    """Eq. 4 (GAIA-1 §5.2): at random diffusion steps, average the image and video denoisers.

        ε̃ = w · ε^π(x_t) + (1 − w) · ε(x_t),   applied at each step with probability p

    ε^π denoises every frame on its own as an image (the U-Net with its temporal layers switched
    off), ε the frames jointly as a video; the paper uses p = 0.25, w = 0.5 to trade each frame's
    fidelity to its tokens against temporal consistency in autoregressive decoding.

    Blending the v predictions is the same as blending ε (and x̂0): at fixed x_t both are affine
    in v with the same coefficients, ε = σ x_t + α v and x̂0 = α x_t − σ v, so with weights summing
    to one w·ε(v_img) + (1 − w)·ε(v_vid) = σ x_t + α (w v_img + (1 − w) v_vid) = ε(w v_img + (1 − w) v_vid).

    Args:
        probability: p, the chance that a step blends.
        weight: w, the image denoiser's share in a blended step.
    """

    def __init__(self, probability: float = 0.25, weight: float = 0.5):
        if not 0.0 <= probability <= 1.0:
            raise ValueError(f"ImageVideoBlend: probability in [0, 1], got {probability}")
        self.probability, self.weight = probability, weight

    def denoiser(self, video: Denoiser, image: Denoiser, generator: torch.Generator | None = None) -> BlendedDenoiser:
        """A Denoiser for one sampling run; the draws come from `generator` (a CPU one avoids device syncs)."""
        return BlendedDenoiser(video, image, self.probability, self.weight, generator)


class BlendedDenoiser:
    """Denoiser returned by ImageVideoBlend.denoiser. One call is one diffusion step; `calls` counts
    them and `blended` those that used eq. 4. Steps that do not blend run the video denoiser only."""

    def __init__(self, video: Denoiser, image: Denoiser, probability: float, weight: float,
                 generator: torch.Generator | None):
        self.video, self.image, self.probability, self.weight = video, image, probability, weight
        self.generator = generator
        self.calls = self.blended = 0

    def __call__(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """x_t (b, ...), t (b,) → v (b, ...), blended for the whole batch or not at all."""
        self.calls += 1
        where = self.generator.device if self.generator is not None else "cpu"
        if torch.rand((), generator=self.generator, device=where).item() >= self.probability:
            return self.video(x, t)
        self.blended += 1
        return self.weight * self.image(x, t) + (1.0 - self.weight) * self.video(x, t)
