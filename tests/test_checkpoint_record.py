"""Checkpoints say which nets they hold (gaia_app/weights/nets.py, NETS_RECORD): written at training time by the
LightningModule, read back by every loader, so no loader names a LightningModule class."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from gaia_app.weights.nets import LEGACY_RECORDS, NETS_RECORD, checkpoint_nets
from tests.conftest import tampered


def test_a_training_checkpoint_records_its_component_and_prefixes(genuine: Path) -> None:
    checkpoint = torch.load(genuine, weights_only=True)
    assert checkpoint[NETS_RECORD] == {"component": "tokenizer", "prefixes": {"net": "net."}}
    loaded = checkpoint_nets(genuine, "tokenizer", role="ckpt")
    assert loaded.component == "tokenizer" and set(loaded.nets) == {"net"}


def test_the_record_decides_and_a_forged_one_is_refused(genuine: Path, tmp_path: Path) -> None:
    as_world_model = tampered(genuine, tmp_path, lambda c: c.update({NETS_RECORD: {
        "component": "world_model", "prefixes": {"net": "net."}}}))
    with pytest.raises(TypeError, match=r"ckpt=.* holds a world_model \(ImageTokenizerModule\) checkpoint, "
                                        "expected a tokenizer checkpoint"):
        checkpoint_nets(as_world_model, "tokenizer", role="ckpt")
    for record in ({"component": "bogus", "prefixes": {"net": "net."}}, {"component": "tokenizer", "prefixes": {}},
                   {"component": "tokenizer", "prefixes": {"discriminator": "disc."}}, "tokenizer"):
        forged = tampered(genuine, tmp_path, lambda c, r=record: c.update({NETS_RECORD: r}))
        with pytest.raises(ValueError, match=f"{NETS_RECORD}=.* is not a record of its nets"):
            checkpoint_nets(forged, "tokenizer", role="ckpt")
    wrong_prefix = tampered(genuine, tmp_path, lambda c: c.update({NETS_RECORD: {
        "component": "tokenizer", "prefixes": {"net": "discriminator."}}}))
    with pytest.raises(ValueError, match="the tensors under 'discriminator.' do not fit"):
        checkpoint_nets(wrong_prefix, "tokenizer", role="ckpt")


def test_a_checkpoint_written_before_the_record_still_loads(genuine: Path, tmp_path: Path) -> None:
    legacy = tampered(genuine, tmp_path, lambda c: c.pop(NETS_RECORD))
    loaded = checkpoint_nets(legacy, "tokenizer", role="ckpt")
    fresh = checkpoint_nets(genuine, "tokenizer", role="ckpt")
    assert loaded.component == "tokenizer"
    for (name, a), b in zip(loaded.nets["net"].state_dict().items(), fresh.nets["net"].state_dict().values()):
        assert torch.equal(a, b), name
    assert set(component for component, _ in LEGACY_RECORDS.values()) == {
        "tokenizer", "world_model", "video_decoder", "video_tokenizer", "latent_world_model"}
