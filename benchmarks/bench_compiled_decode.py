"""Per-token decode time of the GAIA-1 sampler: eager vs the fixed-shape step, uncompiled and compiled, side by side
(issue 51, item 4; docs/gpu_speed.md).

Rows (`AutoregressiveSampler(decode_step=...)`, gaia_app/diffusion/compiled_decode.py):
  eager     the per-token eager loop on the growing KV cache (the default)
  static    the fixed-shape step (static KV cache, attention over the whole capacity under a mask), uncompiled
  compiled  the same step under torch.compile (inductor on a CPU; CUDA graphs on a GPU)
Each round opens one session per row on the same context, decodes one untimed frame (the prefill; the compile, the
first time), then times `--frames` frames: seconds ÷ (frames · n). The rows alternate within every round, so each
sees the same machine load; medians over `--repeats` rounds. The trunk is the shipped GAIA-1 reference layout
(d 128, 4 layers, 4/2 heads, 112 tokens per frame, T = 12, 1024 codes; random weights) unless --size says otherwise.

    OMP_NUM_THREADS=1 python benchmarks/bench_compiled_decode.py                 # reference layout, top-k 50
    OMP_NUM_THREADS=1 python benchmarks/bench_compiled_decode.py --guided --json outputs/bench_compiled_decode.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Any

import torch

from gaia_app.diffusion.ar_sampling import AutoregressiveSampler, TokenPicker
from gaia_app.diffusion.guidance import ClassifierFreeGuidance
from gaia_app.models.gaia1.world_model import WorldModel

SIZES = {  # dim, depth, heads, kv_heads, image tokens, vocabulary, text tokens, window T
    "reference": (128, 4, 4, 2, 112, 1024, 4, 12),
    "small": (64, 2, 4, 2, 24, 256, 2, 6),
}
ROWS = ("eager", "static", "compiled")


def build(size: str, device: torch.device) -> WorldModel:
    dim, depth, heads, kv, n, vocab, m, window = SIZES[size]
    torch.manual_seed(0)
    return WorldModel(vocab, dim, depth, heads, kv, frames=window, text_tokens=m, image_tokens=n, text_dim=dim,
                      ).to(device).eval()


def seconds_per_token(net: WorldModel, sampler: AutoregressiveSampler, args: argparse.Namespace,
                      device: torch.device) -> float:
    """One session: `args.context` context frames, one untimed frame, then `args.frames` timed frames."""
    steps = args.context + 1 + args.frames
    context = torch.randint(0, net.vocab_size, (args.batch, args.context, net.n), device=device,
                            generator=torch.Generator(device).manual_seed(1))
    cond = net.conditioner(args.batch, steps, force_drop={"text": True, "actions": True})
    guidance = ClassifierFreeGuidance(2.0) if args.guided else None
    uncond = cond if args.guided else None
    session = sampler.session(net, context, cond, uncond, guidance, torch.Generator(device).manual_seed(2))
    session.next_frame()
    sync(device)
    start = time.perf_counter()
    for _ in range(args.frames):
        session.next_frame()
    sync(device)
    return (time.perf_counter() - start) / (args.frames * net.n)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def table(result: dict[str, Any]) -> str:
    eager = result["rows"].get("eager", next(iter(result["rows"].values())))["ms_per_token"]
    lines = ["| decode step | ms / token (median) | tokens / s | speed-up over eager | runs (ms / token) |",
             "|---|---|---|---|---|"]
    for name, row in result["rows"].items():
        runs = ", ".join(f"{1e3 * r:.2f}" for r in row["runs_s"])
        lines.append(f"| {name} | {row['ms_per_token']:.3f} | {1e3 / row['ms_per_token']:.0f} | "
                     f"{eager / row['ms_per_token']:.2f}× | {runs} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", choices=tuple(SIZES), default="reference")
    parser.add_argument("--rows", default=",".join(ROWS), help="comma-separated subset of eager,static,compiled")
    parser.add_argument("--context", type=int, default=6, help="context frames (< T: no slide while timing)")
    parser.add_argument("--frames", type=int, default=2, help="timed frames per session")
    parser.add_argument("--repeats", type=int, default=5, help="rounds; medians over them")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--guided", action="store_true", help="classifier-free guidance (two streams per row)")
    parser.add_argument("--top-k", type=int, default=50)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json", help="also write the results to this JSON file")
    args = parser.parse_args()
    device, rows = torch.device(args.device), args.rows.split(",")
    net = build(args.size, device)
    if args.context + 2 + args.frames > net.frames:
        parser.error(f"--context + --frames + 2 must stay within the window of {net.frames} steps")
    samplers = {row: AutoregressiveSampler(TokenPicker("top_k", k=args.top_k), decode_step=row) for row in rows}
    runs: dict[str, list[float]] = {row: [] for row in rows}
    for _ in range(args.repeats):  # alternated: every row sees the same load
        for row, sampler in samplers.items():
            runs[row].append(seconds_per_token(net, sampler, args, device))
    result = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
              "threads": torch.get_num_threads(), "torch": torch.__version__, "size": args.size,
              "layout": dict(zip(("dim", "depth", "heads", "kv_heads", "n", "vocab", "m", "window"), SIZES[args.size])),
              "batch": args.batch, "guided": args.guided, "top_k": args.top_k, "context": args.context,
              "frames": args.frames, "repeats": args.repeats,
              "compiled_fell_back": samplers.get("compiled") is not None and samplers["compiled"].steps.failure,
              "rows": {row: {"ms_per_token": 1e3 * statistics.median(r), "runs_s": r} for row, r in runs.items()}}
    print(table(result))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
