"""GAIA-1 world model on a GPU (issue 8, GAIA-1 §4.2, §5.1): training throughput and MFU, peak memory of the paper's
15 860-position sequence with and without activation checkpointing, KV-cache generation speed vs real time.

    python benchmarks/bench_gpu_world_model.py --mode throughput     # ≈350M model, bf16, SDPA (flash) attention
    python benchmarks/bench_gpu_world_model.py --mode memory         # T = 26 steps × (m 32 + n 576 + l 2) = 15 860
    python benchmarks/bench_gpu_world_model.py --mode generation     # ≈100M MHA and ≈300M GQA, 576 tokens/frame
    python benchmarks/bench_gpu_world_model.py --mode all --json     # everything, one JSON (docs/benchmarks.md)
    python benchmarks/bench_gpu_world_model.py --mode all --smoke --device cpu   # tiny sizes: checks the script runs

MFU = achieved model FLOP/s ÷ the GPU's dense bf16 peak (--peak-tflops; H100/H200 SXM: 989). Model FLOPs per
training step: 6·N·tokens for the non-embedding parameters N (GAIA-1 §6, Kaplan et al.) plus causal attention,
6·L·S·d per position (forward 2·L·S·d for QKᵀ and AV halved by causality, ×3 with backward), the PaLM accounting.
Targets (issue 8): MFU ≥ 40 %; generation ≥ 6.25 frames/s (the 6.25 Hz real-time rate) at batch 1 for ≈100M and,
with grouped-query attention, for ≈300M.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F

from gaia_app.diffusion.ar_sampling import AutoregressiveSampler, TokenPicker
from gaia_app.eval.scaling import non_embedding_parameters
from gaia_app.lit.strategies import enable_activation_checkpointing
from gaia_app.models.gaia1.world_model import WorldModel

# (dim, depth, heads, kv_heads); ≈ params of the blocks: 12·d²·depth (MHA)
SIZES = {"350M": (1024, 28, 16, None), "100M": (768, 14, 12, None), "300M_gqa": (1024, 24, 16, 4),
         "smoke": (64, 2, 4, 2)}
PAPER_LAYOUT = {"frames": 26, "text_tokens": 32, "image_tokens": 576, "action_tokens": 2, "vocab_size": 8192}
SMOKE_LAYOUT = {"frames": 3, "text_tokens": 2, "image_tokens": 12, "action_tokens": 2, "vocab_size": 64}


def build(size: str, layout: dict[str, int], frames: int, device: torch.device,
          checkpointing: bool = False) -> WorldModel:
    dim, depth, heads, kv_heads = SIZES[size]
    net = WorldModel(dim=dim, depth=depth, heads=heads, kv_heads=kv_heads, text_dim=dim,
                     **{**layout, "frames": frames}).to(device)
    if checkpointing:
        enable_activation_checkpointing(net)
    return net


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def train_step(net: WorldModel, optimizer: torch.optim.Optimizer, batch: int, device: torch.device) -> None:
    """One bf16-autocast step on random tokens: forward, next-token loss, backward, AdamW."""
    tokens = torch.randint(0, net.vocab_size, (batch, net.frames, net.n), device=device)
    cond = net.conditioner(batch, net.frames, actions=torch.zeros(batch, net.frames, 2, device=device))
    with torch.autocast(device.type, dtype=torch.bfloat16):
        logits = net(tokens, cond)
        loss = F.cross_entropy(logits.flatten(0, -2).float(), tokens.flatten())
    loss.backward()
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)


def model_flops_per_step(net: WorldModel, batch: int) -> float:
    """6·N·positions + causal attention 6·L·S·d per position (training: forward and backward)."""
    positions = net.frames * net.step_len
    n = non_embedding_parameters(net, WorldModel.block_types)
    dim, depth = net.token_embedding.embedding_dim, len(net.transformer.blocks)
    return batch * positions * (6.0 * n + 6.0 * depth * positions * dim)


def timed_steps(step: Callable[[], None], device: torch.device, warmup: int, steps: int) -> float:
    """Median seconds per call after `warmup` untimed calls."""
    for _ in range(warmup):
        step()
    times = []
    for _ in range(steps):
        synchronize(device)
        start = time.perf_counter()
        step()
        synchronize(device)
        times.append(time.perf_counter() - start)
    return sorted(times)[len(times) // 2]


def throughput(args: argparse.Namespace, device: torch.device) -> dict[str, Any]:
    size, layout = ("smoke", SMOKE_LAYOUT) if args.smoke else ("350M", PAPER_LAYOUT)
    net = build(size, layout, args.frames, device, checkpointing=args.checkpointing)
    optimizer = torch.optim.AdamW(net.parameters(), lr=1e-4, fused=device.type == "cuda")
    seconds = timed_steps(lambda: train_step(net, optimizer, args.batch, device), device, args.warmup, args.steps)
    flops = model_flops_per_step(net, args.batch)
    positions = args.batch * net.frames * net.step_len
    return {"size": size, "parameters": sum(p.numel() for p in net.parameters()),
            "non_embedding": non_embedding_parameters(net, WorldModel.block_types), "batch": args.batch,
            "sequence": net.frames * net.step_len, "seconds_per_step": seconds,
            "positions_per_second": positions / seconds,
            "model_tflops": flops / seconds / 1e12, "mfu": flops / seconds / (args.peak_tflops * 1e12)}


def peak_memory(args: argparse.Namespace, device: torch.device) -> dict[str, Any]:
    """Peak allocated memory of one training step of the paper's sequence, with and without checkpointing."""
    size, layout = ("smoke", SMOKE_LAYOUT) if args.smoke else ("350M", PAPER_LAYOUT)
    frames = layout["frames"]
    result: dict[str, Any] = {"size": size, "sequence": frames * sum(layout[k] for k in ("text_tokens", "image_tokens",
                                                                                         "action_tokens"))}
    for checkpointing in (False, True):
        net = build(size, layout, frames, device, checkpointing=checkpointing)
        optimizer = torch.optim.AdamW(net.parameters(), lr=1e-4)
        key = "checkpointing" if checkpointing else "plain"
        if device.type == "cuda":
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats(device)
        try:
            # the lambda runs before the `del` below, which pyflakes reads as a use after deletion
            seconds = timed_steps(lambda: train_step(net, optimizer, 1, device), device, 1, 1)  # noqa: F821
            peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None  # CUDA only
            result[key] = {"peak_gib": peak, "seconds_per_step": seconds}
        except torch.OutOfMemoryError:
            result[key] = {"peak_gib": "out of memory"}
        del net, optimizer
    return result


