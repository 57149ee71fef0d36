"""The GPU checks of issue 51 (item 5) in one run of at most ~8 minutes on one CUDA GPU (docs/gpu_speed.md).

    python benchmarks/gpu_checks.py --out $OUT/gpu          # on the GPU machine
    python benchmarks/gpu_checks.py --out /tmp/gpu --dry-run   # tiny sizes on a CPU: checks that the script runs

Checks, in this order, each with its own time budget (seconds; a check past it is stopped and marked "timeout"):
  bandwidth         the card's HBM bandwidth: from a table by name (H100 SXM 3.35e12, H200 4.8e12 B/s), else a
                    measured device-to-device copy (always measured and recorded too)
  generation_100M   frames/s at batch 1, 576 tokens per frame (18×32), bf16 weights, top-k 50: eager vs the
  generation_300M   compiled (CUDA-graph captured) decode step, for the ≈100M MHA and ≈300M GQA trunks of
                    bench_gpu_world_model.py; with the memory-bandwidth roofline fraction: (weight + KV bytes read per
                    token) ÷ bandwidth ÷ measured seconds per token
  futures_16        aggregate tokens/s of 16 futures in one batch (the ≈300M GQA trunk), eager vs compiled
  training_mfu      the ≈350M world model's training MFU: bf16 autocast, fused AdamW, SDPA, torch.compile of the blocks
                    (bench_gpu_world_model.py's model FLOPs), against the card's dense bf16 peak
  gaia2_rollout     GAIA-2: frames/s of a 3-camera rollout at the report's latent layout (64 × 14 × 30 per camera)
                    with a small random net (256 × 8), at 50, 20, 10 and 5 Euler steps (gpu_gaia2_rollout.py)
  strategies        train.py with trainer=fsdp, fsdp2 and deepspeed_zero2 on one GPU: 20 steps of the GAIA-1 world
                    model, then a resume from its checkpoint to step 30 (gpu_strategies.py; the dry run: fsdp2 on
                    one CPU process, 4 + 2 steps). Needs hydra-core, omegaconf and, for DeepSpeed, deepspeed there
After every check (and every row of one) DIR/gpu_checks.json and DIR/gpu_checks.md are rewritten, so a run cut short
still returns what it measured. They record the card's name, the torch and CUDA versions and the date. Without CUDA
(and without --dry-run) the script refuses in one line, within its first seconds.
"""

from __future__ import annotations

import argparse
import datetime
import json
import signal
import statistics
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_gpu_world_model as base  # noqa: E402  (its sizes, layouts, train step and model FLOPs)
import gpu_strategies  # noqa: E402  (train.py with trainer=fsdp / fsdp2 / deepspeed_zero2, then a resume)

from gaia_app.diffusion.ar_sampling import AutoregressiveSampler, TokenPicker  # noqa: E402
from gaia_app.models.gaia1.world_model import WorldModel  # noqa: E402

BANDWIDTH = (("H200", 4.8e12), ("H100 80GB HBM3", 3.35e12), ("H100 SXM", 3.35e12))  # name contains → bytes/s
PEAK_BF16_TFLOPS = (("H200", 989.0), ("H100 80GB HBM3", 989.0), ("H100 SXM", 989.0), ("H100", 756.0), ("A100", 312.0))
# seconds per check; the whole run stays under --budget-s
BUDGETS = {"bandwidth": 10, "generation_100M": 80, "generation_300M": 80, "futures_16": 55, "training_mfu": 85,
           "gaia2_rollout": 30, "strategies": 140}


class CheckTimeout(Exception):
    """A check ran past its budget."""


class Report:
    """Results so far, rewritten to DIR as JSON and Markdown at every `save`."""

    def __init__(self, out: Path, meta: dict[str, Any]):
        self.out, self.data = out, {"meta": meta, "checks": {}}
        out.mkdir(parents=True, exist_ok=True)

    def save(self, name: str, result: dict[str, Any]) -> None:
        self.data["checks"][name] = result
        (self.out / "gpu_checks.json").write_text(json.dumps(self.data, indent=2, default=str))
        (self.out / "gpu_checks.md").write_text(markdown(self.data))


