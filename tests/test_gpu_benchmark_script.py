"""benchmarks/bench_gpu_world_model.py runs its three measurements at smoke size on CPU (the GPU numbers come from
a GPU machine; this keeps the commands in docs/benchmarks.md ready to run)."""

from __future__ import annotations

import argparse
import importlib.util

import pytest
import torch

from tests.conftest import ROOT


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_gpu_world_model",
                                                  ROOT / "benchmarks" / "bench_gpu_world_model.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def smoke_args(**overrides) -> argparse.Namespace:
    args = dict(smoke=True, frames=2, batch=2, checkpointing=False, warmup=1, steps=1, context=2, generate=1, repeats=1,
                peak_tflops=1.0)
    return argparse.Namespace(**{**args, **overrides})


def test_throughput_counts_model_flops(bench) -> None:
    result = bench.throughput(smoke_args(), torch.device("cpu"))
    assert result["sequence"] == 2 * (2 + 12 + 2) and result["positions_per_second"] > 0
    net = bench.build("smoke", bench.SMOKE_LAYOUT, 2, torch.device("cpu"))
    n = result["non_embedding"]
    attention = 6 * 2 * result["sequence"] * 64  # 6·L·S·d per position, L = 2 blocks, d = 64
    assert bench.model_flops_per_step(net, 2) == 2 * result["sequence"] * (6 * n + attention)
    assert result["mfu"] == pytest.approx(result["model_tflops"] / 1.0)


def test_memory_runs_with_and_without_checkpointing(bench) -> None:
    result = bench.peak_memory(smoke_args(), torch.device("cpu"))
    assert result["sequence"] == 3 * 16
    assert result["plain"]["seconds_per_step"] > 0 and result["checkpointing"]["seconds_per_step"] > 0


def test_generation_reports_frames_per_second(bench) -> None:
    result = bench.generation(smoke_args(), torch.device("cpu"))
    assert result["real_time_fps"] == 6.25 and result["smoke"]["frames_per_second"] > 0
    assert result["smoke"]["kv_heads"] == 2
