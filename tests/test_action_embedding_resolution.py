"""benchmarks/action_embedding_resolution.py (issue 50, item 2): how far a command moves the first attention layer's
input at the action positions of a GAIA-1 world model."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from gaia_app.models.gaia1.world_model import WorldModel
from tests.conftest import load_benchmark


def tiny_net(speed_std: float = 8.0) -> WorldModel:
    torch.manual_seed(0)
    return WorldModel(32, dim=32, depth=1, heads=4, frames=3, text_tokens=2, image_tokens=4, text_dim=8,
                      action_norm={"mean": (10.0, 0.0), "std": (speed_std, 0.03)}).eval()


def test_a_command_moves_only_its_own_token_and_a_finer_scale_moves_it_further() -> None:
    bench = load_benchmark("action_embedding_resolution")
    coarse = bench.resolution(tiny_net(8.0), speed_step=1.8, curvature_step=0.01)
    # the paper's independent linear layers: a speed change leaves the curvature token where it was, and back
    assert coarse["speed"]["curvature"] == 0.0 and coarse["curvature"]["speed"] == 0.0
    assert 0.0 < coarse["speed"]["speed"] < 1.0
    # the same net with speed divided by 2 m/s instead of 8 (the same weights): the step is 4× as large in model
    # units, so the normalised input turns further, by less than 4× (LayerNorm is blind to the token's scale)
    fine = bench.resolution(tiny_net(2.0), speed_step=1.8, curvature_step=0.01)
    assert coarse["speed"]["speed"] * 1.5 < fine["speed"]["speed"] < coarse["speed"]["speed"] * 4.0
    assert fine["curvature"]["curvature"] == pytest.approx(coarse["curvature"]["curvature"])


def test_the_script_reads_checkpoints_by_name_and_writes_both_tables(tmp_path: Path, monkeypatch) -> None:
    bench = load_benchmark("action_embedding_resolution")
    monkeypatch.setattr(bench, "load", lambda path: tiny_net())
    model = tmp_path / "last.ckpt"
    model.write_bytes(b"")
    report = bench.main(["--model", f"tiny={model}", "--out", str(tmp_path / "out")])
    written = json.loads((tmp_path / "out" / "resolution.json").read_text())
    assert written == report and set(written["models"]["tiny"]) == {"speed", "curvature"}
    assert "| tiny |" in (tmp_path / "out" / "resolution.md").read_text()
    with pytest.raises(SystemExit, match="NAME=<existing"):
        bench.main(["--model", f"missing={tmp_path / 'nope.ckpt'}", "--out", str(tmp_path / "out")])
