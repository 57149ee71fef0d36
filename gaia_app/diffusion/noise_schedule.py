"""Gaussian diffusion for the GAIA-1 video decoder: cosine β schedule and v-parameterisation (GAIA-1 §2.4, eq. 2, §4.3).

Legend:
    b batch, T diffusion timesteps (discrete t ∈ {0, …, T − 1}, t = 0 the least noisy), `...` any
    trailing dims of a sample (video `v t c h w`, an image `c h w`, …).

Forward process: x_t = α_t x0 + σ_t ε with α_t = sqrt(ᾱ_t), σ_t = sqrt(1 − ᾱ_t), so α² + σ² = 1
(variance preserving). The network predicts v = α ε − σ x0 (Salimans & Ho 2022, GAIA-1 ref. [39]);
x0 and ε are both affine in v at fixed x_t, which is all the samplers need.
"""

from __future__ import annotations

import math

import torch


class CosineNoiseSchedule:
    """Cosine β schedule of Nichol & Dhariwal (2021), GAIA-1 §4.3 "cosine β-noise schedule".

    ᾱ(τ) = f(τ) / f(0), f(τ) = cos²((τ + s) / (1 + s) · π/2) on τ ∈ [0, 1]; the discrete
    β_t = min(1 − ᾱ((t + 1)/T) / ᾱ(t/T), max_beta) and ᾱ_t = Π_{i ≤ t} (1 − β_i). The offset s keeps
    β_0 from vanishing (σ_0 ≈ 0.006 for T = 1000); max_beta keeps ᾱ_{T−1} > 0 (f(1) = 0).

    Attributes:
        timesteps: T.
        betas: (T,) float64.
        alphas_cumprod: ᾱ, (T,) float64, strictly decreasing from ≈ 1 to ≈ 0.
    """

    def __init__(self, timesteps: int = 1000, offset: float = 0.008, max_beta: float = 0.999):
        if timesteps < 1 or offset <= 0 or not 0 < max_beta < 1:
            raise ValueError(f"CosineNoiseSchedule: timesteps ≥ 1, offset > 0, 0 < max_beta < 1; got "
                             f"{timesteps}, {offset}, {max_beta}")
        self.timesteps, self.offset, self.max_beta = timesteps, offset, max_beta
        tau = torch.arange(timesteps + 1, dtype=torch.float64) / timesteps
        f = torch.cos((tau + offset) / (1 + offset) * math.pi / 2) ** 2
        self.betas = (1 - f[1:] / f[:-1]).clamp(max=max_beta)
        self.alphas_cumprod = torch.cumprod(1 - self.betas, dim=0)
        # α, σ tables are square-rooted in float64 (σ_0 = sqrt(1 − ᾱ_0) loses digits in float32),
        # then cached per device so alpha_sigma never copies host → device inside the sampling loop.
        self._tables: dict[torch.device, tuple[torch.Tensor, torch.Tensor]] = {}

    def __repr__(self) -> str:
        return f"CosineNoiseSchedule(timesteps={self.timesteps}, offset={self.offset}, max_beta={self.max_beta})"

    def alpha_sigma(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """t: (b,) int64 → α_t, σ_t: (b,) float32 each, on t.device."""
        if t.device not in self._tables:
            alpha, sigma = self.alphas_cumprod.sqrt(), (1 - self.alphas_cumprod).sqrt()
            self._tables[t.device] = alpha.float().to(t.device), sigma.float().to(t.device)
        alpha, sigma = self._tables[t.device]
        return alpha[t], sigma[t]

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Forward process of eq. 2: x0, noise (b, ...), t (b,) → x_t = α_t x0 + σ_t ε, (b, ...)."""
        alpha, sigma = self.alpha_sigma(t)
        return expand(alpha, x0) * x0 + expand(sigma, x0) * noise

    def sample_timesteps(self, batch: int, device: torch.device | str,
                         generator: torch.Generator | None = None) -> torch.Tensor:
        """(b,) int64 uniform over {0, …, T − 1} (the discrete t' ~ U(0, 1) of eq. 2), on `device`."""
        # drawn where the generator lives, so a CPU generator also seeds CUDA training
        where = generator.device if generator is not None else device
        return torch.randint(0, self.timesteps, (batch,), generator=generator, device=where).to(device)


def expand(coef: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Per-sample coefficients (b,) → (b, 1, …, 1) in like's dtype, broadcasting over like's trailing dims."""
    return coef.to(like.dtype).reshape(*coef.shape, *([1] * (like.ndim - coef.ndim)))


def v_target(x0: torch.Tensor, noise: torch.Tensor, alpha: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """The regression target of eq. 2 in v-parameterisation: v = α ε − σ x0, (b, ...)."""
    return expand(alpha, x0) * noise - expand(sigma, x0) * x0


def x0_from_v(x_t: torch.Tensor, v: torch.Tensor, alpha: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Clean-sample prediction x0 = α x_t − σ v, (b, ...)."""
    return expand(alpha, x_t) * x_t - expand(sigma, x_t) * v


def eps_from_v(x_t: torch.Tensor, v: torch.Tensor, alpha: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Noise prediction ε = σ x_t + α v, (b, ...)."""
    return expand(sigma, x_t) * x_t + expand(alpha, x_t) * v


def v_from_x0(x_t: torch.Tensor, x0: torch.Tensor, alpha: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Inverse of x0_from_v at fixed x_t: v = (α x_t − x0) / σ, (b, ...). σ_t > 0 for every t of the schedule."""
    return (expand(alpha, x_t) * x_t - x0) / expand(sigma, x_t)
