"""Issue 51, item 3: `trainer=fsdp`, `trainer=fsdp2` and `trainer=deepspeed_zero2` each train the GAIA-1 world model
for `--steps` steps on one GPU through train.py, then resume from their own `checkpoints/last.ckpt` for `--more`
(docs/distributed.md). A check of `benchmarks/gpu_checks.py` ("strategies"), or on its own:

    python benchmarks/gpu_strategies.py --out $OUT/strategies                 # on the GPU machine
    python benchmarks/gpu_strategies.py --out /tmp/strategies --dry-run       # fsdp2 on one CPU process (gloo)

The world model trains on a token cache written here: 4 segments of 80 steps of 8 × 14 tokens (vocabulary 1 024,
the shipped GAIA-1 layout) drifting one code per step, with random actions; width 256, depth 4, T = 4, batch 8. Each
strategy is two `train.py` processes in one run dir: `trainer.max_steps=S` with a checkpoint every S/2 steps, then
`ckpt_path=last trainer.max_steps=S+M`. It passes when both exit 0, the second log says it resumed from the first's
checkpoint and both report the step they were asked to reach ("trained to step N").
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
STRATEGIES = ("fsdp", "fsdp2", "deepspeed_zero2")
GRID, VOCABULARY = (8, 14), 1024
STEP = re.compile(r"trained to step (\d+)")


def write_token_cache(root: Path, segments: int = 4, steps: int = 80, seed: int = 0) -> Path:
    """`segments` token segments (steps, 8, 14) int16 with (steps, 2) actions, as the token cache reads them."""
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for index in range(segments):
        start = rng.integers(0, VOCABULARY, size=GRID[0] * GRID[1])
        tokens = (start[None] + np.arange(steps)[:, None]) % VOCABULARY
        np.save(root / f"seg{index}.npy", tokens.reshape(steps, *GRID).astype(np.int16))
        np.save(root / f"seg{index}.actions.npy", rng.normal(size=(steps, 2)).astype(np.float32))
    return root


def overrides(strategy: str, cache: Path, run_dir: Path, max_steps: int, every: int, dry_run: bool) -> list[str]:
    """train.py arguments: the world model on the cache, one device, checkpoints every `every` steps."""
    device = ["trainer.accelerator=cpu", "trainer.precision=32-true"] if dry_run else []
    if dry_run and strategy == "fsdp2":
        device.append("trainer.strategy.param_dtype=null")  # FSDP2's own bf16 policy: fp32 on the CPU
    width = ["model.net.dim=32", "model.net.depth=2", "model.net.heads=2", "model.net.kv_heads=1"] if dry_run else \
        ["model.net.dim=256", "model.net.depth=4", "model.net.heads=4", "model.net.kv_heads=2"]
    return ["experiment=gaia1/world_model_tiny", f"trainer={strategy}", "trainer.devices=1", *device,
            f"trainer.max_steps={max_steps}", f"trainer.val_check_interval={every}", "trainer.limit_val_batches=1",
            "+trainer.num_sanity_val_steps=0", f"callbacks.model_checkpoint.every_n_train_steps={every}",
            f"data.path={cache}", "data.frame_stride=1", "data.batch_size=2" if dry_run else "data.batch_size=8",
            f"model.net.vocab_size={VOCABULARY}", f"model.net.image_tokens={GRID[0] * GRID[1]}", *width,
            "callbacks.rerun_media=null", "extras.print_config=false", f"hydra.run.dir={run_dir}"]


def run_train(args: list[str], timeout: float) -> dict[str, Any]:
    """One train.py process: exit code, seconds, the step it reached and the end of its log."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    start = time.perf_counter()
    try:
        done = subprocess.run([sys.executable, "train.py", *args], cwd=ROOT, capture_output=True, text=True,
                              env=env, timeout=max(timeout, 1.0))
        code, log = done.returncode, done.stdout + done.stderr
    except subprocess.TimeoutExpired as expired:
        code = None
        log = "".join(part.decode() if isinstance(part, bytes) else (part or "")
                      for part in (expired.stdout, expired.stderr)) + f"\n(stopped after {timeout:.0f} s)"
    steps = [int(found) for found in STEP.findall(log)]
    return {"returncode": code, "seconds": round(time.perf_counter() - start, 1),
            "step": steps[-1] if steps else None, "resumed": "resuming from" in log, "log_tail": log[-1500:]}


