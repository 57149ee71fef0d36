"""Scaling laws of the world model (GAIA-1 §6, Fig. 8): compute, power-law fit, extrapolation.

GAIA-1 §6: C = 6·N per token for a forward-backward pass, N the parameter count without embeddings, times the
training tokens; the validation cross-entropy of models trained with less compute is fitted with
f(x) = c + (x / a)^b and the fit predicts the final (largest) model's loss.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
from torch import nn


def non_embedding_parameters(net: nn.Module, block_types: Sequence[type[nn.Module]]) -> int:
    """N of GAIA-1 §6: the parameters of the repeated blocks (the transformer trunk), without token and position
    embeddings, output head or condition projections, which do not grow with depth (Kaplan et al. [49] §2.1)."""
    types = tuple(block_types)
    seen: set[int] = set()
    total = 0
    for module in net.modules():
        if isinstance(module, types):
            for p in module.parameters():
                if id(p) not in seen:
                    seen.add(id(p))
                    total += p.numel()
    if not total:
        raise ValueError(f"{type(net).__name__} has no parameters in blocks of types {[t.__name__ for t in types]}")
    return total


def training_compute(non_embedding: int, tokens: int) -> float:
    """C = 6·N·tokens floating-point operations (GAIA-1 §6)."""
    return 6.0 * non_embedding * tokens


@dataclass(frozen=True)
class PowerLaw:
    """f(x) = c + (x / a)^b (GAIA-1 §6); b < 0 for a loss falling with compute.

    Kept as log a: for nearly flat losses b → 0 and a itself overflows while (x / a)^b stays finite.
    """

    log_a: float
    b: float
    c: float

    @classmethod
    def from_a(cls, a: float, b: float, c: float) -> PowerLaw:
        return cls(math.log(a), b, c)

    @property
    def a(self) -> float:
        return math.exp(self.log_a) if self.log_a < 700 else math.inf

    def __call__(self, x: np.ndarray | float) -> np.ndarray | float:
        return self.c + np.exp(self.b * (np.log(np.asarray(x, dtype=np.float64)) - self.log_a))

    def as_dict(self) -> dict[str, float]:
        return {**asdict(self), "a": self.a}


def fit_power_law(x: Sequence[float], y: Sequence[float], grid: int = 4000) -> PowerLaw:
    """Least-squares fit of f(x) = c + (x / a)^b to (x, y), x > 0 and y above the floor c.

    For a fixed floor c, log(y − c) = b·log x − b·log a is linear, so (a, b) come from a line fit in log space;
    the floor is searched on a grid in [0, min y) and the one with the smallest squared error of f itself wins
    (no optimiser to seed, no local minima of a 3-parameter non-linear fit). Needs ≥ 3 points.
    """
    xs, ys = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if xs.ndim != 1 or xs.shape != ys.shape or len(xs) < 3:
        raise ValueError(f"fit_power_law needs ≥ 3 matching (x, y) points; got x {xs.shape}, y {ys.shape}")
    if (xs <= 0).any():
        raise ValueError(f"fit_power_law needs x > 0; got {xs.tolist()}")
    floor = float(ys.min())
    best: tuple[float, PowerLaw] | None = None
    # the floor runs up to just below the smallest loss, denser near it where good fits tend to sit
    for frac in 1.0 - np.geomspace(1.0, 1e-4, grid):
        law = _line_fit(xs, ys, frac * floor)
        error = float(np.square(law(xs) - ys).sum())
        if math.isfinite(error) and (best is None or error < best[0]):
            best = (error, law)
    assert best is not None
    return best[1]


def _line_fit(xs: np.ndarray, ys: np.ndarray, c: float) -> PowerLaw:
    """(a, b) of log(y − c) = b·(log x − log a) by least squares (flat losses, b = 0: a = 1)."""
    b, intercept = np.polyfit(np.log(xs), np.log(ys - c), 1)
    return PowerLaw(log_a=float(-intercept / b) if b else 0.0, b=float(b), c=float(c))


def extrapolation_error(law: PowerLaw, x: float, y: float) -> float:
    """|f(x) − y| / y: the relative error of the fit's prediction for a held-out point."""
    return abs(float(law(x)) - y) / y
