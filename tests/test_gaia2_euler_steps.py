"""benchmarks/gaia2_euler_steps.py (issue 51, item 2): its FVMD ratios and jackknife intervals from per-clip features,
and the reading of the fewest steps within 10 %."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import load_benchmark


def features(rng: np.random.Generator, scenes: int, shift: float) -> np.ndarray:
    bench = load_benchmark("gaia2_euler_steps")
    return rng.normal(shift, 1.0, size=(scenes * 3, bench.FEATURE_DIM))


def test_rows_further_from_the_real_features_read_higher_and_the_reference_reads_one() -> None:
    bench = load_benchmark("gaia2_euler_steps")
    rng = np.random.default_rng(0)
    real = features(rng, 40, 0.0)
    rows = {"50 steps": features(rng, 40, 0.2), "5 steps": features(rng, 40, 1.0)}
    out = bench.intervals(rows, real, cameras=3, reference="50 steps")
    assert out["50 steps"]["ratio"] == 1.0 and abs(out["50 steps"]["ratio_high"] - 1.0) < 1e-9
    assert out["5 steps"]["ratio_low"] > 1.5 and out["5 steps"]["fvmd"] > out["50 steps"]["fvmd"]
    assert out["5 steps"]["fvmd_low"] < out["5 steps"]["fvmd"] < out["5 steps"]["fvmd_high"]


def test_the_fewest_steps_within_ten_percent_by_point_and_by_interval() -> None:
    bench = load_benchmark("gaia2_euler_steps")
    rows = {"50 steps": {"ratio": 1.0, "ratio_high": 1.0}, "20 steps": {"ratio": 1.04, "ratio_high": 1.08},
            "10 steps": {"ratio": 1.08, "ratio_high": 1.2}, "5 steps": {"ratio": 1.5, "ratio_high": 1.9}}
    assert bench.fewest_within(rows, [5, 10, 20, 50]) == {"tolerance": 0.1, "point": 10, "interval": 20}


@pytest.mark.slow
def test_the_benchmark_runs_on_the_shipped_weights(tmp_path) -> None:
    bench = load_benchmark("gaia2_euler_steps")
    result = bench.euler_steps("gaia2", [3, 2], ["context.seed=7", "model.evaluate.contexts=2"],
                               tmp_path / "features.npz")
    assert result["scenes"] == 2 and result["cameras"] == 3
    assert np.load(tmp_path / "features.npz")["real"].shape == (6, bench.FEATURE_DIM)
    assert set(result["rows"]) == {"3 steps", "2 steps", "tokenized real (ceiling)", "held frame (floor)"}
    assert result["rows"]["3 steps"]["ratio"] == 1.0 and result["rows"]["2 steps"]["seconds_per_rollout"] > 0
    assert "Fewest steps within 10 %" in bench.markdown(result)
