"""Streaming Fréchet distance between two feature sets (FID, FDD, FVMD all reduce to it).

FID (Heusel et al. 2017) and the Fréchet DINO Distance GAIA-2 reports (§6) fit a Gaussian to the features of
real and of generated samples and measure

    d² = |μ_r − μ_g|² + Tr(Σ_r + Σ_g − 2 (Σ_r Σ_g)^½).

Features arrive batch by batch: `FrechetStatistics` keeps the count, the feature sum and the sum of outer
products in float64 (a float32 running covariance loses several digits over 50k samples), merges across
processes with one all-reduce, and turns into (μ, Σ) only at the end.
"""

from __future__ import annotations

import torch
import torch.distributed as dist


class FrechetStatistics:
    """Running first and second moments of d-dimensional features (float64, any device)."""

    def __init__(self, dim: int, device: torch.device | str = "cpu"):
        self.dim = dim
        self.count = torch.zeros((), dtype=torch.float64, device=device)
        self.total = torch.zeros(dim, dtype=torch.float64, device=device)
        self.outer = torch.zeros(dim, dim, dtype=torch.float64, device=device)

    def update(self, features: torch.Tensor) -> FrechetStatistics:
        """Add a batch of features (b, d); returns self."""
        if features.ndim != 2 or features.shape[1] != self.dim:
            raise ValueError(f"FrechetStatistics.update expects features of shape (batch, {self.dim}), "
                             f"got {tuple(features.shape)}")
        if not torch.isfinite(features).all():
            raise ValueError("FrechetStatistics.update got non-finite features (NaN or inf)")
        x = features.detach().to(self.total.device, torch.float64)
        self.count += x.shape[0]
        self.total += x.sum(0)
        self.outer += x.T @ x
        return self

    def merge(self, other: FrechetStatistics) -> FrechetStatistics:
        """Add another set's moments (same dim) into this one; returns self."""
        if other.dim != self.dim:
            raise ValueError(f"cannot merge Fréchet statistics of dim {other.dim} into dim {self.dim}")
        self.count += other.count.to(self.count.device)
        self.total += other.total.to(self.total.device)
        self.outer += other.outer.to(self.outer.device)
        return self

    def all_reduce(self) -> FrechetStatistics:
        """A copy holding the moments summed over every process of the default group (this rank's own moments
        stay as they are, so calling it twice does not double-count); a plain copy when not distributed."""
        reduced = FrechetStatistics(self.dim, self.total.device)
        reduced.merge(self)
        if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
            for tensor in (reduced.count, reduced.total, reduced.outer):
                dist.all_reduce(tensor, op=dist.ReduceOp.SUM)
        return reduced

    def mean_cov(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(μ (d,), unbiased Σ (d, d)) in float64; needs at least 2 samples."""
        n = float(self.count)
        if n < 2:
            raise ValueError(f"a Fréchet distance needs at least 2 feature vectors per set, got {int(n)}")
        mean = self.total / n
        cov = (self.outer - n * torch.outer(mean, mean)) / (n - 1)
        return mean, (cov + cov.T) / 2


def _sqrt_psd(matrix: torch.Tensor) -> torch.Tensor:
    """Symmetric square root of a symmetric positive semi-definite matrix; eigenvalues below 0 (round-off) → 0."""
    values, vectors = torch.linalg.eigh(matrix)
    return (vectors * values.clamp_min(0).sqrt()) @ vectors.T


def frechet_distance_gaussians(mean_a: torch.Tensor, cov_a: torch.Tensor, mean_b: torch.Tensor,
                               cov_b: torch.Tensor) -> float:
    """d² between N(μ_a, Σ_a) and N(μ_b, Σ_b), float64.

    Tr (Σ_a Σ_b)^½ equals Σ √λ of the symmetric PSD matrix Σ_a^½ Σ_b Σ_a^½, whose eigenvalues `eigh` finds stably;
    this avoids the complex parts scipy's general `sqrtm` returns for nearly singular covariances.
    """
    mean_a, cov_a, mean_b, cov_b = (t.to(torch.float64) for t in (mean_a, cov_a, mean_b, cov_b))
    root_a = _sqrt_psd(cov_a)
    middle = root_a @ cov_b @ root_a
    trace_sqrt = torch.linalg.eigvalsh((middle + middle.T) / 2).clamp_min(0).sqrt().sum()
    distance = (mean_a - mean_b).pow(2).sum() + cov_a.trace() + cov_b.trace() - 2 * trace_sqrt
    return float(distance.clamp_min(0))


def frechet_distance(real: FrechetStatistics, generated: FrechetStatistics) -> float:
    """Fréchet distance between the Gaussians fitted to two streamed feature sets."""
    if real.dim != generated.dim:
        raise ValueError(f"Fréchet distance between features of dim {real.dim} and {generated.dim}")
    return frechet_distance_gaussians(*real.mean_cov(), *generated.mean_cov())
