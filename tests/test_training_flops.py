"""benchmarks/training_flops.py (issue 50): training compute per budget, read off a weights folder's net."""

from __future__ import annotations

import argparse

import pytest

from tests.conftest import load_benchmark


@pytest.fixture(scope="module")
def training_flops():
    return load_benchmark("training_flops")


def test_flops_follow_the_nets_shape_and_the_windows_trained(training_flops) -> None:
    one, many = (training_flops.run_flops(training_flops.parse_run(f"shipped=gaia1:{s}")) for s in ("10x2", "40x4"))
    positions = 12 * (4 + 112 + 2)  # the shipped layout: 12 steps of text, image and action tokens
    assert one["positions"] == positions and one["windows"] == 20
    dim, depth, n = 128, 4, one["non_embedding_parameters"]
    assert 0.5e6 < n < 1e6
    assert one["flops"] == pytest.approx(20 * positions * (6 * n + 6 * depth * positions * dim))
    assert many["flops"] == pytest.approx(8 * one["flops"])
    assert "| 8.0 |" in training_flops.table([one, many])


@pytest.mark.parametrize("text", ["gaia1", "x=gaia1:10", "x=gaia1:10x", "=gaia1:1x1"])
def test_a_malformed_run_names_the_expected_form(training_flops, text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match="expected NAME=<weights folder>:<steps>x<windows per step>"):
        training_flops.parse_run(text)
