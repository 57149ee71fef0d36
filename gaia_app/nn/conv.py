"""Convolutional building blocks: residual blocks and down/up-sampling stacks (VQGAN-style U-Net halves).

Legend: b batch, c channels, h w spatial size.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint


def group_norm(channels: int) -> nn.GroupNorm:
    """GroupNorm with the largest group count ≤ 32 that divides `channels`."""
    groups = next(g for g in range(min(32, channels), 0, -1) if channels % g == 0)
    return nn.GroupNorm(groups, channels, eps=1e-6)


class ResBlock(nn.Module):
    """Pre-norm residual block: (b, c_in, h, w) → (b, c_out, h, w)."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.norm1 = group_norm(in_channels)
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, padding=1)
        self.norm2 = group_norm(out_channels)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, padding=1)
        self.skip = nn.Conv2d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h)))
        return self.skip(x) + h


def residual_stage(in_channels: int, out_channels: int, blocks: int, resample: nn.Module | None) -> nn.Sequential:
    """`blocks` ResBlocks (the first changes the width), then an optional resampling layer."""
    layers: list[nn.Module] = [ResBlock(in_channels if i == 0 else out_channels, out_channels) for i in range(blocks)]
    return nn.Sequential(*layers, *([resample] if resample is not None else []))


def downsample(channels: int) -> nn.Module:
    """Halve h and w with a strided convolution."""
    return nn.Conv2d(channels, channels, 3, stride=2, padding=1)


def upsample(channels: int) -> nn.Module:
    """Double h and w: nearest-neighbour then a convolution (no checkerboard artefacts of transposed convs)."""
    return nn.Sequential(nn.Upsample(scale_factor=2.0, mode="nearest"), nn.Conv2d(channels, channels, 3, padding=1))


class ConvEncoder(nn.Module):
    """Fully convolutional encoder: (b, c_in, h, w) → (b, c_out, h / 2^(len(mults)-1), w / 2^(len(mults)-1)).

    Args:
        channels: base width; stage i has channels * mults[i].
        mults: per-stage multipliers; each stage but the last halves the resolution.
        blocks_per_stage: residual blocks per stage.
        checkpointing: recompute each stage's activations in backward (memory for compute).
    """

    def __init__(self, in_channels: int, out_channels: int, channels: int, mults: Sequence[int], blocks_per_stage: int,
                 checkpointing: bool = False):
        super().__init__()
        self.checkpointing = checkpointing
        widths = [channels * m for m in mults]
        self.stem = nn.Conv2d(in_channels, widths[0], 3, padding=1)
        self.stages = nn.ModuleList(
            residual_stage(prev, width, blocks_per_stage, downsample(width) if i < len(widths) - 1 else None)
            for i, (prev, width) in enumerate(zip([widths[0], *widths], widths))
        )
        prev = widths[-1]
        self.mid = ResBlock(prev, prev)
        self.out = nn.Sequential(group_norm(prev), nn.SiLU(), nn.Conv2d(prev, out_channels, 3, padding=1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.stem(x)
        for stage in self.stages:
            h = run_stage(stage, h, self.checkpointing and self.training)
        return self.out(self.mid(h))


class ConvDecoder(nn.Module):
    """Mirror of ConvEncoder: (b, c_in, h, w) → (b, c_out, h·2^(len(mults)-1), w·2^(len(mults)-1))."""

    def __init__(self, in_channels: int, out_channels: int, channels: int, mults: Sequence[int], blocks_per_stage: int,
                 checkpointing: bool = False):
        super().__init__()
        self.checkpointing = checkpointing
        widths = [channels * m for m in reversed(mults)]
        self.stem = nn.Conv2d(in_channels, widths[0], 3, padding=1)
        self.mid = ResBlock(widths[0], widths[0])
        self.stages = nn.ModuleList(
            residual_stage(prev, width, blocks_per_stage, upsample(width) if i < len(widths) - 1 else None)
            for i, (prev, width) in enumerate(zip([widths[0], *widths], widths))
        )
        prev = widths[-1]
        self.out = nn.Sequential(group_norm(prev), nn.SiLU(), nn.Conv2d(prev, out_channels, 3, padding=1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.mid(self.stem(x))
        for stage in self.stages:
            h = run_stage(stage, h, self.checkpointing and self.training)
        return self.out(h)


def run_stage(stage: nn.Module, h: torch.Tensor, recompute: bool) -> torch.Tensor:
    """stage(h), optionally keeping only its input for backward and recomputing the rest (activation checkpointing)."""
    if recompute and torch.is_grad_enabled():
        return checkpoint(stage, h, use_reentrant=False)
    return stage(h)
