"""benchmarks/gpu_strategies.py (issue 51, item 3) and what its dry run found: an FSDP2 run whose parameters did not
all get gradients could not resume, because its checkpoint lacked their optimizer state
(gaia_app/lit/strategies.py:fill_missing_optimizer_state)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from gaia_app.lit.strategies import fill_missing_optimizer_state
from tests.conftest import load_benchmark


@pytest.mark.parametrize("fused", [False, True])
def test_parameters_without_state_get_one_and_nothing_else_moves(fused: bool) -> None:
    torch.manual_seed(0)
    used, unused = nn.Linear(3, 3), nn.Linear(3, 3)
    optimizer = torch.optim.AdamW([*used.parameters(), *unused.parameters()], lr=1e-2, weight_decay=0.1,
                                  fused=fused)
    used(torch.randn(4, 3)).sum().backward()
    optimizer.step()
    before = {name: p.detach().clone() for name, p in [*used.named_parameters("used"),
                                                        *unused.named_parameters("unused")]}
    state_before = {k: v.clone() for k, v in optimizer.state[used.weight].items()}
    grad = used.weight.grad.clone()
    assert fill_missing_optimizer_state(optimizer) == 2  # the unused layer's weight and bias
    assert all(p in optimizer.state for p in [*used.parameters(), *unused.parameters()])
    after = dict([*used.named_parameters("used"), *unused.named_parameters("unused")])
    assert all(torch.equal(before[name], after[name]) for name in before)  # no weight moved, decay included
    assert all(torch.equal(state_before[k], optimizer.state[used.weight][k]) for k in state_before)
    assert torch.equal(used.weight.grad, grad) and unused.weight.grad is None
    assert optimizer.param_groups[0]["lr"] == 1e-2
    assert torch.count_nonzero(optimizer.state[unused.weight]["exp_avg"]) == 0
    assert float(optimizer.state[unused.weight]["step"]) == 0  # as lazily created: the first update is a first one
    assert fill_missing_optimizer_state(optimizer) == 0


def test_a_filled_state_gives_the_same_first_update_as_none() -> None:
    """A parameter whose state was filled takes, at its first gradient, the step an untouched one takes."""
    torch.manual_seed(0)
    layers = [nn.Linear(3, 3) for _ in range(2)]
    layers[1].load_state_dict(layers[0].state_dict())
    optimizers = [torch.optim.AdamW(layer.parameters(), lr=1e-2, weight_decay=0.1) for layer in layers]
    fill_missing_optimizer_state(optimizers[1])
    x = torch.randn(4, 3)
    for layer, optimizer in zip(layers, optimizers):
        layer(x).sum().backward()
        optimizer.step()
    assert all(torch.allclose(a, b) for a, b in zip(layers[0].parameters(), layers[1].parameters()))


def test_filling_inside_inference_mode_leaves_trainable_state() -> None:
    layer = nn.Linear(3, 3)
    optimizer = torch.optim.AdamW(layer.parameters(), lr=1e-2)
    with torch.inference_mode():
        fill_missing_optimizer_state(optimizer)
    assert not optimizer.state[layer.weight]["exp_avg"].is_inference()
    layer(torch.randn(2, 3)).sum().backward()
    optimizer.step()  # would raise on inference tensors


def test_the_token_cache_has_the_shipped_layout(tmp_path: Path) -> None:
    bench = load_benchmark("gpu_strategies")
    cache = bench.write_token_cache(tmp_path, segments=2, steps=10)
    tokens = np.load(cache / "seg0.npy")
    assert tokens.shape == (10, 8, 14) and tokens.dtype == np.int16 and tokens.max() < 1024
    assert np.load(cache / "seg1.actions.npy").shape == (10, 2)
    args = bench.overrides("deepspeed_zero2", cache, tmp_path / "run", 20, 10, dry_run=False)
    assert "trainer=deepspeed_zero2" in args and "trainer.devices=1" in args and "trainer.max_steps=20" in args


@pytest.mark.rehearsal
def test_the_dry_run_trains_and_resumes_fsdp2_on_one_cpu_process(tmp_path: Path) -> None:
    bench = load_benchmark("gpu_strategies")
    result = bench.run_all(tmp_path, ["fsdp2"], steps=4, more=2, budget=280, dry_run=True)
    row, logs = result["rows"]["fsdp2"], result["logs"]["fsdp2"]
    assert row["status"] == "ok", logs
    assert logs["train"]["step"] == 4 and logs["resume"]["step"] == 6 and logs["resume"]["resumed"]
    assert row["steps"] == "4 → 6" and row["checkpoint"] == "folder" and row["error"] is None
    assert result["passed"] == 1
