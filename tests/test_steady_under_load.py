"""Steady under load (issue: nothing runs, nothing lost): the thread policy's precedence and arithmetic, and long
decoding stages that show progress from the inside. The side-by-side timings are a benchmark
(benchmarks/bench_under_load.py, docs/benchmarks.md "Beside a busy process"), never a timed test."""

from __future__ import annotations

import pytest
import torch

from gaia_app.utils import threads


@pytest.mark.parametrize(("quota", "busy", "expected"), [(2, 0.1, 2), (2, 1.0, 1), (2, 3.5, 1), (16, 4.4, 12),
                                                         (8, 0.0, 8), (1, 0.0, 1)])
def test_the_policy_takes_the_allowed_cpus_less_the_busy_ones(monkeypatch, quota: int, busy: float,
                                                                expected: int) -> None:
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(threads, "cpu_quota", lambda: quota)
    monkeypatch.setattr(threads, "busy_cpus", lambda: busy)
    count, why = threads.choose_threads(None)
    assert count == expected and f"{quota} CPU(s) allowed" in why


def test_a_configured_count_beats_the_environment_which_beats_the_policy(monkeypatch) -> None:
    monkeypatch.setattr(threads, "busy_cpus", lambda: 0.0)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert threads.choose_threads(5) == (5, "extras.num_threads")
    assert threads.choose_threads(None) == (3, "OMP_NUM_THREADS")
    before = torch.get_num_threads()
    try:
        assert threads.apply_thread_policy(None)[0] == 3 and torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)


def test_busy_cpus_are_measured_from_the_machine() -> None:
    assert 0.0 <= threads.busy_cpus(0.05) <= (threads.os.cpu_count() or 1) + 1e-6
    assert threads.cpu_quota() >= 1


def test_decoding_shows_each_decoder_pass_not_only_windows(capsys) -> None:
    from gaia_app.pipelines.gaia1 import Gaia1Pipeline
    from gaia_app.weights.folders import shipped_folder

    pipeline = Gaia1Pipeline.from_weights(shipped_folder("gaia1"), decoder_steps=3, decoder_sampler="ddim",
                                          decoder_blend=None)
    tokens = torch.randint(0, 1024, (1, 3, 8, 14), generator=torch.Generator().manual_seed(0))
    pipeline.decoder.decode(tokens, torch.Generator().manual_seed(0))
    err = capsys.readouterr().err
    assert "decoder pass 3" in err  # one window of 3 DDIM steps, counted as it runs


def test_the_governor_follows_load_that_appears_later(monkeypatch) -> None:
    """A run alone on 2 CPUs (2 threads); another process then keeps one CPU busy for 10 s: the next tick moves the
    run to 1 thread; when it is gone again, back to 2. Its own busy time does not count as another's."""
    tck = threads.os.sysconf("SC_CLK_TCK")
    monkeypatch.setattr(threads, "cpu_quota", lambda: 2)
    governor = threads.ThreadGovernor()
    governor.enabled = True
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        # 10 s: the machine was busy 2 × 10 CPU-seconds, this process used 10 of them → another used one CPU
        governor.mark = (0.0, (0, 0), 0.0)
        monkeypatch.setattr(governor, "sample", lambda: (10.0, (20 * tck, 0), 10.0))
        monkeypatch.setattr(threads.time, "monotonic", lambda: 10.0)
        assert governor.tick() == 1 and torch.get_num_threads() == 1
        # the next 10 s: busy 10 CPU-seconds, all of them this process's own → nobody else: 2 threads again
        monkeypatch.setattr(governor, "sample", lambda: (20.0, (40 * tck, 10 * tck), 20.0))
        monkeypatch.setattr(threads.time, "monotonic", lambda: 20.0)
        assert governor.tick() == 2 and torch.get_num_threads() == 2
        monkeypatch.setattr(threads.time, "monotonic", lambda: 21.0)
        assert governor.tick() is None  # between counts: a clock read, nothing else
    finally:
        torch.set_num_threads(before)


def test_a_configured_thread_count_is_never_moved(monkeypatch) -> None:
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    threads.apply_thread_policy(None)
    assert not threads.GOVERNOR.enabled
    threads.apply_thread_policy(2)
    assert not threads.GOVERNOR.enabled
    torch.set_num_threads(1)
