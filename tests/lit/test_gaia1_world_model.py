"""GAIA-1 world-model training (GAIA-1 §4.2): the experiment trains on a token cache and logs nats/token."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from gaia_app.encoders.text import LearnedTextEncoder
from gaia_app.lit.gaia1_world_model import WorldModelModule
from gaia_app.tasks.train import train
from tests.conftest import compose_config


@pytest.fixture(scope="module")
def token_cache(tmp_path_factory) -> Path:
    """One 40-step segment of 3×4 tokens (vocabulary 16) that drift by one code per step, plus actions."""
    root = tmp_path_factory.mktemp("tokens")
    base = np.random.default_rng(0).integers(0, 16, size=12)
    tokens = (base[None] + np.arange(40)[:, None]) % 16
    np.save(root / "seg.npy", tokens.reshape(40, 3, 4).astype(np.int16))
    np.save(root / "seg.actions.npy", np.random.default_rng(1).normal(size=(40, 2)).astype(np.float32))
    return root


def test_world_model_experiment_trains_and_logs_perplexity(token_cache: Path, tmp_path: Path) -> None:
    cfg = compose_config("train", [
        "experiment=gaia1/world_model_tiny", "trainer=tiny", "logger=csv", "extras.print_config=false",
        "trainer.max_steps=4", "trainer.val_check_interval=2", "trainer.limit_val_batches=1",
        f"data.path={token_cache}", "data.frame_stride=1", "model.net.vocab_size=16", "model.net.image_tokens=12",
        "model.net.dim=32",
        "model.net.depth=1", "model.net.heads=2", "model.net.kv_heads=1",
    ], tmp_path)
    assert cfg.trainer.gradient_clip_val == 1.0 and list(cfg.model.optim.betas) == [0.9, 0.95]
    out = train(cfg)
    metrics = out["trainer"].callback_metrics
    assert out["trainer"].global_step == 4
    assert math.isclose(float(metrics["val/perplexity"]), math.exp(float(metrics["val/loss"])), rel_tol=1e-4)
    assert 0 < float(metrics["train/loss"]) < 2 * math.log(16)
    # the cache has actions but no captions: the text mode is not scored
    assert {"val/loss_unconditional", "val/loss_actions"} <= set(metrics) and "val/loss_text" not in metrics


def test_text_captions_reach_the_conditioner() -> None:
    from gaia_app.models.gaia1.world_model import WorldModel

    module = WorldModelModule(lambda: WorldModel(16, 32, 1, 2, frames=2, text_tokens=3, image_tokens=4, text_dim=8),
                              optim=torch.optim.AdamW, text_encoder=lambda: LearnedTextEncoder(dim=8, tokens=3))
    module.configure_model()
    module.eval()
    tokens = torch.zeros(2, 2, 4, dtype=torch.long)
    captions = [["turn left", "stop"], [None, "red light ahead"]]
    with_text = module.conditions({"tokens": tokens, "text": captions})
    without = module.conditions({"tokens": tokens})
    assert with_text.text.shape == (2, 2, 3, 32)
    assert not torch.allclose(with_text.text, without.text)
    encoder = LearnedTextEncoder(tokens=3)
    assert encoder.ids("Turn LEFT at the junction") == [5, 2, 18]  # "at", "the" are skipped
    assert encoder.ids("It is night. It is snowing. Turning left.") == [25, 27, 5]  # prefixes: snow, turn
    assert encoder.ids("Hello there") == [1, 0, 0] and encoder.ids(None) == [0, 0, 0]


def tiny_module(**net_kw) -> WorldModelModule:
    from functools import partial

    from gaia_app.models.gaia1.world_model import WorldModel

    module = WorldModelModule(lambda: WorldModel(16, 32, 1, 2, frames=2, text_tokens=3, image_tokens=4, text_dim=8,
                                                 tie_embeddings=True, **net_kw),
                              optim=partial(torch.optim.AdamW, weight_decay=0.1),
                              text_encoder=lambda: LearnedTextEncoder(dim=8, tokens=3))
    module.configure_model()
    return module


def test_weight_decay_spares_embeddings_norms_biases_and_null_tokens() -> None:
    module = tiny_module()
    optimizer = module.configure_optimizers()
    names = {id(p): n for n, p in module.named_parameters()}
    groups = {g["weight_decay"]: {names[id(p)] for p in g["params"]} for g in optimizer.param_groups}
    decayed, spared = groups[0.1], groups[0.0]
    for name in ("net.conditioner.null_text", "net.conditioner.null_actions", "net.conditioner.action_weight",
                 "net.conditioner.action_bias", "net.token_embedding.weight", "net.temporal", "net.spatial",
                 "text_encoder.embedding.weight"):
        assert name in spared, name
    assert any(n.endswith("norm1.weight") or "norm" in n for n in spared)
    assert all(n.endswith(".weight") for n in decayed) and "net.conditioner.text_proj.weight" in decayed
    assert not any("norm" in n or "embedding" in n for n in decayed)
    # the tied head shares the embedding's tensor: one parameter, in the spared group only
    assert len(decayed) + len(spared) == len(names)


def test_validation_reports_each_trained_mode() -> None:
    module = tiny_module()
    module.eval()
    tokens = torch.randint(0, 16, (2, 2, 4))
    full = {"tokens": tokens, "actions": torch.randn(2, 2, 2) * torch.tensor([8.0, 0.03]) + torch.tensor([10.0, 0.0]),
            "text": [["It is night.", "It is night."], ["It is snowing.", None]]}
    with torch.no_grad():  # as in Lightning's validation loop
        losses = module.mode_losses(full)
        actions_only = module.mode_losses({"tokens": tokens, "actions": full["actions"]})
        bare = module.mode_losses({"tokens": tokens})
    assert set(losses) == {"unconditional", "actions", "text"}  # "both" is trained with rate 0
    assert len({round(float(v), 6) for v in losses.values()}) == 3  # each mode sees other conditions
    assert set(actions_only) == {"unconditional", "actions"} and set(bare) == {"unconditional"}


def test_init_from_starts_a_fresh_fit_from_a_checkpoints_weights(token_cache: Path, tmp_path: Path) -> None:
    """model.init_from (the reference recipe's fine-tune, step 3b) loads net and text-encoder weights before the first
    step; the run keeps its own step count and schedule, and a file that is not such a checkpoint is named."""
    from gaia_app.lit.checkpoint import load_module

    overrides = ["experiment=gaia1/world_model_tiny", "trainer=tiny", "logger=csv", "extras.print_config=false",
                 "trainer.limit_val_batches=1", f"data.path={token_cache}", "data.frame_stride=1",
                 "model.net.vocab_size=16", "model.net.image_tokens=12", "model.net.dim=32", "model.net.depth=1",
                 "model.net.heads=2", "model.net.kv_heads=1", "trainer.val_check_interval=2"]
    first = compose_config("train", [*overrides, "trainer.max_steps=2"], tmp_path / "first")
    train(first)
    parent = tmp_path / "first" / "checkpoints" / "last.ckpt"
    assert parent.is_file()
    trained = load_module(parent)
    # steps of a vanishing learning rate: what the fine-tune holds is the parent's weights
    child_cfg = compose_config("train", [*overrides, "trainer.max_steps=2", "model.optim.lr=1e-12",
                                         f"model.init_from={parent}"], tmp_path / "child")
    child = train(child_cfg)
    assert child["trainer"].global_step == 2
    for name, value in trained.state_dict().items():
        torch.testing.assert_close(child["model"].state_dict()[name], value, msg=name)
    bad = compose_config("train", [*overrides, "trainer.max_steps=1", f"model.init_from={tmp_path / 'nope.ckpt'}"],
                         tmp_path / "bad")
    with pytest.raises(FileNotFoundError, match="model.init_from=.*nope.ckpt"):
        train(bad)


def test_init_from_a_weights_folder_starts_from_its_world_model(token_cache: Path, tmp_path: Path) -> None:
    """model.init_from=<weights folder> (e.g. the shipped gaia1) fine-tunes from world_model.safetensors, with no
    training checkpoint; a folder without that component is named."""
    from gaia_app.lit.checkpoint import load_module
    from gaia_app.weights.checkpoints import read_checkpoint
    from gaia_app.weights.folders import export_component

    overrides = ["experiment=gaia1/world_model_tiny", "trainer=tiny", "logger=csv", "extras.print_config=false",
                 "trainer.limit_val_batches=1", f"data.path={token_cache}", "data.frame_stride=1",
                 "model.net.vocab_size=16", "model.net.image_tokens=12", "model.net.dim=32", "model.net.depth=1",
                 "model.net.heads=2", "model.net.kv_heads=1", "trainer.val_check_interval=2", "trainer.max_steps=2"]
    train(compose_config("train", overrides, tmp_path / "first"))
    parent = tmp_path / "first" / "checkpoints" / "last.ckpt"
    export_component(read_checkpoint(parent), tmp_path / "weights", "world_model", ["net", "text_encoder"],
                     {"rate": 6.25}, "float32")  # as mode=export writes it, in float32 to compare exactly
    child = train(compose_config("train", [*overrides, "model.optim.lr=1e-12",
                                           f"model.init_from={tmp_path / 'weights'}"], tmp_path / "child"))
    for name, value in load_module(parent).state_dict().items():  # net and learned text encoder
        torch.testing.assert_close(child["model"].state_dict()[name], value, msg=name)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="world_model"):
        train(compose_config("train", [*overrides, f"model.init_from={tmp_path / 'empty'}"], tmp_path / "bad"))
