"""Balanced sampling over binned features (GAIA-1 §3, DESIGN.md §4).

Per feature, an example's weight is (empirical frequency of its bin) ** -exponent; the joint weight
is the product over features; an example is kept with probability weight / max weight.
Exponent 0 keeps the empirical distribution, 1 makes each feature's bins equally likely.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence

import numpy as np
from torch.utils.data import Sampler


def bin_feature(values: Sequence, bins: int | Sequence[float] | None) -> np.ndarray:
    """Bin ids (n,) int for one feature.

    Numbers go into `bins` equal-width bins (an int) or between explicit edges (a sequence);
    categorical values (strings, or bins=None) map each distinct value to its own bin.
    """
    arr = np.asarray(values)
    if bins is None or arr.dtype.kind in "OUSb":
        _, ids = np.unique(arr.astype(str), return_inverse=True)
        return ids.reshape(-1)
    arr = arr.astype(np.float64)
    if np.isnan(arr).any():
        raise ValueError("bin_feature: numeric feature has NaN values; label them or balance on another feature")
    if isinstance(bins, int):
        lo, hi = float(arr.min()), float(arr.max())
        edges = np.linspace(lo, hi if hi > lo else lo + 1.0, bins + 1)
    else:
        edges = np.asarray(bins, dtype=np.float64)
    return np.clip(np.digitize(arr, edges[1:-1]), 0, len(edges) - 2)


def balancing_weights(features: Mapping[str, Sequence], bins: Mapping[str, int | Sequence[float] | None],
                      exponent: float) -> np.ndarray:
    """Joint acceptance weights (n,) in (0, 1]: the per-feature inverse-frequency weights multiplied."""
    if not features:
        raise ValueError("balancing_weights: no features given")
    n = {len(v) for v in features.values()}
    if len(n) != 1:
        raise ValueError(f"balancing_weights: features have different lengths {sorted(n)}")
    weight = np.ones(n.pop(), dtype=np.float64)
    for name, values in features.items():
        ids = bin_feature(values, bins.get(name))
        freq = np.bincount(ids) / len(ids)
        weight *= freq[ids] ** -exponent
    return weight / weight.max()


class BalancedSampler(Sampler[int]):
    """Yields `num_samples` indices per epoch, each drawn uniformly and kept with probability w/max w.

    Args:
        weights: (n,) acceptance weights from `balancing_weights`.
        num_samples: indices per epoch (default n).
        seed: base seed; epoch e uses seed + e, so runs are reproducible and epochs differ.
    """

    def __init__(self, weights: np.ndarray, num_samples: int | None = None, seed: int = 0):
        self.weights = np.asarray(weights, dtype=np.float64)
        if self.weights.ndim != 1 or len(self.weights) == 0 or (self.weights <= 0).any():
            raise ValueError("BalancedSampler: weights must be a non-empty 1-D array of positive values")
        self.num_samples = int(num_samples or len(self.weights))
        self.seed = seed
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return self.num_samples

    def __iter__(self) -> Iterator[int]:
        rng = np.random.default_rng(self.seed + self.epoch)
        accept = self.weights / self.weights.max()
        chosen: list[int] = []
        while len(chosen) < self.num_samples:
            candidates = rng.integers(0, len(accept), size=max(64, 2 * self.num_samples))
            kept = candidates[rng.random(len(candidates)) < accept[candidates]]
            chosen.extend(kept.tolist())
        self.epoch += 1
        return iter(chosen[: self.num_samples])


def clip_features(clip, names: Sequence[str]) -> dict[str, object]:
    """Balancing features of one clip: metadata keys (e.g. weather) or 'speed' / 'curvature'
    (mean over the clip, needs actions). Raises KeyError naming the missing feature."""
    out: dict[str, object] = {}
    for name in names:
        if name in ("speed", "curvature"):
            if clip.actions is None:
                raise KeyError(f"clip '{clip.clip_id}' has no actions, cannot balance on '{name}'")
            col = 0 if name == "speed" else 1
            out[name] = float(np.mean(clip.actions[:, col]))
        elif name in clip.meta:
            out[name] = clip.meta[name]
        else:
            raise KeyError(f"clip '{clip.clip_id}' has no metadata '{name}' to balance on (has {sorted(clip.meta)})")
    return out