def check_strategy(strategy: str, cache: Path, out: Path, steps: int, more: int, timeout: float,
                   dry_run: bool) -> dict[str, Any]:
    """Train `steps`, then resume to `steps + more` in the same run dir; `timeout` seconds for both."""
    run_dir = out / strategy
    every = max(1, steps // 2)
    started = time.perf_counter()
    first = run_train(overrides(strategy, cache, run_dir, steps, every, dry_run), timeout / 2)
    result: dict[str, Any] = {"train": first}
    if first["returncode"] == 0:
        left = timeout - (time.perf_counter() - started)
        result["resume"] = run_train([*overrides(strategy, cache, run_dir, steps + more, every, dry_run),
                                      "ckpt_path=last"], left)
    last = run_dir / "checkpoints" / "last.ckpt"
    result["checkpoint"] = "folder" if last.is_dir() else "file" if last.is_file() else None
    second = result.get("resume", {})
    result["status"] = "ok" if (first["step"] == steps and second.get("returncode") == 0 and second.get("resumed")
                                and second.get("step") == steps + more) else "failed"
    return result


def summary(row: dict[str, Any]) -> dict[str, Any]:
    """One table row of a strategy's check: status, seconds, steps reached, the checkpoint's kind, and the last
    line of the failing process's log."""
    first, second = row["train"], row.get("resume", {})
    failed = next((run for run in (first, second) if run and run.get("returncode") != 0), None)
    last_line = failed["log_tail"].strip().splitlines()[-1][:200] if failed and failed["log_tail"].strip() else None
    return {"status": row["status"], "train_s": first["seconds"], "resume_s": second.get("seconds"),
            "steps": f"{first['step']} → {second.get('step')}", "checkpoint": row["checkpoint"],
            "error": last_line}


def run_all(out: Path, strategies: list[str], steps: int, more: int, budget: float, dry_run: bool,
            save=None) -> dict[str, Any]:
    """Every strategy in turn, each with an equal share of what is left of `budget`; `save(result)` after each.
    `rows` holds one summary per strategy, `logs` both processes' details."""
    started = time.perf_counter()
    cache = write_token_cache(out / "tokens")
    result: dict[str, Any] = {"rows": {}, "logs": {}, "steps": steps, "more": more}
    for index, strategy in enumerate(strategies):
        left = budget - (time.perf_counter() - started)
        row = check_strategy(strategy, cache, out, steps, more, left / (len(strategies) - index), dry_run)
        result["rows"][strategy], result["logs"][strategy] = summary(row), row
        result["passed"] = sum(r["status"] == "ok" for r in result["rows"].values())
        print(f"strategies: {strategy} {row['status']}", flush=True)
        if save is not None:
            save(result)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--dry-run", action="store_true", help="fsdp2 only, on one CPU process")
    parser.add_argument("--strategies", default=None, help=f"comma-separated (default: {','.join(STRATEGIES)})")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--more", type=int, default=10)
    parser.add_argument("--budget-s", type=float, default=150.0)
    args = parser.parse_args()
    strategies = (args.strategies or ("fsdp2" if args.dry_run else ",".join(STRATEGIES))).split(",")
    out = Path(args.out)
    result = run_all(out, strategies, args.steps, args.more, args.budget_s, args.dry_run)
    (out / "strategies.json").write_text(json.dumps(result, indent=2))
    for strategy, row in result["rows"].items():
        print(f"{strategy}: {row}")


if __name__ == "__main__":
    main()
