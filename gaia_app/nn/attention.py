"""Causal self-attention on `scaled_dot_product_attention`, with grouped-query heads and a KV cache.

Legend:
    b batch, s query length, p cached (past) length, d model width, h query heads, g key/value heads
    (h % g == 0; g < h is grouped-query attention), e head width (d / h).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from gaia_app.nn.rope import rotate


class KVCache:
    """Keys and values of the positions already decoded, one (k, v) pair per layer.

    Each layer appends its new keys/values (b, g, s, e) during a forward; `length` is the number of
    cached positions. Data only: decoding state lives in this object, never in the network or the sampler.

    capacity: positions to preallocate per layer (a static cache, as gpt-fast keeps one): new keys are written in
    place and layers read views, so a token costs no copy of the cache. Without it (or beyond it) the cache grows by
    concatenation. `drop_front` forgets the oldest positions (a sliding window with relative positions); `offset`
    counts them, so `next_position` stays absolute.
    """

    def __init__(self, capacity: int | None = None) -> None:
        self.capacity = capacity
        self.buffers: list[tuple[torch.Tensor, torch.Tensor]] = []
        self.begin, self.end = [], []  # per layer: the live slice of its buffers
        self.offset = 0

    @property
    def length(self) -> int:
        """Positions cached in the last layer (every layer, between forwards)."""
        return self.end[-1] - self.begin[-1] if self.buffers else 0

    @property
    def next_position(self) -> int:
        """The absolute position of the next token, counting dropped positions."""
        return self.offset + self.length

    def past(self, layer: int) -> int:
        """Positions cached in `layer` before this forward appends to it."""
        return self.end[layer] - self.begin[layer] if layer < len(self.buffers) else 0

    def drop_front(self, count: int) -> None:
        """Forget the `count` oldest positions in every layer."""
        if count > self.length:
            raise ValueError(f"cannot drop {count} positions from a cache of {self.length}")
        self.begin = [b + count for b in self.begin]
        self.offset += count

    def update(self, layer: int, k: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Append (b, g, s, e) keys/values of `layer`; return all of them (b, g, p + s, e)."""
        s = k.shape[2]
        if layer == len(self.buffers):
            size = max(self.capacity or 0, s)
            keys, values = k.new_empty(*k.shape[:2], size, k.shape[3]), v.new_empty(*v.shape[:2], size, v.shape[3])
            self.buffers.append((keys, values))
            self.begin.append(0)
            self.end.append(0)
        keys, values = self.buffers[layer]
        begin, end = self.begin[layer], self.end[layer]
        if end + s > keys.shape[2]:  # full: move the live part to the front, grow if it still does not fit
            live = end - begin
            size = max(keys.shape[2], live + s)
            keys = torch.cat([keys[:, :, begin:end], keys.new_empty(*keys.shape[:2], size - live, keys.shape[3])], 2)
            values = torch.cat([values[:, :, begin:end], values.new_empty(*values.shape[:2], size - live, values.shape[3])], 2)
            self.buffers[layer], begin, end = (keys, values), 0, live
        keys[:, :, end : end + s] = k
        values[:, :, end : end + s] = v
        self.begin[layer], self.end[layer] = begin, end + s
        return keys[:, :, begin : end + s], values[:, :, begin : end + s]


def causal_mask(queries: int, past: int, device: torch.device) -> torch.Tensor:
    """(s, p + s) bool, True where query i (at absolute position p + i) may attend to key j."""
    q = torch.arange(queries, device=device)[:, None] + past
    k = torch.arange(past + queries, device=device)[None, :]
    return k <= q


class CausalSelfAttention(nn.Module):
    """Multi-head causal self-attention; `kv_heads < heads` shares each K/V head among a query group.

    Fewer K/V heads shrink the KV cache and its memory traffic, which dominate incremental decoding.
    """

    def __init__(self, dim: int, heads: int, kv_heads: int | None = None, dropout: float = 0.0):
        super().__init__()
        kv_heads = kv_heads or heads
        if dim % heads or heads % kv_heads:
            raise ValueError(f"dim={dim} must divide by heads={heads}, and heads by kv_heads={kv_heads}")
        self.heads, self.kv_heads, self.head_dim = heads, kv_heads, dim // heads
        self.to_q = nn.Linear(dim, dim, bias=False)
        self.to_kv = nn.Linear(dim, 2 * kv_heads * self.head_dim, bias=False)
        self.to_out = nn.Linear(dim, dim, bias=False)
        self.dropout = dropout

    def forward(self, x: torch.Tensor, cache: KVCache | None = None, layer: int = 0,
                rotary: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """x: (b, s, d) → (b, s, d); with a cache, x holds the positions after the cached ones. rotary: cos, sin
        (s, e) of x's positions (gaia_app/nn/rope.py), applied to queries and keys before the keys are cached."""
        # view/transpose rather than einops: this runs once per layer for every sampled token, where einops'
        # per-call parsing is a tenth of the step on a small model
        b, s, _ = x.shape
        q = self.to_q(x).view(b, s, self.heads, self.head_dim).transpose(1, 2)  # (b, h, s, e)
        k, v = self.to_kv(x).view(b, s, 2, self.kv_heads, self.head_dim).permute(2, 0, 3, 1, 4)  # (b, g, s, e) each
        if rotary is not None:
            q, k = rotate(q, *rotary), rotate(k, *rotary)
        past = cache.past(layer) if cache is not None else 0
        if cache is not None:
            k, v = cache.update(layer, k, v)
        # grouped-query: SDPA lets each K/V head serve heads / kv_heads query heads without copying the keys
        gqa = {"enable_gqa": True} if self.kv_heads != self.heads else {}
        dropout = self.dropout if self.training else 0.0
        if past == 0:  # plain causal mask: lets SDPA pick its flash/efficient kernel
            out = F.scaled_dot_product_attention(q, k, v, dropout_p=dropout, is_causal=True, **gqa)
        elif x.shape[1] == 1:  # one new token sees every cached position
            out = F.scaled_dot_product_attention(q, k, v, dropout_p=dropout, **gqa)
        else:
            mask = causal_mask(x.shape[1], past, x.device)
            out = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=dropout, **gqa)
        return self.to_out(out.transpose(1, 2).reshape(b, s, -1))
