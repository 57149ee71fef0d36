"""Seconds per generated frame of `generate.py` alone and beside another busy process, with the thread policy
(gaia_app/utils/threads.py) and with torch's default (one thread per core), side by side in one run
(docs/benchmarks.md, "Beside a busy process").

The run: `generate.py mode=action weights=gaia1` for `--seconds` of future, `--futures` futures, frames decoded by
the tokenizer. The busy process: another PyTorch job, matrix products on torch's default threads (what a second
training or generation run does), started before the run or `--late` seconds after it (the run then started alone
and must follow the load: `gaia_app.utils.threads.tick`). Each setting runs `--repeats` times, the settings
interleaved; medians.

    python benchmarks/bench_under_load.py --repeats 2
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BUSY = "import torch\nx = torch.randn(512, 512)\nwhile True:\n    x = torch.tanh(x @ x) * 0.5\n"


def generate(seconds: float, futures: int, threads: int | None, out: Path, busy_after: float | None = None) -> float:
    """Wall seconds of one generate.py run (threads None: the policy; a number: extras.num_threads), with a busy
    process started `busy_after` seconds into it (None: none)."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    command = [sys.executable, "generate.py", "mode=action", "weights=gaia1", "speed=brake", "video_decoder=false",
               f"seconds={seconds}", f"num_futures={futures}", "token_sampler.progress=false",
               "extras.print_config=false", f"hydra.run.dir={out}"]
    if threads is not None:
        command.append(f"extras.num_threads={threads}")
    start = time.perf_counter()
    run = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    busy = None
    if busy_after is not None:
        try:
            run.wait(busy_after)
        except subprocess.TimeoutExpired:
            busy = start_busy()
    try:
        _, err = run.communicate()
    finally:
        stop(busy)
    if run.returncode:
        raise SystemExit(f"generate.py failed:\n{err[-2000:]}")
    return time.perf_counter() - start


def start_busy() -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", BUSY], env={k: v for k, v in os.environ.items()
                                                               if k != "OMP_NUM_THREADS"})


def stop(busy: subprocess.Popen | None) -> None:
    if busy is not None:
        busy.kill()
        busy.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=1.0)
    parser.add_argument("--futures", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--late", type=float, default=15.0, help="seconds into the run the late busy process starts")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "bench_under_load")
    args = parser.parse_args()
    cores = os.cpu_count() or 1
    # name: (busy process: None, "before" or "late"; extras.num_threads or None for the policy)
    settings = {"alone, policy": (None, None), "beside a busy process, policy": ("before", None),
                f"busy process from {args.late:g} s in, policy": ("late", None),
                "beside a busy process, torch default threads": ("before", cores),
                f"busy process from {args.late:g} s in, torch default threads": ("late", cores),
                "alone, torch default threads": (None, cores)}
    times: dict[str, list[float]] = {name: [] for name in settings}
    for repeat in range(args.repeats):
        for i, (name, (busy_when, threads)) in enumerate(settings.items()):
            busy = start_busy() if busy_when == "before" else None
            try:
                if busy is not None:
                    time.sleep(3)  # the busy job is under way before the run counts the free CPUs
                times[name].append(generate(args.seconds, args.futures, threads, args.out / f"{repeat}_{i}",
                                            args.late if busy_when == "late" else None))
            finally:
                stop(busy)
    frames = round(args.seconds * 6.25)
    alone = statistics.median(times["alone, policy"])
    print(f"generate.py mode=action weights=gaia1, {frames} frames × {args.futures} futures, {cores} cores, "
          f"medians of {args.repeats} (process start included):")
    for name, values in times.items():
        median = statistics.median(values)
        print(f"  {name}: {median:.1f} s ({', '.join(f'{v:.1f}' for v in values)}), {median / alone:.2f}× alone")


if __name__ == "__main__":
    main()
