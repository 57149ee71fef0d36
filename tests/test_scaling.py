"""Scaling laws (GAIA-1 §6, issue 8): the power-law fit, N and C, and the `experiment=gaia1/scaling` sweep end to
end."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gaia_app.eval.scaling import (
    PowerLaw,
    extrapolation_error,
    fit_power_law,
    non_embedding_parameters,
    training_compute,
)
from gaia_app.models.gaia1.world_model import WorldModel
from tests.conftest import ROOT


def test_fit_recovers_a_known_law_and_extrapolates() -> None:
    truth = PowerLaw.from_a(1e4, -0.12, 2.0)
    compute = np.geomspace(1e7, 1e11, 6)
    loss = truth(compute) * (1 + 0.002 * np.random.default_rng(0).standard_normal(6))  # 0.2 % noise
    law = fit_power_law(compute[:-1], loss[:-1])
    assert extrapolation_error(law, compute[-1], float(truth(compute[-1]))) < 0.01
    assert law.b == pytest.approx(truth.b, rel=0.3) and law.c == pytest.approx(truth.c, rel=0.1)


def test_fit_on_exact_points_is_exact() -> None:
    truth = PowerLaw.from_a(3e3, -0.3, 1.5)
    compute = np.geomspace(1e5, 1e9, 5)
    law = fit_power_law(compute, truth(compute))
    np.testing.assert_allclose(law(compute), truth(compute), rtol=1e-3)


def test_fit_of_flat_losses_is_flat() -> None:
    law = fit_power_law([1e3, 1e4, 1e5, 1e6], [2.78, 2.78, 2.78, 2.78])
    assert float(law(1e9)) == pytest.approx(2.78, rel=1e-6)


def test_fit_rejects_too_few_or_non_positive_points() -> None:
    with pytest.raises(ValueError, match="≥ 3"):
        fit_power_law([1.0, 2.0], [3.0, 2.0])
    with pytest.raises(ValueError, match="x > 0"):
        fit_power_law([0.0, 1.0, 2.0], [3.0, 2.0, 1.0])


def test_non_embedding_parameters_are_the_transformer_blocks() -> None:
    net = WorldModel(512, 64, 3, 4, kv_heads=2, frames=2, image_tokens=20)
    blocks = sum(p.numel() for p in net.transformer.blocks.parameters())
    assert non_embedding_parameters(net, WorldModel.block_types) == blocks
    assert blocks < sum(p.numel() for p in net.parameters())  # embeddings, head, conditioner excluded
    assert training_compute(blocks, 1000) == 6 * blocks * 1000


def test_scaling_sweep_runs_fits_and_plots(tmp_path: Path) -> None:
    """4 tiny widths × 3 steps through train.py: points per job, then the law, its PNG and .rrd in the sweep dir."""
    cache = tmp_path / "tokens"
    cache.mkdir()
    tokens = (np.random.default_rng(0).integers(0, 16, size=12)[None] + np.arange(60)[:, None]) % 16
    np.save(cache / "seg.npy", tokens.reshape(60, 3, 4).astype(np.int16))
    np.save(cache / "seg.actions.npy", np.zeros((60, 2), np.float32))
    args = ["experiment=gaia1/scaling", f"data.path={cache}", "model.net.vocab_size=16", "model.net.image_tokens=12",
            "model.net.dim=8,12,16,24", "trainer.max_steps=3", "trainer.limit_val_batches=1", "data.batch_size=2",
            "logger=csv", "extras.print_config=false", f"paths.log_dir={tmp_path / 'logs'}"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "train.py", *args], cwd=ROOT, capture_output=True, text=True, env=env,
                          timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-4000:]
    (sweep,) = (tmp_path / "logs" / "gaia1_scaling").glob("multirun_*")
    points = [json.loads(p.read_text()) for p in sorted(sweep.glob("*/scaling_point.json"))]
    assert len(points) == 4
    assert [p["tokens"] for p in points] == [3 * 2 * 2 * 12] * 4  # steps × batch × frames × tokens per frame
    assert sorted(p["non_embedding_parameters"] for p in points) == [p["non_embedding_parameters"] for p in points]
    result = json.loads((sweep / "scaling_law.json").read_text())
    assert len(result["fitted"]) == 3 and len(result["held_out"]) == 1
    assert result["held_out"][0]["compute"] == max(p["compute"] for p in points)
    assert (sweep / "scaling_law.png").stat().st_size > 10_000 and (sweep / "scaling_law.rrd").stat().st_size > 0
    assert "scaling law f(C)" in done.stdout + done.stderr
