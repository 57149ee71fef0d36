"""benchmarks/gpu_gaia2_rollout.py (issue 51, item 2): the GAIA-2 rollout it times on a GPU is the report's latent
layout with the small net and the report's conditioning paths only."""

from __future__ import annotations

import torch

from tests.conftest import load_benchmark


def test_the_timed_net_has_the_reports_layout_and_no_rasters() -> None:
    bench = load_benchmark("gpu_gaia2_rollout")
    net = bench.build(dry_run=False, device=torch.device("cpu"))
    assert net.latent_channels == 64 and net.dim == 256 and len(net.blocks) == 8
    assert net.conditioner.agent_raster is None and net.conditioner.action_raster is None


def test_the_dry_run_times_every_step_count() -> None:
    bench = load_benchmark("gpu_gaia2_rollout")
    with torch.no_grad():
        result = bench.measure(dry_run=True, device=torch.device("cpu"), steps_list=(4, 2), repeats=1)
    assert list(result["rows"]) == ["4 Euler steps", "2 Euler steps"]
    assert all(row["frames_per_s"] == 4 * 8 / row["seconds"] for row in result["rows"].values())
