"""Reference cross-entropies (nats/token) for image-token world models (GAIA-1 §2.3 objective).

Legend:
    t time steps, n image tokens per step, V vocabulary.

A world model worth its compute must beat both: the unigram distribution of the training tokens,
and "copy the token at the same position in the previous frame", smoothed with the ε that is best
on the evaluated tokens themselves (an optimistic baseline, so beating it is a conservative test).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch


def unigram_cross_entropy(train: torch.Tensor, target: torch.Tensor, vocab: int) -> float:
    """Cross-entropy of `target` tokens under add-one-smoothed unigram counts of `train` (any int shapes)."""
    counts = torch.bincount(train.flatten(), minlength=vocab).double() + 1.0
    log_p = (counts / counts.sum()).log()
    return float(-log_p[target.flatten()].mean())


def copy_previous_cross_entropy(tokens: torch.Tensor, vocab: int) -> tuple[float, float]:
    """(cross-entropy, ε) of predicting z_{t,i} = z_{t-1,i} with probability 1 − ε, ε/(V − 1) elsewhere.

    tokens: (..., t, n); frames 2..t are scored. The best ε is the mismatch rate (the closed-form MLE),
    clamped away from 0 and 1.
    """
    same = (tokens[..., 1:, :] == tokens[..., :-1, :]).double().mean().item()
    eps = min(max(1.0 - same, 1e-6), 1 - 1e-6)
    ce = -(same * math.log(1.0 - eps) + (1.0 - same) * math.log(eps / (vocab - 1)))
    return ce, eps


@torch.no_grad()
def model_cross_entropy(logits_fn: Callable[[torch.Tensor], torch.Tensor], windows: torch.Tensor,
                        batch: int = 8) -> float:
    """Mean eq. 1 cross-entropy (nats/token) over image tokens of frames 2..T, the frames the copy baseline scores.

    logits_fn: tokens (b, t, n) → logits (b, t, n, V), e.g. a world model with null conditions.
    windows: (w, t, n) int64.
    """
    total, count = 0.0, 0
    for chunk in windows.split(batch):
        logits = logits_fn(chunk)[:, 1:]
        nll = torch.nn.functional.cross_entropy(logits.flatten(0, 2), chunk[:, 1:].flatten(), reduction="sum")
        total, count = total + nll.item(), count + chunk[:, 1:].numel()
    return total / count
