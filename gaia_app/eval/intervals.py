"""95 % intervals for the tables that compare a model with its ceiling and floor.

Three cases cover them: the mean of independent per-unit scores (per context, per rollout) gets a Student-t
interval; a share of units that pass (rollouts that read "night") gets a Wilson score interval, which stays
inside [0, 1] and is not degenerate at 0 or 1 successes; a pooled ratio over units (IoU = Σ intersection / Σ union
over scenes) and the paired difference of two such ratios on the same units get a percentile bootstrap over units.
"""

from __future__ import annotations

import functools
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


def _two_sided_t_mass(t: float, df: int) -> float:
    """P(|T| < t) for Student's t with an integer df, by its closed form in θ = atan(t / √df) (Abramowitz & Stegun
    26.7.3–4): a finite sum in cos²θ, even and odd df apart."""
    theta = math.atan(t / math.sqrt(df))
    c2 = math.cos(theta) ** 2
    if df % 2 == 0:
        term, total = 1.0, 1.0
        for k in range(1, df // 2):  # 1 + ½c² + (1·3)/(2·4)c⁴ + … up to c^(df−2)
            term *= c2 * (2 * k - 1) / (2 * k)
            total += term
        return math.sin(theta) * total
    if df == 1:
        return 2 * theta / math.pi
    term, total = 1.0, 1.0
    for k in range(1, (df - 1) // 2):  # 1 + (2/3)c² + (2·4)/(3·5)c⁴ + … up to c^(df−3)
        term *= c2 * (2 * k) / (2 * k + 1)
        total += term
    return 2 / math.pi * (theta + math.sin(theta) * math.cos(theta) * total)


@functools.lru_cache(maxsize=None)
def t_quantile(df: int) -> float:
    """Student-t 97.5 % quantile for df degrees of freedom, exact to 1e-12: bisection on the closed-form two-sided
    mass (an interval over two or three training runs, df 1–2, needs the exact value: 12.71 and 4.30)."""
    if df < 1:
        return math.inf
    low, high = Z95, 20.0
    while _two_sided_t_mass(high, df) < 0.95:
        high *= 2
    for _ in range(200):
        middle = (low + high) / 2
        low, high = (middle, high) if _two_sided_t_mass(middle, df) < 0.95 else (low, middle)
        if high - low < 1e-12:
            break
    return (low + high) / 2


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
