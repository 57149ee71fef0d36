"""generate.py mode=tokenize: a trained tokenizer writes a resumable, atomic token cache that
TokenCacheDataModule reads back with its actions, timestamps and captions."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import gaia_app.utils.run_dir as run_dir_module
from gaia_app.data.datamodules import TokenCacheDataModule
from gaia_app.data.token_cache import find_segments, load_segment
from gaia_app.tasks.generate import generate
from gaia_app.utils.locks import LOCK_FILE
from tests.conftest import compose_config

# 8 train + 2 val clips of 8 frames at 25 Hz (data=synthetic_tiny), kept at the source rate
TOKENIZE = ["mode=tokenize", "data=synthetic_tiny", "extras.print_config=false"]


@pytest.fixture(scope="module")
def ckpt(tiny_tokenizer_ckpt: Path) -> Path:
    return tiny_tokenizer_ckpt


def run_tokenize(ckpt: Path, run_dir: Path, out_dir: Path, *extra: str) -> dict:
    cfg = compose_config("generate", [*TOKENIZE, f"ckpt={ckpt}", f"out_dir={out_dir}", *extra], run_dir)
    return generate(cfg)["results"]


def test_tokenize_writes_segments_with_sidecars(ckpt: Path, tmp_path: Path) -> None:
    out = tmp_path / "cache"
    results = run_tokenize(ckpt, tmp_path / "g1", out)
    assert results["train"]["written"] == 8 and results["val"]["written"] == 2
    files = find_segments(out / "train")
    # one folder per clip, one file per camera, and the cache's manifest
    assert len(files) == 8 and all(f.stem == "front" and f.parent.parent == out / "train" for f in files)
    manifest = json.loads((out / "train" / "cache.json").read_text())
    assert manifest["kind"] == "gaia1_tokens" and manifest["image_size"] == [64, 112] and manifest["format"] == 2
    tokens = np.load(files[0])
    assert tokens.shape == (8, 16, 28) and tokens.dtype == np.int16  # (T, h, w) at D = 4 on 64×112
    stem = files[0].with_suffix("")
    assert np.load(f"{stem}.actions.npy").shape == (8, 2)
    times = np.load(f"{stem}.timestamps.npy")
    assert times.shape == (8,) and np.allclose(np.diff(times), 1 / 25)
    assert len(json.loads(Path(f"{stem}.text.json").read_text())) == 8
    segment = load_segment(files[0])
    assert segment.timestamps is not None and segment.text is not None and segment.actions is not None


def test_tokenize_resumes_and_skips_finished_clips(ckpt: Path, tmp_path: Path) -> None:
    out = tmp_path / "cache"
    run_tokenize(ckpt, tmp_path / "g1", out, "max_clips=3", "splits=[train]")
    first = {f: f.stat().st_mtime_ns for f in (out / "train").rglob("*") if f.is_file() and f.name != LOCK_FILE}
    results = run_tokenize(ckpt, tmp_path / "g2", out, "splits=[train]")
    assert results["train"] == {"written": 5, "skipped": 3, "out_dir": str(out / "train")}
    # the three finished clips were left untouched
    assert all(path.stat().st_mtime_ns == t for path, t in first.items())


def test_interrupted_write_leaves_no_partial_file(ckpt: Path, tmp_path: Path, monkeypatch) -> None:
    out = tmp_path / "cache"
    real_save = np.save

    def save_then_die(f, array):
        if array.ndim == 3:  # the token file: half-written, then the process "dies"
            f.write(b"\x93NUMPY partial")
            raise KeyboardInterrupt
        real_save(f, array)

    monkeypatch.setattr(run_dir_module.np, "save", save_then_die)
    with pytest.raises(KeyboardInterrupt):
        run_tokenize(ckpt, tmp_path / "g1", out, "splits=[train]")
    monkeypatch.undo()
    # sidecars of the first clip may exist, but no token file and no temp file
    assert not list((out / "train").rglob("*.tmp"))
    assert [p.name for p in (out / "train").rglob(".*")] == [LOCK_FILE]  # the writer's lock, no hidden temp file
    assert not [p for p in (out / "train").rglob("*.npy") if p.name.count(".") == 1]
    results = run_tokenize(ckpt, tmp_path / "g2", out, "splits=[train]")
    assert results["train"]["written"] == 8 and results["train"]["skipped"] == 0


def test_token_cache_datamodule_loads_the_cache(ckpt: Path, tmp_path: Path) -> None:
    out = tmp_path / "cache"
    run_tokenize(ckpt, tmp_path / "g1", out, "splits=[train]")
    dm = TokenCacheDataModule(str(out / "train"), seq_len=4, val_fraction=0.25, batch_size=2)
    dm.setup()
    batch = next(iter(dm.train_dataloader()))
    assert batch["tokens"].shape == (2, 4, 16 * 28)
    assert batch["actions"].shape == (2, 4, 2)
    assert batch["timestamps"].shape == (2, 4) and float(batch["timestamps"][0, 0]) == 0.0
    assert 0 < dm.vocab_size <= 512
