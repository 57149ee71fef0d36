"""Issue 5 on real data: the tiny world model trained on commaVQ tokens beats both token baselines."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from gaia_app.eval.token_baselines import copy_previous_cross_entropy, model_cross_entropy, unigram_cross_entropy
from gaia_app.lit.checkpoint import load_module
from gaia_app.tasks.train import train
from tests.conftest import compose_config


def windows(dataset) -> torch.Tensor:
    return torch.stack([dataset[i]["tokens"] for i in range(len(dataset))])


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_tiny_world_model_beats_unigram_and_copy_previous(shared_data: Path, tmp_path: Path) -> None:
    """A shortened world_model_commavq run (100 of its 400 steps: its best checkpoint is the last one; 83 s on 2 cores
    of an AVX2 host, 2026-12-05)."""
    overrides = ["experiment=gaia1/world_model_commavq", f"data.path={shared_data}/commavq/tokens.npy",
                 "trainer.max_steps=100", "extras.print_config=false", "logger=none", "callbacks=model_checkpoint"]
    out = train(compose_config("train", overrides, tmp_path))
    best = sorted((tmp_path / "checkpoints").glob("best_step_*.ckpt"))
    assert len(best) == 1, best
    module = load_module(best[0]).eval()
    net, dm = module.world_model.eval(), out["datamodule"]
    train_windows, val = windows(dm.train_set), windows(dm.val_set)
    model = model_cross_entropy(lambda x: net(x, module.conditions({"tokens": x})), val)
    copy_prev, _ = copy_previous_cross_entropy(val, net.vocab_size)
    unigram = unigram_cross_entropy(train_windows, val[:, 1:], net.vocab_size)
    # measured: model 5.54 at 100 steps (≈ 5.5 at 150), copy-previous 6.18, unigram 6.76 nats/token
    assert model < copy_prev - 0.3 and model < unigram - 0.3, (model, copy_prev, unigram)
