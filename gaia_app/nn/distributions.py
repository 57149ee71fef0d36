"""Diagonal Gaussian posterior of a continuous (VAE-style) tokenizer (GAIA-2 report, tokenizer: "the encoder
outputs parameters for a Gaussian distribution for each latent token").

Legend: any shape `...`; the distribution is over every element independently.
"""

from __future__ import annotations

import torch


class DiagonalGaussian:
    """N(mean, exp(logvar)) per element. mean, logvar: tensors of the same shape.

    logvar is clamped to [-30, 20] so exp() neither underflows to a zero σ nor overflows early in
    training (the Stable Diffusion / LDM convention).
    """

    def __init__(self, mean: torch.Tensor, logvar: torch.Tensor):
        if mean.shape != logvar.shape:
            raise ValueError(f"DiagonalGaussian: mean {tuple(mean.shape)} and logvar {tuple(logvar.shape)} differ")
        self.mean = mean
        self.logvar = logvar.clamp(-30.0, 20.0)

    @property
    def std(self) -> torch.Tensor:
        return torch.exp(0.5 * self.logvar)

    def sample(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """mean + σ·ε, ε ~ N(0, I): differentiable in mean and logvar (reparameterisation)."""
        eps = torch.randn(self.mean.shape, generator=generator, device=self.mean.device, dtype=self.mean.dtype)
        return self.mean + self.std * eps

    def mode(self) -> torch.Tensor:
        """The most likely latent: the mean."""
        return self.mean

    def kl(self) -> torch.Tensor:
        """KL(q ‖ N(0, I)) per element, closed form ½(μ² + σ² − 1 − log σ²), in nats; shape of mean."""
        return 0.5 * (self.mean.pow(2) + self.logvar.exp() - 1.0 - self.logvar)
