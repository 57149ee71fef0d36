"""How many CPU threads a run uses: what its CPU quota allows, less what other processes keep busy.

PyTorch's default is one OpenMP thread per core. Beside another busy process on the same cores that means more
threads than cores, and each parallel region then waits for a thread the scheduler has parked elsewhere: measured
on 2 cores, `generate.py mode=controllability weights=gaia1` took 60–80 s per frame beside one busy process
against 8–20 s with one thread (docs/benchmarks.md, "Beside a busy process"). So a run counts the CPUs it may use
(affinity mask and cgroup quota, as containers and SLURM set them) and subtracts what other processes keep busy
(the machine's CPU use sampled for a quarter second at start), keeping at least one.

Precedence: `extras.num_threads` (a config value) > `OMP_NUM_THREADS` in the environment (the user chose) > this
policy. The choice is logged with its reason.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path


def cpu_quota() -> int:
    """CPUs this process may run on: its affinity mask, capped by a cgroup v2 `cpu.max` quota when one is set."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    limit = Path("/sys/fs/cgroup/cpu.max")
    try:
        quota, period = limit.read_text().split()[:2]
        if quota != "max":
            cpus = min(cpus, max(1, math.floor(int(quota) / int(period))))
    except (OSError, ValueError):
        pass
    return max(1, cpus)


def busy_cpus(sample_s: float = 0.25) -> float:
    """CPUs kept busy by other processes now: the machine's non-idle share over `sample_s` seconds (/proc/stat)
    times its CPU count, while this process sleeps; the 1-minute load average where /proc is missing (it lags:
    a job that ended a minute ago still counts)."""
    try:
        first = cpu_times()
        time.sleep(sample_s)
        second = cpu_times()
    except (OSError, ValueError, IndexError):
        try:
            return os.getloadavg()[0]
        except (AttributeError, OSError):
            return 0.0
    total, idle = second[0] - first[0], second[1] - first[1]
    return 0.0 if total <= 0 else (total - idle) / total * (os.cpu_count() or 1)


def cpu_times() -> tuple[int, int]:
    """(all, idle + iowait) jiffies of the machine since boot, from /proc/stat's `cpu` line."""
    fields = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    return sum(fields[:8]), fields[3] + fields[4]


def choose_threads(configured: int | None = None) -> tuple[int, str]:
    """(threads, why) under the module docstring's precedence."""
    if configured:
        return int(configured), "extras.num_threads"
    from_env = os.environ.get("OMP_NUM_THREADS", "").strip()
    if from_env.isdigit() and int(from_env) > 0:
        return int(from_env), "OMP_NUM_THREADS"
    quota, busy = cpu_quota(), busy_cpus()
    free = max(1, min(quota, math.floor(quota - busy + 0.5)))
    return free, f"{quota} CPU(s) allowed, {busy:.1f} busy with other processes"


def apply_thread_policy(configured: int | None = None) -> tuple[int, str]:
    """Set torch's intra-op threads by `choose_threads`; returns (threads, why)."""
    import torch

    threads, why = choose_threads(configured)
    torch.set_num_threads(threads)
    return threads, why