def markdown(data: dict[str, Any]) -> str:
    meta = data["meta"]
    lines = [f"# GPU checks ({meta['date']})", "", f"{meta['device']}, torch {meta['torch']}, CUDA {meta['cuda']}"
             f"{', DRY RUN (tiny sizes on CPU)' if meta['dry_run'] else ''}", "",
             "| check | row | frames / s | tokens / s (all rollouts) | ms / decode step | roofline fraction | other |",
             "|---|---|---|---|---|---|---|"]
    for name, result in data["checks"].items():
        rows = result.get("rows", {})
        other = {k: v for k, v in result.items() if k != "rows" and not isinstance(v, dict)}
        if not rows:
            lines.append(f"| {name} | | | | | | {fmt(other)} |")
        for row, r in rows.items():
            lines.append(f"| {name} | {row} | {num(r.get('frames_per_s'))} | {num(r.get('tokens_per_s'))} | "
                         f"{num(r.get('ms_per_step'))} | {num(r.get('roofline_fraction'))} | "
                         f"{fmt({k: v for k, v in r.items() if k not in ROW_COLUMNS})} |")
        if rows and other:
            lines.append(f"| {name} | (check) | | | | | {fmt(other)} |")
    return "\n".join(lines) + "\n"


ROW_COLUMNS = ("frames_per_s", "tokens_per_s", "ms_per_step", "roofline_fraction", "frame_seconds")


def num(value: Any) -> str:
    return "" if value is None else f"{value:.3g}" if isinstance(value, float) else str(value)


def fmt(values: dict[str, Any]) -> str:
    return "; ".join(f"{k} {num(v)}" for k, v in values.items())


def lookup(table: tuple[tuple[str, float], ...], name: str) -> float | None:
    return next((value for key, value in table if key in name), None)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def on_timeout(signum: int, frame: Any) -> None:
    raise CheckTimeout


Check = Callable[[Callable[[dict], None]], dict[str, Any]]  # given a `save` for partial results → the result


def run_check(report: Report, name: str, check: Check, budget: float) -> None:
    """Run one check under a wall-clock budget (SIGALRM); record its result, a timeout or its error."""
    partial: dict[str, Any] = {"status": "running", "budget_s": round(budget)}

    def save(update: dict[str, Any]) -> None:  # rows as they come, so a timeout keeps them
        partial.update(update)
        report.save(name, partial)

    save({})
    start = time.perf_counter()
    signal.setitimer(signal.ITIMER_REAL, max(budget, 1.0))
    try:
        partial.update(check(save))
        partial["status"] = "ok"
    except CheckTimeout:
        partial["status"] = "timeout"
    except Exception as error:  # noqa: BLE001 — record it and go on to the next check
        partial.update(status="error", error=f"{type(error).__name__}: {error}"[:500],
                       trace=traceback.format_exc(limit=4)[-1500:])
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
    partial["seconds"] = round(time.perf_counter() - start, 1)
    report.save(name, partial)
    print(f"{name}: {partial['status']} in {partial['seconds']} s", flush=True)
    torch._dynamo.reset()  # drop the check's compiled graphs and their CUDA-graph pools
    if torch.cuda.is_available():
        torch.cuda.empty_cache()


def measure_bandwidth(device: torch.device, megabytes: int) -> float:
    """Bytes/s of a large device-to-device copy (each byte read once and written once)."""
    x = torch.empty(megabytes * 2**20, dtype=torch.uint8, device=device)
    y = torch.empty_like(x)
    y.copy_(x)
    sync(device)
    times = []
    for _ in range(5):
        start = time.perf_counter()
        y.copy_(x)
        sync(device)
        times.append(time.perf_counter() - start)
    return 2 * x.numel() / statistics.median(times)


def bandwidth_check(args: argparse.Namespace, device: torch.device, name: str) -> dict[str, Any]:
    measured = measure_bandwidth(device, 16 if args.dry_run else 2048)
    listed = lookup(BANDWIDTH, name)
    return {"listed_bytes_per_s": listed, "measured_copy_bytes_per_s": measured,
            "used_bytes_per_s": listed or measured, "source": "table" if listed else "measured copy"}


def weight_bytes(net: WorldModel) -> int:
    """Bytes of the weights one decoded token reads: every block, the final norm and the head (one embedding row)."""
    skip = ("token_embedding", "conditioner", "spatial", "temporal")
    return sum(p.numel() * p.element_size() for name, p in net.named_parameters() if not name.startswith(skip))


def kv_bytes_per_position(net: WorldModel, rows: int) -> int:
    attn = net.transformer.blocks[0].attn
    return 2 * len(net.transformer.blocks) * rows * attn.kv_heads * attn.head_dim * net.head.weight.element_size()


