"""Pre-norm decoder-only transformer (GPT-2 style) shared by the GAIA world models.

Legend:
    b batch, s sequence length, d model width.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn
from torch.utils.checkpoint import checkpoint

from gaia_app.nn.attention import CausalSelfAttention, KVCache, StaticKVCache
from gaia_app.nn.rope import StepRotary


class FeedForward(nn.Module):
    """Two-layer GELU MLP, hidden width `mult`·d."""

    def __init__(self, dim: int, mult: float = 4.0, dropout: float = 0.0):
        super().__init__()
        hidden = int(dim * mult)
        self.net = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim), nn.Dropout(dropout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class TransformerBlock(nn.Module):
    """x + attn(norm(x)), then x + mlp(norm(x)). x: (b, s, d)."""

    def __init__(self, dim: int, heads: int, kv_heads: int | None = None, mlp_ratio: float = 4.0, dropout: float = 0.0):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = CausalSelfAttention(dim, heads, kv_heads, dropout)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = FeedForward(dim, mlp_ratio, dropout)

    def forward(self, x: torch.Tensor, cache: KVCache | None = None, layer: int = 0,
                rotary: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), cache, layer, rotary)
        return x + self.mlp(self.norm2(x))

    def decode_static(self, x: torch.Tensor, keys: torch.Tensor, values: torch.Tensor, slot: torch.Tensor,
                      rotary: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """One position x: (b, 1, d) against this layer's static cache (CausalSelfAttention.decode_static)."""
        x = x + self.attn.decode_static(self.norm1(x), keys, values, slot, rotary)
        return x + self.mlp(self.norm2(x))


class CausalTransformer(nn.Module):
    """Stack of causal pre-norm blocks and a final LayerNorm.

    Args:
        dim, depth, heads: width, number of blocks, query heads.
        kv_heads: key/value heads (None: = heads; fewer: grouped-query attention).
        mlp_ratio: MLP hidden width over d.
        checkpointing: recompute each block's activations in backward (training without a cache only).
        rotary: rotary time-step positions for every attention layer (gaia_app/nn/rope.py), or None.
    """

    def __init__(self, dim: int, depth: int, heads: int, kv_heads: int | None = None, mlp_ratio: float = 4.0,
                 dropout: float = 0.0, checkpointing: bool = False, rotary: StepRotary | None = None):
        super().__init__()
        self.blocks = nn.ModuleList(TransformerBlock(dim, heads, kv_heads, mlp_ratio, dropout) for _ in range(depth))
        self.norm = nn.LayerNorm(dim)
        self.checkpointing = checkpointing
        self.rotary = rotary

    def forward(self, x: torch.Tensor, cache: KVCache | None = None) -> torch.Tensor:
        """x: (b, s, d) → (b, s, d). With a cache, x holds the positions after the cached ones."""
        rotary = None
        if self.rotary is not None:
            rotary = self.rotary(cache.next_position if cache is not None else 0, x.shape[1], x.device)
        for i, block in enumerate(self.blocks):
            if self.checkpointing and self.training and cache is None:
                x = checkpoint(block, x, None, i, rotary, use_reentrant=False)
            else:
                x = block(x, cache, i, rotary)
        return self.norm(x)

    def decode_static(self, x: torch.Tensor, buffers: Sequence[tuple[torch.Tensor, torch.Tensor]], slot: torch.Tensor,
                      position: torch.Tensor) -> torch.Tensor:
        """One position x: (b, 1, d) → (b, 1, d) in fixed shapes: buffers, one (keys, values) (b, g, C, e) per layer
        (a StaticKVCache's), written in place at `slot`; slot, position: 0-dim int64 tensors, the cached positions
        and the absolute position of x (for rotary time)."""
        rotary = self.rotary.at(position) if self.rotary is not None else None
        for block, (keys, values) in zip(self.blocks, buffers, strict=True):
            x = block.decode_static(x, keys, values, slot, rotary)
        return self.norm(x)

    def static_cache(self, batch: int, capacity: int, dtype: torch.dtype, device: torch.device) -> StaticKVCache:
        """An empty StaticKVCache for `batch` sequences of up to `capacity` positions."""
        attn = self.blocks[0].attn
        return StaticKVCache(len(self.blocks), batch, attn.kv_heads, attn.head_dim, capacity, dtype, device)

    def initialize_weights(self) -> None:
        """GPT-2 init: N(0, 0.02) weights, zero biases, residual projections scaled by 1/√(2·depth) (nanoGPT)."""
        for module in self.modules():
            if isinstance(module, nn.Linear):
                nn.init.normal_(module.weight, std=0.02)
                if module.bias is not None:
                    nn.init.zeros_(module.bias)
        residual_std = 0.02 / math.sqrt(2 * len(self.blocks))
        for block in self.blocks:
            nn.init.normal_(block.attn.to_out.weight, std=residual_std)
            nn.init.normal_(block.mlp.net[2].weight, std=residual_std)