def generation(args: argparse.Namespace, device: torch.device) -> dict[str, Any]:
    """Frames/s of KV-cached greedy generation at batch 1 after a 4-frame context, bf16."""
    layout = SMOKE_LAYOUT if args.smoke else PAPER_LAYOUT
    sizes = ["smoke"] if args.smoke else ["100M", "300M_gqa", "350M"]
    result: dict[str, Any] = {"real_time_fps": 6.25, "tokens_per_frame": layout["image_tokens"]}
    for size in sizes:
        net = build(size, layout, args.context + args.generate, device).eval()
        context = torch.randint(0, net.vocab_size, (1, args.context, net.n), device=device)
        cond = net.conditioner(1, net.frames, force_drop={"text": True, "actions": True})
        sampler = AutoregressiveSampler(TokenPicker("argmax"))

        def rollout() -> None:
            with torch.no_grad(), torch.autocast(device.type, dtype=torch.bfloat16):
                sampler(net, context, cond, frames=args.generate)  # noqa: F821  (runs before the `del net` below)

        seconds = timed_steps(rollout, device, 1, args.repeats)
        result[size] = {"parameters": sum(p.numel() for p in net.parameters()),
                        "kv_heads": SIZES[size][3] or SIZES[size][2],
                        "frames_per_second": args.generate / seconds}
        del net
    return result


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--mode", choices=("throughput", "memory", "generation", "all"), default="all")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes and layout: checks the script, not the GPU")
    parser.add_argument("--frames", type=int, default=8, help="throughput: steps T per sequence (T·610 positions)")
    parser.add_argument("--batch", type=int, default=4, help="throughput: sequences per step")
    parser.add_argument("--checkpointing", action="store_true", help="throughput: with activation checkpointing")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--context", type=int, default=4, help="generation: context frames")
    parser.add_argument("--generate", type=int, default=4, help="generation: frames generated per timed rollout")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--peak-tflops", type=float, default=989.0, help="dense bf16 peak of the GPU (H100/H200 SXM)")
    parser.add_argument("--json", action="store_true")
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    device = torch.device(args.device)
    torch.manual_seed(0)
    if device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = True
    modes = {"throughput": throughput, "memory": peak_memory, "generation": generation}
    chosen = list(modes) if args.mode == "all" else [args.mode]
    results = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
               **{mode: modes[mode](args, device) for mode in chosen}}
    print(json.dumps(results, indent=2) if args.json else "\n".join(f"{k}: {v}" for k, v in results.items()))


if __name__ == "__main__":
    main()