def decode_rows(net: WorldModel, batch: int, rows: list[str], frames: dict[str, int], args: argparse.Namespace,
                device: torch.device, bandwidth: float, save: Callable[[dict], None]) -> dict[str, Any]:
    """Frames/s of `batch` rollouts per decode step (after a `args.context`-frame context and one untimed frame:
    the prefill, the compile and the capture), with the roofline fraction of the bytes each token reads."""
    out: dict[str, Any] = {}
    context = torch.randint(0, net.vocab_size, (batch, args.context, net.n), device=device)
    cond = net.conditioner(batch, net.frames, force_drop={"text": True, "actions": True})
    for row in rows:
        decode_step = "static" if args.dry_run and row == "compiled" else row  # no inductor build in a dry run
        per_call = args.tokens_per_call if decode_step != "eager" else 1
        sampler = AutoregressiveSampler(TokenPicker("top_k", k=50), decode_step=decode_step, tokens_per_call=per_call)
        session = sampler.session(net, context, cond, generator=torch.Generator(device).manual_seed(0))
        session.next_frame()
        filled = session.stream.cache.length
        times = []
        for _ in range(frames[row]):
            sync(device)
            start = time.perf_counter()
            session.next_frame()
            sync(device)
            times.append(time.perf_counter() - start)
        seconds = statistics.median(times)
        cache = session.stream.cache
        # the eager step reads the live keys (their mean count while timed), the fixed-shape one its whole capacity
        positions = cache.capacity if decode_step != "eager" else (filled + cache.length) / 2
        read = weight_bytes(net) + kv_bytes_per_position(net, batch) * positions
        per_step = seconds / net.n  # one decode step: one token of every rollout in the batch
        out[row] = {"frames_per_s": 1 / seconds, "tokens_per_s": batch * net.n / seconds, "ms_per_step": 1e3 * per_step,
                    "roofline_fraction": read / bandwidth / per_step, "bytes_per_step": read,
                    "frame_seconds": times, "decode_step": decode_step, "tokens_per_call": per_call,
                    "fell_back": sampler.steps.failure if sampler.steps is not None else None}
        save({"rows": dict(out)})
    if "eager" in out and "compiled" in out:
        out["compiled"]["speedup_over_eager"] = out["eager"]["ms_per_step"] / out["compiled"]["ms_per_step"]
    return out


def generation_check(size: str, batch: int, args: argparse.Namespace, device: torch.device,
                     report_meta: dict[str, Any]) -> Check:
    def check(save: Callable[[dict], None]) -> dict[str, Any]:
        layout = base.SMOKE_LAYOUT if args.dry_run else base.PAPER_LAYOUT
        trunk = "smoke" if args.dry_run else size
        window = args.context + 2 + max(args.eager_frames, args.compiled_frames)  # no slide while timing
        net = base.build(trunk, layout, window, device).to(torch.bfloat16).eval()
        save({"trunk": trunk, "parameters": sum(p.numel() for p in net.parameters()), "batch": batch,
              "kv_heads": base.SIZES[trunk][3] or base.SIZES[trunk][2], "tokens_per_frame": net.n, "window": window,
              "picker": "top_k 50", "dtype": "bfloat16"})
        frames = {"eager": args.eager_frames, "compiled": args.compiled_frames}
        if report_meta["bandwidth_bytes_per_s"] is None:  # the bandwidth check did not run: a quick copy
            report_meta["bandwidth_bytes_per_s"] = measure_bandwidth(device, 16 if args.dry_run else 1024)
        rows = decode_rows(net, batch, ["eager", "compiled"], frames, args, device,
                           report_meta["bandwidth_bytes_per_s"], save)
        return {"rows": rows}
    return check


def training_check(args: argparse.Namespace, device: torch.device, peak_tflops: float) -> Check:
    def check(save: Callable[[dict], None]) -> dict[str, Any]:
        size, layout = ("smoke", base.SMOKE_LAYOUT) if args.dry_run else ("350M", base.PAPER_LAYOUT)
        net = base.build(size, layout, args.train_frames, device)
        if not args.dry_run:
            for block in net.transformer.blocks:  # one compiled graph, shared by the identical blocks
                block.compile()
        optimizer = torch.optim.AdamW(net.parameters(), lr=1e-4, fused=device.type == "cuda")
        save({"size": size, "batch": args.train_batch, "sequence": net.frames * net.step_len,
              "compiled_blocks": not args.dry_run, "peak_tflops": peak_tflops})
        seconds = base.timed_steps(lambda: base.train_step(net, optimizer, args.train_batch, device), device,
                                   1 if args.dry_run else 3, 1 if args.dry_run else 6)
        flops = base.model_flops_per_step(net, args.train_batch)
        return {"seconds_per_step": seconds, "model_tflops": flops / seconds / 1e12,
                "mfu": flops / seconds / (peak_tflops * 1e12),
                "positions_per_s": args.train_batch * net.frames * net.step_len / seconds}
    return check


