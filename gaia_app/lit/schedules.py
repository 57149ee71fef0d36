"""Learning-rate schedules used by every component (built from `_partial_` configs)."""

from __future__ import annotations

import math

from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR


def warmup_cosine_factor(step: int, warmup_steps: int, decay_steps: int, final_ratio: float) -> float:
    """Multiplier of the peak LR at `step`: linear warm-up, cosine decay to `final_ratio`, then flat.

    GAIA-1 §4.1 (tokenizer: 5k warm-up, 10k cosine to 1e-5 from 1e-4) and §4.2 (world model:
    cosine decay by 10×) both fit this shape.
    """
    if step < warmup_steps:
        return (step + 1) / warmup_steps
    progress = min(1.0, (step - warmup_steps) / max(1, decay_steps))
    return final_ratio + (1.0 - final_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))


def warmup_cosine(optimizer: Optimizer, warmup_steps: int, decay_steps: int, final_lr: float) -> LambdaLR:
    """LambdaLR stepping per optimiser step; `final_lr` is absolute (e.g. 1e-5)."""
    peak = optimizer.param_groups[0]["lr"]
    if peak <= 0:
        raise ValueError(f"warmup_cosine: optimizer lr must be > 0, got {peak}")
    ratio = final_lr / peak
    return LambdaLR(optimizer, lambda step: warmup_cosine_factor(step, warmup_steps, decay_steps, ratio))
