"""Streaming generation cost of the GAIA-1 world model, side by side in one run (docs/benchmarks.md, "Streaming
sampler"; issue 25, item 2).

For each trunk (random weights) this measures, after a full window of context:
  rolling     temporal_encoding=rope: every frame past the window drops the oldest step from the KV cache
  re-prefill  temporal_encoding=learned (GAIA-1 §2.1): every slide re-embeds and re-prefills the window
  full        the full-recompute reference (re-runs the window at every token), only where --full says so
as frames/s over `--frames` generated frames (every one slides the window; medians of `--repeats` alternated runs),
and the real-time ratio frames/s ÷ 6.25.
Per-token speed: the sampler's time per image token in the rolling steady state next to a gpt-fast-style GPT
(`StaticGPT`: the same trunk and rotary positions, a preallocated static KV cache written in place, attention over the
whole cache under a mask, one token per forward, greedy) over
the same number of positions, in the same process.

Trunks: `reference` = the shipped GAIA-1 reference world model's layout (d 128, 4 layers, 4/2 heads, 112 tokens per
frame, T = 12), `300M_gqa` = the paper-layout 300M-class GQA trunk (d 1024, 24 layers, 16/4 heads) with 576 tokens
per frame, at a window of --window-300m steps (T = 26 would take hours per frame on 2 cores; the slide cost per frame
does not depend on T for the rolling cache).

    python benchmarks/bench_streaming_sampler.py --trunks reference --frames 6
    python benchmarks/bench_streaming_sampler.py --trunks 300M_gqa --frames 2 --window-300m 3   # long on a CPU
    python benchmarks/bench_streaming_sampler.py --device cuda --trunks reference,300M_gqa --window-300m 26   # a GPU
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from gaia_app.diffusion.ar_sampling import AutoregressiveSampler, TokenPicker
from gaia_app.models.gaia1.world_model import WorldModel
from gaia_app.nn.rope import rotate

TRUNKS = {  # dim, depth, heads, kv_heads, image tokens, vocabulary, text tokens, window
    "reference": (128, 4, 4, 2, 112, 1024, 4, 12),
    "300M_gqa": (1024, 24, 16, 4, 576, 8192, 32, None),
}
REAL_TIME_HZ = 6.25


class StaticGPT(nn.Module):
    """A gpt-fast-style decoder over the same trunk: preallocated (b, g, max, e) caches written at `position`,
    attention of one new token against the whole cache under a mask. Shares the world model's trunk weights."""

    def __init__(self, net: WorldModel, batch: int, max_positions: int):
        super().__init__()
        self.net, self.max = net, max_positions
        attn = net.transformer.blocks[0].attn
        shape = (batch, attn.kv_heads, max_positions, attn.head_dim)
        device = net.head.weight.device
        self.caches = [(torch.zeros(shape, device=device), torch.zeros(shape, device=device))
                       for _ in net.transformer.blocks]

    def attend(self, block: nn.Module, x: torch.Tensor, layer: int, position: int, rotary: Any) -> torch.Tensor:
        attn = block.attn
        q = rearrange(attn.to_q(x), "b s (h e) -> b h s e", h=attn.heads)
        k, v = rearrange(attn.to_kv(x), "b s (two g e) -> two b g s e", two=2, g=attn.kv_heads)
        if rotary is not None:  # gpt-fast rotates queries and keys too
            q, k = rotate(q, *rotary), rotate(k, *rotary)
        keys, values = self.caches[layer]
        keys[:, :, position : position + 1] = k
        values[:, :, position : position + 1] = v
        mask = (torch.arange(self.max, device=x.device) <= position)[None]  # (1 query, max keys)
        out = F.scaled_dot_product_attention(q, keys, values, attn_mask=mask, enable_gqa=attn.kv_heads != attn.heads)
        return attn.to_out(rearrange(out, "b h s e -> b s (h e)"))

    @torch.no_grad()
    def decode_one(self, token: torch.Tensor, position: int) -> torch.Tensor:
        x = self.net.token_embedding(token)[:, None] + self.net.spatial[position % self.net.step_len]
        table = self.net.transformer.rotary
        rotary = table(position, 1, x.device) if table is not None else None
        for layer, block in enumerate(self.net.transformer.blocks):
            x = x + self.attend(block, block.norm1(x), layer, position, rotary)
            x = x + block.mlp(block.norm2(x))
        return self.net.head(self.net.transformer.norm(x))[:, -1].argmax(-1)


