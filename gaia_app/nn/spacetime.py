"""Space-time factorised transformer blocks shared by the GAIA-2 video tokenizer and latent world model.

Legend:
    b batch (cameras folded in where views are independent), t time steps, n tokens per step
    (h·w, or v·h·w when several cameras attend to each other), d model width, e head width.

A factorised block attends over the n tokens of each time step (spatial), then over the t steps at
each token position (temporal), then applies an MLP: cost O(t·n² + n·t²) instead of O((t·n)²)
(GAIA-2 report, world model: "a large space-time factorized transformer"). Positions come from fixed sine-cosine tables,
so one network runs at any resolution and any number of steps.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn
from torch.utils.checkpoint import checkpoint

from gaia_app.nn.transformer import FeedForward


def sincos_1d(positions: torch.Tensor, dim: int, base: float = 10_000.0) -> torch.Tensor:
    """positions (...) float → (..., dim) [sin | cos] features at geometric frequencies (Vaswani et al.)."""
    if dim % 2:
        raise ValueError(f"sincos_1d: dim={dim} must be even")
    freqs = torch.exp(-math.log(base) * torch.arange(dim // 2, device=positions.device, dtype=torch.float32)
                      / (dim // 2))
    angles = positions.float()[..., None] * freqs
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


def sincos_2d(height: int, width: int, dim: int, device: torch.device | None = None) -> torch.Tensor:
    """(h·w, dim) position table of a row-major h×w grid: half the channels encode the row, half the column."""
    rows, cols = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij")
    return sincos_2d_at(rows.flatten(), cols.flatten(), dim)


def sincos_2d_at(rows: torch.Tensor, cols: torch.Tensor, dim: int) -> torch.Tensor:
    """(..., dim) features of continuous grid positions (rows, cols of the same shape), laid out as `sincos_2d`:
    at whole positions the entries of its table, so a point can be keyed by the code its grid cells carry."""
    if dim % 4:
        raise ValueError(f"sincos_2d_at: dim={dim} must be divisible by 4")
    return torch.cat([sincos_1d(rows, dim // 2), sincos_1d(cols, dim // 2)], dim=-1)


def attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, **kwargs) -> torch.Tensor:
    """`scaled_dot_product_attention` of (b, h, s, e) heads, in float32 when bfloat16 activations sit on a CPU.

    Why: under CPU bfloat16 autocast the linear layers run on AMX/AVX512-BF16 at 3-4x the float32 rate, but SDPA's
    CPU flash kernel is slower in bfloat16 than in float32 (GAIA-2 s = 4 tokenizer step on one core: 2.06 against
    1.14 s of attention; docs/benchmarks.md, "CPU: bfloat16 autocast"). The output comes back in q's dtype.
    """
    if q.device.type != "cpu" or q.dtype != torch.bfloat16:
        return F.scaled_dot_product_attention(q, k, v, **kwargs)
    with torch.autocast("cpu", enabled=False):
        out = F.scaled_dot_product_attention(q.float(), k.float(), v.float(), **kwargs)
    return out.to(q.dtype)


class SelfAttention(nn.Module):
    """Bidirectional multi-head attention on `scaled_dot_product_attention`: x (b, s, d) → (b, s, d)."""

    def __init__(self, dim: int, heads: int, dropout: float = 0.0):
        super().__init__()
        if dim % heads:
            raise ValueError(f"SelfAttention: dim={dim} must divide by heads={heads}")
        self.heads, self.dropout = heads, dropout
        self.to_qkv = nn.Linear(dim, 3 * dim, bias=False)
        self.to_out = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        q, k, v = rearrange(self.to_qkv(x), "b s (three h e) -> three b h s e", three=3, h=self.heads)
        out = attention(q, k, v, dropout_p=self.dropout if self.training else 0.0)
        return self.to_out(rearrange(out, "b h s e -> b s (h e)"))


class SpaceTimeBlock(nn.Module):
    """Pre-norm factorised block on x (b, t, n, d): spatial attention, temporal attention, MLP.

    temporal=False skips the temporal attention (a per-step block, e.g. an image-only encoder).
    """

    def __init__(self, dim: int, heads: int, mlp_ratio: float = 4.0, dropout: float = 0.0, temporal: bool = True):
        super().__init__()
        self.norm_space = nn.LayerNorm(dim)
        self.space = SelfAttention(dim, heads, dropout)
        self.temporal = temporal
        if temporal:
            self.norm_time = nn.LayerNorm(dim)
            self.time = SelfAttention(dim, heads, dropout)
        self.norm_mlp = nn.LayerNorm(dim)
        self.mlp = FeedForward(dim, mlp_ratio, dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, t = x.shape[:2]
        spatial = rearrange(x, "b t n d -> (b t) n d")
        x = x + rearrange(self.space(self.norm_space(spatial)), "(b t) n d -> b t n d", b=b)
        if self.temporal and t > 1:
            temporal = rearrange(x, "b t n d -> (b n) t d")
            x = x + rearrange(self.time(self.norm_time(temporal)), "(b n) t d -> b t n d", b=b)
        return x + self.mlp(self.norm_mlp(x))


class SpaceTimeTransformer(nn.Module):
    """`depth` SpaceTimeBlocks and a final LayerNorm: (b, t, n, d) → (b, t, n, d).

    checkpointing: recompute each block's activations in the backward pass (memory for compute).
    """

    def __init__(self, dim: int, depth: int, heads: int, mlp_ratio: float = 4.0, dropout: float = 0.0,
                 temporal: bool = True, checkpointing: bool = False):
        super().__init__()
        self.blocks = nn.ModuleList(SpaceTimeBlock(dim, heads, mlp_ratio, dropout, temporal) for _ in range(depth))
        self.norm = nn.LayerNorm(dim)
        self.checkpointing = checkpointing
        self.initialize_weights()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for block in self.blocks:
            x = checkpoint(block, x, use_reentrant=False) if self.checkpointing and self.training else block(x)
        return self.norm(x)

    def initialize_weights(self) -> None:
        """Xavier-uniform linear weights and zero biases (ViT/DiT init)."""
        for module in self.modules():
            if isinstance(module, nn.Linear):
                nn.init.xavier_uniform_(module.weight)
                if module.bias is not None:
                    nn.init.zeros_(module.bias)


def spacetime_positions(steps: int, height: int, width: int, dim: int, device: torch.device) -> torch.Tensor:
    """(steps, h·w, dim) table: 2-D spatial sine-cosine plus a 1-D temporal one, added."""
    space = sincos_2d(height, width, dim, device)
    time = sincos_1d(torch.arange(steps, device=device), dim)
    return time[:, None, :] + space[None, :, :]


class CrossAttention(nn.Module):
    """Queries from x (B, n, d) attend to a context (B, m, d_c) where `mask` (B, m), or (B, n, m) per query, is
    True; → (B, n, d).

    Every row of `mask` must keep at least one key (conditioners always supply a null token), or SDPA
    would average over nothing.
    """

    def __init__(self, dim: int, context_dim: int, heads: int, dropout: float = 0.0):
        super().__init__()
        if dim % heads:
            raise ValueError(f"CrossAttention: dim={dim} must divide by heads={heads}")
        self.heads, self.dropout = heads, dropout
        self.to_q = nn.Linear(dim, dim, bias=False)
        self.to_kv = nn.Linear(context_dim, 2 * dim, bias=False)
        self.to_out = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, context: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        q = rearrange(self.to_q(x), "b n (h e) -> b h n e", h=self.heads)
        k, v = rearrange(self.to_kv(context), "b m (two h e) -> two b h m e", two=2, h=self.heads)
        attn_mask = mask
        if mask is not None:  # (B, m) shared by every query, or (B, n, m) one row per query; heads broadcast
            attn_mask = mask[:, None, None, :] if mask.ndim == 2 else mask[:, None]
        out = attention(q, k, v, attn_mask=attn_mask, dropout_p=self.dropout if self.training else 0.0)
        return self.to_out(rearrange(out, "b h n e -> b n (h e)"))


def modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """AdaLN: x (b, t, n, d) · (1 + scale) + shift, with shift/scale (b, t, d) per time step."""
    return x * (1 + scale[:, :, None]) + shift[:, :, None]


class AdaLNSpaceTimeBlock(nn.Module):
    """Factorised block on x (b, t, n, d), modulated per time step by c (b, t, d) and reading a context.

        x += g₁ · SpatialAttn(AdaLN₁(x))          over the n tokens of a step (every camera's)
        x += CrossAttn(LN(x), context[b, t])       condition tokens of that step (agents, metadata, text, …)
        x += g₂ · TemporalAttn(AdaLN₂(x))         over the t steps of each token position
        x += g₃ · MLP(AdaLN₃(x))
    AdaLN(x) = LN(x)·(1 + scale) + shift with (shift, scale, gate) per sub-layer from a linear map of c,
    zero-initialised ("adaLN-Zero", DiT): every block starts as the identity (GAIA-2 report: AdaLN for
    ego action and flow time τ, cross-attention for the other conditions).
    """

    def __init__(self, dim: int, heads: int, context_dim: int, mlp_ratio: float = 4.0, dropout: float = 0.0):
        super().__init__()
        self.norm_space = nn.LayerNorm(dim, elementwise_affine=False)
        self.space = SelfAttention(dim, heads, dropout)
        self.norm_cross = nn.LayerNorm(dim)
        self.cross = CrossAttention(dim, context_dim, heads, dropout)
        self.norm_time = nn.LayerNorm(dim, elementwise_affine=False)
        self.time = SelfAttention(dim, heads, dropout)
        self.norm_mlp = nn.LayerNorm(dim, elementwise_affine=False)
        self.mlp = FeedForward(dim, mlp_ratio, dropout)
        self.modulation = nn.Sequential(nn.SiLU(), nn.Linear(dim, 9 * dim))
        nn.init.zeros_(self.modulation[-1].weight)
        nn.init.zeros_(self.modulation[-1].bias)

    def forward(self, x: torch.Tensor, c: torch.Tensor, context: torch.Tensor, context_mask: torch.Tensor | None = None,
                query_position: torch.Tensor | None = None) -> torch.Tensor:
        """x (b, t, n, d); c (b, t, d); context (b, t, m, d_c); context_mask (b, t, m) or, per token, (b, t, n, m)
        bool, or None;
        query_position (b or 1, 1, n, d) or None: a code added to the cross-attention's queries only (DETR adds its
        positional codes to the queries and keys of every attention layer, never to the values)."""
        b, t = x.shape[:2]
        shift1, scale1, gate1, shift2, scale2, gate2, shift3, scale3, gate3 = self.modulation(c).chunk(9, dim=-1)
        spatial = rearrange(modulate(self.norm_space(x), shift1, scale1), "b t n d -> (b t) n d")
        x = x + gate1[:, :, None] * rearrange(self.space(spatial), "(b t) n d -> b t n d", b=b)
        queries = self.norm_cross(x)
        if query_position is not None:
            queries = queries + query_position
        queries = rearrange(queries, "b t n d -> (b t) n d")
        mask = None if context_mask is None else rearrange(context_mask, "b t ... m -> (b t) ... m")
        cross = self.cross(queries, rearrange(context, "b t m d -> (b t) m d"), mask)
        x = x + rearrange(cross, "(b t) n d -> b t n d", b=b)
        if t > 1:
            temporal = rearrange(modulate(self.norm_time(x), shift2, scale2), "b t n d -> (b n) t d")
            x = x + gate2[:, :, None] * rearrange(self.time(temporal), "(b n) t d -> b t n d", b=b)
        return x + gate3[:, :, None] * self.mlp(modulate(self.norm_mlp(x), shift3, scale3))
