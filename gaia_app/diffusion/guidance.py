"""Classifier-free guidance of autoregressive logits and its schedules (GAIA-1 §5.1, eq. 3, Fig. 7).

Legend:
    b batch, V vocabulary, f generated frames, n image tokens per frame.

Schedules are config objects returning multipliers of the guidance scale; ClassifierFreeGuidance
combines them into a (f, n) table of scales, one per generated token.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import torch


@dataclass(frozen=True)
class ConstantSchedule:
    """Multiplier 1 everywhere."""

    def __call__(self, length: int) -> torch.Tensor:
        return torch.ones(length)


@dataclass(frozen=True)
class LinearSchedule:
    """Multipliers from `start` (first token of a frame) linearly to `end` (last) — GAIA-1 §5.1 over tokens."""

    start: float = 1.0
    end: float = 0.0

    def __call__(self, length: int) -> torch.Tensor:
        return torch.linspace(self.start, self.end, length) if length > 1 else torch.full((length,), self.start)


@dataclass(frozen=True)
class CosineSchedule:
    """`plateau` frames at multiplier 1, then cosine decay to `end` at the last frame — GAIA-1 §5.1, Fig. 7 over
    frames."""

    plateau: int = 0
    end: float = 0.0

    def __call__(self, length: int) -> torch.Tensor:
        decay = max(1, length - self.plateau - 1)
        progress = ((torch.arange(length) - self.plateau).clamp(min=0) / decay).clamp(max=1.0)
        return self.end + (1.0 - self.end) * 0.5 * (1.0 + torch.cos(math.pi * progress))


@dataclass(frozen=True)
class ClassifierFreeGuidance:
    """Eq. 3: l = (1 + s)·l_cond − s·l_uncond, with s = scale × frame multiplier × token multiplier.

    scale 0 gives the conditional logits (the diffusers-style weight 1 + s = 1). Replacing the
    unconditioned stream by a negative prompt's stream gives negative prompting (GAIA-1 §5.1).
    text_scale: the scale of rollouts prompted with text, when it differs from that of rollouts steered by actions
    alone (None: `scale` for both). GAIA-1 §5.1 leaves scale and schedule to be tuned per use; a text prompt
    changes the whole scene and takes more guidance than a command, whose larger scales break frames up.
    """

    scale: float = 3.0
    tokens: ConstantSchedule | LinearSchedule | CosineSchedule = field(default_factory=ConstantSchedule)
    frames: ConstantSchedule | LinearSchedule | CosineSchedule = field(default_factory=ConstantSchedule)
    text_scale: float | None = None

    def __post_init__(self) -> None:
        for name in ("scale", "text_scale"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, (int, float)) and 0 <= value < float("inf")):
                raise ValueError(f"guidance.{name}={value!r}: expected a finite number ≥ 0")

    def for_rollout(self, prompted: bool) -> ClassifierFreeGuidance:
        """The guidance of one rollout: `text_scale` replaces `scale` when the rollout is prompted with text."""
        return replace(self, scale=self.text_scale) if prompted and self.text_scale is not None else self

    def scales(self, frames: int, tokens: int) -> torch.Tensor:
        """(f, n) guidance scale of each generated token."""
        return self.scale * self.frames(frames)[:, None] * self.tokens(tokens)[None, :]

    def __call__(self, cond_logits: torch.Tensor, uncond_logits: torch.Tensor,
                 scale: float | torch.Tensor) -> torch.Tensor:
        """(b, V) guided logits from the two streams' (b, V) logits."""
        return (1.0 + scale) * cond_logits - scale * uncond_logits