def build(trunk: str, window: int, encoding: str, device: torch.device) -> WorldModel:
    dim, depth, heads, kv, n, vocab, m, _ = TRUNKS[trunk]
    torch.manual_seed(0)
    return WorldModel(vocab, dim, depth, heads, kv, frames=window, text_tokens=m, image_tokens=n, text_dim=dim,
                      temporal_encoding=encoding).to(device).eval()


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def frames_per_second(net: WorldModel, frames: int, device: torch.device, use_cache: bool = True) -> float:
    """Frames/s of greedy generation of `frames` frames after a full window of context (every frame slides)."""
    b, window = 1, net.frames
    context = torch.randint(0, net.vocab_size, (b, window - 1, net.n), device=device)
    cond = net.conditioner(b, window - 1 + frames, force_drop={"text": True, "actions": True})
    sampler = AutoregressiveSampler(TokenPicker("argmax"), use_cache=use_cache)
    sampler(net, context[:, :1], cond, frames=1)  # warm-up
    sync(device)
    start = time.perf_counter()
    sampler(net, context, cond, frames=frames)
    sync(device)
    return frames / (time.perf_counter() - start)


def per_token(net: WorldModel, device: torch.device, tokens: int) -> dict[str, float]:
    """Seconds per token: the sampler's rolling steady state (a second frame past the window costs its slide and
    its n tokens: t(2 frames) − t(1 frame), over n) and StaticGPT over n positions from the same start."""
    window = net.frames
    cond = net.conditioner(1, window + 1, force_drop={"text": True, "actions": True})
    context = torch.randint(0, net.vocab_size, (1, window - 1, net.n), device=device)
    sampler = AutoregressiveSampler(TokenPicker("argmax"))
    timings = []
    for frames in (1, 2):
        sampler(net, context[:, :1], cond, frames=1)  # warm-up
        sync(device)
        start = time.perf_counter()
        sampler(net, context, cond, frames=frames)
        sync(device)
        timings.append(time.perf_counter() - start)
    sampler_token = max(timings[1] - timings[0], 1e-9) / net.n
    reference = StaticGPT(net, 1, (window + 1) * net.step_len)
    token = torch.zeros(1, dtype=torch.long, device=device)
    first = (window - 1) * net.step_len
    reference.decode_one(token, 0)  # warm-up
    sync(device)
    start = time.perf_counter()
    for position in range(first, first + tokens):
        token = reference.decode_one(token, position)
    sync(device)
    static_token = (time.perf_counter() - start) / tokens
    return {"sampler_s_per_token": sampler_token, "static_gpt_s_per_token": static_token,
            "sampler_speed_over_static_gpt": static_token / sampler_token}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trunks", default="reference")
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3, help="medians over alternated repeats")
    parser.add_argument("--window-300m", type=int, default=3)
    parser.add_argument("--full", default="", help="trunks for which the full-recompute reference runs too")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default="outputs/bench_streaming_sampler.json")
    args = parser.parse_args()
    device = torch.device(args.device)
    results: dict[str, Any] = {"device": str(device), "threads": torch.get_num_threads()}
    for trunk in args.trunks.split(","):
        window = TRUNKS[trunk][7] or args.window_300m
        row: dict[str, Any] = {"window": window}
        nets = {"rolling": build(trunk, window, "rope", device), "re-prefill": build(trunk, window, "learned", device)}
        runs: dict[str, list[float]] = {name: [] for name in nets}
        for _ in range(args.repeats):  # alternated, so both see the same machine
            for name, net in nets.items():
                runs[name].append(frames_per_second(net, args.frames, device))
        for name, rates in runs.items():
            fps = statistics.median(rates)
            row[name] = {"frames_per_s": fps, "real_time_ratio": fps / REAL_TIME_HZ, "runs": rates}
            print(f"{trunk} {name}: {fps:.3f} frames/s ({fps / REAL_TIME_HZ:.3f}× real time)")
        if trunk in args.full.split(","):
            fps = frames_per_second(build(trunk, window, "rope", device), 1, device, use_cache=False)
            row["full recompute"] = {"frames_per_s": fps, "real_time_ratio": fps / REAL_TIME_HZ}
            print(f"{trunk} full recompute: {fps:.4f} frames/s")
        row["rolling_over_re_prefill"] = row["rolling"]["frames_per_s"] / row["re-prefill"]["frames_per_s"]
        tokens = [per_token(nets["rolling"], device, TRUNKS[trunk][4]) for _ in range(args.repeats)]
        row["per_token"] = {key: statistics.median(t[key] for t in tokens) for key in tokens[0]}
        print(f"{trunk}: rolling / re-prefill {row['rolling_over_re_prefill']:.2f}×, per-token speed vs static-KV "
              f"GPT {row['per_token']['sampler_speed_over_static_gpt']:.2f}×")
        results[trunk] = row
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
