"""How many CPU threads a run uses: what its CPU quota allows, less what other processes keep busy.

PyTorch's default is one OpenMP thread per core. Beside another busy process on the same cores that means more
threads than cores, and each parallel region then waits for a thread the scheduler has parked elsewhere: measured
on 2 cores, `generate.py mode=controllability weights=gaia1` took 60–80 s per frame beside one busy process
against 8–20 s with one thread (docs/benchmarks.md, "Beside a busy process"). So a run counts the CPUs it may use
(affinity mask and cgroup quota, as containers and SLURM set them) and subtracts what other processes keep busy
(the machine's CPU use sampled for a quarter second at start), keeping at least one.

Load that appears later matters as much: a second job started beside a running one turns the first one's idle
OpenMP threads into spinning ones (12 s instead of 0.3 s for the same loop of small products, measured). So while
a run under the policy works, `tick()` (called once per generated frame, decoder window, solver step and training
step) re-counts, at most every `INTERVAL_S` (3) seconds and without sleeping, the CPUs other processes used since the
last count (the machine's busy time from /proc/stat less this process's own) and moves torch's thread count to
what is free.

Precedence: `extras.num_threads` (a config value) > `OMP_NUM_THREADS` in the environment (the user chose) > this
policy. The choice is logged with its reason.
"""

from __future__ import annotations

import logging
import math
import os
import time
from pathlib import Path

log = logging.getLogger(__name__)
INTERVAL_S = 3.0


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
    """Set torch's intra-op threads by `choose_threads` and, when the policy (not a setting) chose them, let
    `tick()` follow the load from now on; returns (threads, why)."""
    import torch

    threads, why = choose_threads(configured)
    torch.set_num_threads(threads)
    GOVERNOR.start(enabled=why not in ("extras.num_threads", "OMP_NUM_THREADS"))
    return threads, why


class ThreadGovernor:
    """Moves torch's thread count with the load other processes put on this run's CPUs (module docstring)."""

    def __init__(self) -> None:
        self.enabled = False
        self.mark: tuple[float, tuple[int, int], float] | None = None

    def start(self, enabled: bool = True) -> None:
        self.enabled = enabled and Path("/proc/stat").is_file()
        self.mark = self.sample() if self.enabled else None

    @staticmethod
    def sample() -> tuple[float, tuple[int, int], float]:
        """(wall time, machine (all, idle) jiffies, this process's CPU seconds)."""
        times = os.times()
        return time.monotonic(), cpu_times(), times.user + times.system

    def tick(self, interval_s: float = INTERVAL_S) -> int | None:
        """Re-count at most every `interval_s`; returns the new thread count when it changed."""
        if not self.enabled or self.mark is None or time.monotonic() - self.mark[0] < interval_s:
            return None
        import torch

        now = self.sample()
        wall = now[0] - self.mark[0]
        if wall <= 0:
            return None
        (all0, idle0), (all1, idle1) = self.mark[1], now[1]
        machine_busy = ((all1 - all0) - (idle1 - idle0)) / os.sysconf("SC_CLK_TCK")  # CPU seconds
        others = max(0.0, (machine_busy - (now[2] - self.mark[2])) / wall)
        self.mark = now
        quota = cpu_quota()
        threads = max(1, min(quota, math.floor(quota - others + 0.5)))
        if threads == torch.get_num_threads():
            return None
        log.info("CPU threads: %d (other processes kept %.1f of %d CPU(s) busy over the last %.0f s)", threads,
                 others, quota, wall)
        torch.set_num_threads(threads)
        return threads


GOVERNOR = ThreadGovernor()


def tick() -> None:
    """Let the thread count follow the load (cheap: a clock read between counts). Call from the main thread: torch's
    thread count is per thread."""
    GOVERNOR.tick()
