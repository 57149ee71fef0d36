"""Rotary position embedding over time steps (RoPE, Su et al. 2021) for interleaved per-step token sequences.

Legend: b batch, h heads, s positions, e head width, L tokens per time step.

Every position of one time step gets the same rotation, by its step index p // L: the attention score of two tokens
then depends on how many steps apart they are, never on where the window starts. A KV cache can therefore drop the
oldest step when a window slides and keep the other cached keys (GAIA-1's learned absolute temporal embeddings
change all of them). The first layer's keys are then exactly a re-prefilled window's; deeper layers' keys were
computed while the dropped step was in view and keep a trace of it, as in Transformer-XL's segment memory, so a
rolled window approximates the re-prefilled one. Not in GAIA-1 (§2.1: learned factorised embeddings); an option
for new models.
"""

from __future__ import annotations

import torch
from torch import nn


class StepRotary(nn.Module):
    """cos/sin tables (s, e) of the time step of each absolute position.

    Args:
        head_dim: e (even). step_len: L, tokens per time step. base: the frequency base (RoPE's 10 000).
    """

    def __init__(self, head_dim: int, step_len: int, base: float = 10_000.0):
        super().__init__()
        if head_dim % 2:
            raise ValueError(f"rotary embeddings need an even head width, got {head_dim}")
        self.step_len = step_len
        inverse = base ** (-torch.arange(0, head_dim, 2, dtype=torch.float32) / head_dim)
        self.register_buffer("inverse_frequency", inverse, persistent=False)

    def forward(self, start: int, length: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """cos, sin (length, e) of positions start..start+length-1 (absolute, counting dropped ones)."""
        return self.table(torch.arange(start, start + length, device=device))

    def at(self, position: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """cos, sin (1, e) of one absolute position given as a 0-dim int64 tensor (a fixed-shape decode step reads
        its position from a tensor, so one captured graph serves every position)."""
        return self.table(position.view(1))

    def table(self, positions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """cos, sin (s, e) of absolute positions (s,) int64."""
        steps = torch.div(positions, self.step_len, rounding_mode="floor")
        angles = steps[:, None].float() * self.inverse_frequency.to(positions.device)[None]  # (s, e/2)
        angles = torch.cat([angles, angles], dim=-1)
        return angles.cos(), angles.sin()


def rotate(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """Apply the rotation to queries or keys x (b, h, s, e) with cos, sin (s, e) (the rotate-half convention)."""
    half = x.shape[-1] // 2
    turned = torch.cat([-x[..., half:], x[..., :half]], dim=-1)
    return (x * cos + turned * sin).to(x.dtype)
