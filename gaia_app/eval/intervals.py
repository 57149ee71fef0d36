"""95 % intervals for the tables that compare a model with its ceiling and floor.

Three cases cover them: the mean of independent per-unit scores (per context, per rollout) gets a Student-t
interval; a share of units that pass (rollouts that read "night") gets a Wilson score interval, which stays
inside [0, 1] and is not degenerate at 0 or 1 successes; a pooled ratio over units (IoU = Σ intersection / Σ union
over scenes) and the paired difference of two such ratios on the same units get a percentile bootstrap over units.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

Z95 = 1.959963984540054  # standard normal 97.5 % quantile


@dataclass(frozen=True)
class Estimate:
    """A point estimate with its 95 % interval [low, high] over n units."""

    mean: float
    low: float
    high: float
    n: int

    @property
    def half_width(self) -> float:
        return (self.high - self.low) / 2

    def as_dict(self) -> dict[str, float]:
        return {"mean": self.mean, "low": self.low, "high": self.high, "n": self.n}

    def format(self, digits: int) -> str:
        """'m ± h' with `digits` decimals (the mean interval is symmetric; Wilson's is shown as [low, high])."""
        return f"{self.mean:.{digits}f} ± {self.half_width:.{digits}f}"


def t_quantile(df: int) -> float:
    """Student-t 97.5 % quantile for df degrees of freedom (Cornish–Fisher expansion; < 0.2 % error for df ≥ 3)."""
    if df < 1:
        return math.inf
    z = Z95
    return z + (z**3 + z) / (4 * df) + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * df**2) \
        + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * df**3)


def mean_interval(values: Sequence[float]) -> Estimate:
    """Mean of independent scores with its Student-t 95 % interval (infinite for a single value)."""
    values = [float(v) for v in values]
    n = len(values)
    if n == 0:
        raise ValueError("mean_interval needs at least one value")
    mean = sum(values) / n
    if n == 1:
        return Estimate(mean, -math.inf, math.inf, 1)
    sd = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1))
    half = t_quantile(n - 1) * sd / math.sqrt(n)
    return Estimate(mean, mean - half, mean + half, n)


def share_interval(successes: int, n: int) -> Estimate:
    """Share successes / n with its Wilson score 95 % interval."""
    if n <= 0 or not 0 <= successes <= n:
        raise ValueError(f"share_interval needs 0 ≤ successes ≤ n and n > 0, got {successes} of {n}")
    p, z2 = successes / n, Z95**2
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = Z95 * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return Estimate(p, max(0.0, centre - half), min(1.0, centre + half), n)


def ratio_interval(numerators: Sequence[float], denominators: Sequence[float], minus: tuple[Sequence[float],
                   Sequence[float]] | None = None, resamples: int = 2000, seed: int = 0) -> Estimate:
    """Pooled ratio Σ numerators / Σ denominators over units, with a 95 % percentile bootstrap interval (units
    drawn with replacement, a fixed seed so a table is reproducible). `minus` = (numerators, denominators) of a
    second ratio on the same units: the paired difference of the two, resampled together."""
    num, den = np.asarray(numerators, dtype=float), np.asarray(denominators, dtype=float)
    if num.shape != den.shape or num.ndim != 1 or len(num) == 0:
        raise ValueError(f"ratio_interval needs equal non-empty 1-D counts, got {num.shape} and {den.shape}")
    other = None if minus is None else (np.asarray(minus[0], dtype=float), np.asarray(minus[1], dtype=float))
    if other is not None and (other[0].shape != num.shape or other[1].shape != num.shape):
        raise ValueError(f"ratio_interval: the paired ratio's counts {other[0].shape} do not match {num.shape}")

    def pooled(index: np.ndarray) -> np.ndarray:  # (r, n) unit draws → (r,) ratio (difference)
        value = num[index].sum(-1) / np.maximum(den[index].sum(-1), 1e-12)
        return value if other is None else value - other[0][index].sum(-1) / np.maximum(other[1][index].sum(-1), 1e-12)

    n = len(num)
    point = float(pooled(np.arange(n)[None])[0])
    if n == 1:
        return Estimate(point, -math.inf, math.inf, 1)
    draws = pooled(np.random.default_rng(seed).integers(0, n, size=(resamples, n)))
    return Estimate(point, float(np.quantile(draws, 0.025)), float(np.quantile(draws, 0.975)), n)
