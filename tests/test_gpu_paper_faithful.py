"""benchmarks/gpu_paper_faithful.py (issue 50): the study's smaller budgets trained and scored on one GPU. On a CPU:
the commands it builds, its refusal without CUDA and what it brings back; the whole dry run is run by hand
(docs/paper_faithful.md), since it scores five 448-token world models."""

from __future__ import annotations

import argparse
import tarfile
from pathlib import Path

import pytest
import torch

from tests.conftest import load_benchmark


@pytest.fixture(scope="module")
def ladder():
    return load_benchmark("gpu_paper_faithful")


def test_each_arm_at_each_fraction_gets_its_own_schedule(ladder, tmp_path: Path) -> None:
    arms = ladder.ladder_arms(tmp_path / "cache", tmp_path, 200, dry=False, minilm=tmp_path / "minilm",
                              fractions=[1 / 32, 1 / 4])
    assert sorted(arms) == ["paper_1750", "paper_219", "shortcuts_1750", "shortcuts_219"]
    assert {"trainer.max_steps=219", "model.sched.decay_steps=219"} <= set(arms["paper_219"])
    assert "experiment=gaia1/paper_faithful/world_model_d4_gpu" in arms["paper_1750"]
    assert f"model.text_encoder.path={tmp_path / 'minilm'}" in arms["paper_1750"]
    assert not any(a.startswith("model.text_encoder") for a in arms["shortcuts_1750"])
    without = ladder.ladder_arms(tmp_path / "cache", tmp_path, 200, dry=False, minilm=None, fractions=[1 / 4])
    assert list(without) == ["shortcuts_1750"]  # no MiniLM, no paper arm


def test_scoring_uses_the_studys_protocol_once_per_setting(ladder, tmp_path: Path) -> None:
    real = ladder.score_command(tmp_path / "w", tmp_path / "run", dry=False)
    assert {"mode=controllability", "controllability.contexts=32", "context.seed=5050", "device=cuda"} <= set(real)
    dry = ladder.score_command(tmp_path / "w", tmp_path / "run", dry=True)
    keys = [setting.split("=")[0] for setting in dry]
    assert len(keys) == len(set(keys)) and "controllability.contexts=2" in dry and "device=cpu" in dry


def test_what_comes_back_is_one_archive(ladder, tmp_path: Path) -> None:
    back, work, out = tmp_path / "back", tmp_path / "work", tmp_path / "out"
    for folder in (back, work / "score_a", out):
        folder.mkdir(parents=True)
    (back / "a.ckpt").write_bytes(b"w")
    (back / "tokenize.log").write_text("t")
    (work / "score_a" / "controllability.json").write_text("{}")
    ladder.pack(out, back, work, ["a", "b"])
    with tarfile.open(out / "ladder.tar") as archive:
        assert sorted(archive.getnames()) == ["a.ckpt", "score_a_controllability.json", "tokenize.log"]
    assert [p.name for p in out.iterdir()] == ["ladder.tar"]


def test_bad_arguments_and_no_cuda_are_refused(ladder, tmp_path: Path, monkeypatch) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match="expected NAME=<world-model checkpoint>"):
        ladder.parse_score("no_equals_sign")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SystemExit, match="needs CUDA"):
        ladder.main(["--out", str(tmp_path), "--tokenizer", str(tmp_path / "t.ckpt")])
