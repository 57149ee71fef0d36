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
            values = torch.cat([values[:, :, begin:end],
                                values.new_empty(*values.shape[:2], size - live, values.shape[3])], 2)
            self.buffers[layer], begin, end = (keys, values), 0, live
        keys[:, :, end : end + s] = k
        values[:, :, end : end + s] = v
        self.begin[layer], self.end[layer] = begin, end + s
        return keys[:, :, begin : end + s], values[:, :, begin : end + s]


class StaticKVCache(KVCache):
    """A KVCache whose buffers never move, for a fixed-shape (graph-captured) decode step.

    Every layer's keys and values (b, g, capacity, e) are allocated up front and kept for the cache's whole life
    (`reset` empties it for the next session), so a captured graph can read and write them at fixed addresses.
    The live positions always start at slot 0: `drop_front` shifts them forward in place (one copy per layer per
    slide; a frame then decodes n tokens, so the copy is small next to them), which keeps the keys in the order an
    eager KVCache holds them. It never grows: an append beyond `capacity` is a ValueError naming both sizes.
    Eager appends (`update`, e.g. a prefill) and the captured step's in-place writes (`CausalSelfAttention.
    decode_static`, followed by `advance`) share the buffers.
    """

    def __init__(self, layers: int, batch: int, kv_heads: int, head_dim: int, capacity: int,
                 dtype: torch.dtype, device: torch.device) -> None:
        super().__init__(capacity)
        shape = (batch, kv_heads, capacity, head_dim)
        # zeros, not empty: masked slots still enter SDPA's products (times 0), and stale NaNs would poison them
        self.buffers = [(torch.zeros(shape, dtype=dtype, device=device), torch.zeros(shape, dtype=dtype, device=device))
                        for _ in range(layers)]
        self.begin, self.end = [0] * layers, [0] * layers

    def reset(self) -> None:
        """Forget every position (the buffers stay where they are)."""
        self.begin, self.end, self.offset = [0] * len(self.buffers), [0] * len(self.buffers), 0

    def drop_front(self, count: int) -> None:
        """Forget the `count` oldest positions in every layer, moving the others to the front in place."""
        if count > self.length:
            raise ValueError(f"cannot drop {count} positions from a cache of {self.length}")
        for layer, (keys, values) in enumerate(self.buffers):
            end = self.end[layer]
            for buffer in (keys, values):  # source and target overlap: copy through a temporary
                buffer[:, :, : end - count] = buffer[:, :, count:end].clone()
            self.end[layer] = end - count
        self.offset += count

    def advance(self, count: int) -> None:
        """Count `count` positions the captured step wrote in place (at slot `length`) in every layer."""
        if self.length + count > self.capacity:
            raise ValueError(f"static KV cache: {self.length} + {count} positions exceed its capacity of "
                             f"{self.capacity}")
        self.end = [e + count for e in self.end]

    def update(self, layer: int, k: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Append (b, g, s, e) keys/values of `layer` in place; return the live ones (b, g, p + s, e)."""
        keys, values = self.buffers[layer]
        end, s = self.end[layer], k.shape[2]
        if end + s > self.capacity:
            raise ValueError(f"static KV cache: {end} + {s} positions exceed its capacity of {self.capacity}")
        if k.shape[:2] != keys.shape[:2] or k.dtype != keys.dtype:
            raise ValueError(f"static KV cache holds {tuple(keys.shape)} {keys.dtype}, got keys {tuple(k.shape)} "
                             f"{k.dtype}")
        keys[:, :, end : end + s] = k
        values[:, :, end : end + s] = v
        self.end[layer] = end + s
        return keys[:, :, : end + s], values[:, :, : end + s]


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

    def attention_probs(self, x: torch.Tensor, queries: torch.Tensor,
                        rotary: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """The attention probabilities (b, h, k, s) that a causal forward of x (b, s, d) gives the query positions
        `queries` (k,) int64, zero on the positions each query cannot see; for diagnosis
        (gaia_app/eval/action_signal.py). Materialises (b, h, k, s): pass a few hundred queries at a time."""
        b, s, _ = x.shape
        q = self.to_q(x).view(b, s, self.heads, self.head_dim).transpose(1, 2)
        k, _ = self.to_kv(x).view(b, s, 2, self.kv_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        if rotary is not None:
            q, k = rotate(q, *rotary), rotate(k, *rotary)
        k = k.repeat_interleave(self.heads // self.kv_heads, dim=1)  # (b, h, s, e)
        scores = q[:, :, queries] @ k.transpose(-1, -2) / self.head_dim ** 0.5  # (b, h, k, s)
        hidden = torch.arange(s, device=x.device)[None] > queries[:, None]  # (k, s): keys after the query
        return scores.masked_fill(hidden, float("-inf")).softmax(dim=-1)

    def value_writes(self, x: torch.Tensor) -> torch.Tensor:
        """What each position's value adds to the residual stream through `to_out`, per query head: (b, h, s, d),
        so that Σ_heads Σ_j attention_probs[..., j, None] · writes[:, :, j] is the attention output at a query."""
        b, s, _ = x.shape
        _, v = self.to_kv(x).view(b, s, 2, self.kv_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        v = v.repeat_interleave(self.heads // self.kv_heads, dim=1)  # (b, h, s, e)
        # to_out acts on heads concatenated along d: head i's slice of its weight maps that head's values
        return torch.einsum("bhse,dhe->bhsd", v, self.to_out.weight.view(-1, self.heads, self.head_dim))

    def decode_static(self, x: torch.Tensor, keys: torch.Tensor, values: torch.Tensor, slot: torch.Tensor,
                      rotary: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """One new position x: (b, 1, d) → (b, 1, d) against a static cache, in fixed shapes (graph-capturable).

        keys, values: (b, g, C, e) buffers of a StaticKVCache; slot: 0-dim int64 tensor, the positions cached before
        this one. The new key/value is written in place at `slot`; the query attends to all C slots with those after
        `slot` masked, so neither the shapes nor the addresses change from token to token (gpt-fast's decode step).
        """
        b = x.shape[0]
        q = self.to_q(x).view(b, 1, self.heads, self.head_dim).transpose(1, 2)  # (b, h, 1, e)
        k, v = self.to_kv(x).view(b, 1, 2, self.kv_heads, self.head_dim).permute(2, 0, 3, 1, 4)  # (b, g, 1, e) each
        if rotary is not None:
            q, k = rotate(q, *rotary), rotate(k, *rotary)
        index = slot.view(1)
        keys[:, :, index] = k  # index_put_: stays in place when compiled (the cache is never copied)
        values[:, :, index] = v
        # one query: two small matmuls and a softmax, which the compiler fuses; SDPA's CPU flash kernel, tiled for
        # many queries, cost 95 µs a call here, a third of the compiled step (docs/benchmarks.md, issue 51 item 4)
        q = q.reshape(b, self.kv_heads, self.heads // self.kv_heads, self.head_dim)  # (b, g, r, e): r heads per K/V
        scores = (q @ keys.transpose(-1, -2)) * self.head_dim ** -0.5  # (b, g, r, C)
        hidden = torch.arange(keys.shape[2], device=x.device) > slot  # (C,) slots not written yet
        # softmax in float32 as SDPA's kernels do inside, so that a bfloat16 net keeps eager's rounding
        probs = scores.masked_fill(hidden, float("-inf")).softmax(dim=-1, dtype=torch.float32).to(values.dtype)
        out = probs @ values  # (b, g, r, e)
        return self.to_out(out.reshape(b, 1, -1))