def gaia2_rollout_check(args: argparse.Namespace, device: torch.device) -> Check:
    def check(save: Callable[[dict], None]) -> dict[str, Any]:
        import gpu_gaia2_rollout  # here: its hydra / lightning imports must not stop the other checks

        return gpu_gaia2_rollout.measure(args.dry_run, device, save=save)
    return check


def strategies_check(args: argparse.Namespace) -> Check:
    def check(save: Callable[[dict], None]) -> dict[str, Any]:
        budget = max(signal.getitimer(signal.ITIMER_REAL)[0] - 3.0, 1.0)  # end the processes before the alarm
        strategies = ["fsdp2"] if args.dry_run else list(gpu_strategies.STRATEGIES)
        steps, more = (4, 2) if args.dry_run else (20, 10)
        return gpu_strategies.run_all(Path(args.out) / "strategies", strategies, steps, more, budget, args.dry_run,
                                      save)
    return check


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="folder for gpu_checks.json and gpu_checks.md")
    parser.add_argument("--dry-run", action="store_true", help="tiny sizes on the CPU (checks the script, not a GPU)")
    parser.add_argument("--budget-s", type=float, default=480.0, help="the whole run's wall-clock budget")
    parser.add_argument("--checks", default=",".join(BUDGETS), help="comma-separated subset, in this order")
    parser.add_argument("--context", type=int, default=4, help="generation: context frames")
    parser.add_argument("--eager-frames", type=int, default=2, help="generation: timed frames of the eager row")
    parser.add_argument("--compiled-frames", type=int, default=4, help="generation: timed frames of the compiled row")
    parser.add_argument("--tokens-per-call", type=int, default=1,
                        help="generation: image tokens per call (per graph replay) of the compiled row")
    parser.add_argument("--train-frames", type=int, default=8, help="training: steps T per sequence (T·610 positions)")
    parser.add_argument("--train-batch", type=int, default=4)
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    started = time.perf_counter()
    if not args.dry_run and not torch.cuda.is_available():
        print(f"gpu_checks: no CUDA device (torch {torch.__version__}); run it on a GPU, or add --dry-run for tiny "
              "sizes on this CPU", file=sys.stderr)
        sys.exit(2)
    device = torch.device("cuda" if torch.cuda.is_available() and not args.dry_run else "cpu")
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    if device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = True
    torch.manual_seed(0)
    meta = {"device": name, "torch": torch.__version__, "cuda": torch.version.cuda, "dry_run": args.dry_run,
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "argv": sys.argv[1:], "bandwidth_bytes_per_s": lookup(BANDWIDTH, name)}
    print(f"gpu_checks: {name}, torch {torch.__version__}, CUDA {torch.version.cuda}; writing to {args.out}",
          flush=True)
    report = Report(Path(args.out), meta)
    signal.signal(signal.SIGALRM, on_timeout)
    peak = lookup(PEAK_BF16_TFLOPS, name) or 989.0
    checks = {
        "bandwidth": lambda save: bandwidth_check(args, device, name),
        "generation_100M": generation_check("100M", 1, args, device, meta),
        "generation_300M": generation_check("300M_gqa", 1, args, device, meta),
        "futures_16": generation_check("300M_gqa", 16, args, device, meta),
        "training_mfu": training_check(args, device, peak),
        "gaia2_rollout": gaia2_rollout_check(args, device),
        "strategies": strategies_check(args),
    }
    for key in args.checks.split(","):
        left = args.budget_s - (time.perf_counter() - started)
        if left < 10:
            report.save(key, {"status": "skipped: the run's budget is spent"})
            continue
        run_check(report, key, checks[key], min(BUDGETS[key], left))
        if key == "bandwidth":
            meta["bandwidth_bytes_per_s"] = report.data["checks"][key].get("used_bytes_per_s")
    report.save("total", {"status": "ok", "seconds": round(time.perf_counter() - started, 1)})
    print((Path(args.out) / "gpu_checks.md").read_text())


if __name__ == "__main__":
    main()
