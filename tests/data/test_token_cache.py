"""Token caches: synthetic segments and the real commaVQ tokens, split without overlap."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gaia_app.data.clip import ClipError
from gaia_app.data.collate import collate_token_windows
from gaia_app.data.datamodules import TokenCacheDataModule


def test_folder_of_segments_with_actions(tmp_path: Path) -> None:
    for k in range(4):
        np.save(tmp_path / f"seg{k}.npy", np.full((40, 2, 3), k, dtype=np.int16))
        np.save(tmp_path / f"seg{k}.actions.npy", np.full((40, 2), k, dtype=np.float32))
    dm = TokenCacheDataModule(str(tmp_path), seq_len=5, frame_stride=2, val_fraction=0.25, batch_size=2)
    dm.setup()
    batch = next(iter(dm.train_dataloader()))
    assert batch["tokens"].shape == (2, 5, 6) and batch["actions"].shape == (2, 5, 2)
    # the last segment is validation only
    val_values = {int(b["tokens"].max()) for b in dm.val_dataloader()}
    train_values = {int(x["tokens"][0, 0]) for x in dm.train_set}
    assert val_values == {3} and train_values == {0, 1, 2}


def test_captions_batch_as_lists_per_window(tmp_path: Path) -> None:
    np.save(tmp_path / "seg.npy", np.zeros((20, 4), dtype=np.int64))
    captions = [f"frame {i}" if i % 3 else None for i in range(20)]
    (tmp_path / "seg.text.json").write_text(json.dumps(captions))
    dm = TokenCacheDataModule(str(tmp_path), seq_len=4, stride=4, val_fraction=0.2, batch_size=2)
    dm.setup()
    batch = next(iter(dm.val_dataloader()))
    assert batch["tokens"].shape == (1, 4, 4)  # 4 of 20 steps held out: one window
    assert batch["text"] == [captions[16:20]]  # b lists of t captions, None kept


def test_windows_with_and_without_captions_do_not_mix(tmp_path: Path) -> None:
    for name in ("a", "b"):
        np.save(tmp_path / f"{name}.npy", np.zeros((8, 4), dtype=np.int64))
    (tmp_path / "a.text.json").write_text(json.dumps(["x"] * 8))
    dm = TokenCacheDataModule(str(tmp_path), seq_len=4, stride=4, val_fraction=0.5, batch_size=2)
    dm.setup()
    with pytest.raises(ClipError, match="'text'"):
        collate_token_windows([dm.train_set[0], dm.val_set[0]])


def test_bad_token_file_is_named(tmp_path: Path) -> None:
    np.save(tmp_path / "bad.npy", np.zeros((4,), dtype=np.float32))
    dm = TokenCacheDataModule(str(tmp_path / "bad.npy"))
    with pytest.raises(ClipError, match="bad.npy"):
        dm.setup()


def test_mismatched_actions_are_named(tmp_path: Path) -> None:
    np.save(tmp_path / "a.npy", np.zeros((10, 4), dtype=np.int64))
    np.save(tmp_path / "a.actions.npy", np.zeros((9, 2), dtype=np.float32))
    with pytest.raises(ClipError, match="a.actions.npy"):
        TokenCacheDataModule(str(tmp_path / "a.npy")).setup()


@pytest.mark.real_data
def test_real_commavq_tokens(shared_data: Path) -> None:
    dm = TokenCacheDataModule(str(shared_data / "commavq" / "tokens.npy"), seq_len=16, frame_stride=3, val_fraction=0.1)
    dm.setup()
    assert dm.vocab_size <= 1024
    batch = next(iter(dm.train_dataloader()))
    assert batch["tokens"].shape == (8, 16, 128)
    train_steps = {s + k for _, s in dm.train_set.index for k in range(16)}
    val_steps = {s + k for _, s in dm.val_set.index for k in range(16)}
    assert not train_steps & val_steps and len(val_steps) >= 16
