"""mode=export export_parts=tokenizer: a tokenizer trained before any world model on its tokens (the road-users
tokenizers of issue 49) leaves the training machine as a weights folder that the tokenize / encode modes and the
agent-fidelity benchmark read, and that rebuilds the same net."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from gaia_app.tasks.generate import generate
from gaia_app.weights.folders import load_nets
from gaia_app.weights.nets import checkpoint_nets
from tests.conftest import compose_config, load_benchmark

pytestmark = pytest.mark.usefixtures("one_thread")

RIG = ["data=synthetic_rig_tiny", "extras.print_config=false"]


def export_alone(family: list[str], ckpt: Path, out: Path, run_dir: Path, *extra: str) -> dict:
    overrides = [*family, "mode=export", "export_parts=tokenizer", "export_dtype=float32", f"tokenizer_ckpt={ckpt}",
                 f"out_dir={out}", *extra]
    return generate(compose_config("generate", overrides, run_dir))["results"]


def test_a_gaia2_video_tokenizer_exports_alone_and_encodes_like_its_checkpoint(gaia2_tiny, tmp_path: Path) -> None:
    folder = tmp_path / "g2"
    results = export_alone(["model=gaia2", *RIG], gaia2_tiny["tokenizer"], folder, tmp_path / "e")
    assert {p.name for p in folder.iterdir()} == {"video_tokenizer.safetensors", "video_tokenizer.yaml"}
    assert results["video_tokenizer"]["parameters"] > 0
    exported = load_nets(folder, "video_tokenizer")[0]["net"]
    trained = checkpoint_nets(gaia2_tiny["tokenizer"], "video_tokenizer", "tokenizer_ckpt").nets["net"]
    video = torch.rand(1, 1, 4, 3, 64, 112) * 2 - 1
    with torch.no_grad():
        torch.testing.assert_close(exported.encode(video).mean, trained.encode(video).mean, rtol=0, atol=0)
    encoded = generate(compose_config("generate", ["mode=encode", *RIG, f"weights={folder}",
                                                   f"out_dir={tmp_path / 'latents'}"], tmp_path / "enc"))["results"]
    assert encoded["train"]["written"] == 8 and encoded["val"]["written"] == 2  # data=synthetic_rig_tiny's clips


def test_a_gaia1_tokenizer_exports_alone_and_the_fidelity_benchmark_reads_it(gaia1_tiny, tmp_path: Path) -> None:
    folder = tmp_path / "g1"
    export_alone([], gaia1_tiny["tokenizer_ckpt"], folder, tmp_path / "e", "data.height=32", "data.width=48")
    assert {p.name for p in folder.iterdir()} == {"tokenizer.safetensors", "tokenizer.yaml"}
    family, round_trip = load_benchmark("agent_fidelity").tokenizer_round_trip(str(folder))
    assert family == "gaia1" and callable(round_trip)


def test_export_parts_refuses_what_a_tokenizer_alone_cannot_hold(gaia1_tiny, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="export_parts=tokenizer writes the tokenizer alone; drop world_model_ckpt"):
        export_alone([], gaia1_tiny["tokenizer_ckpt"], tmp_path / "x", tmp_path / "a",
                     f"world_model_ckpt={gaia1_tiny['world_model_ckpt']}")
    with pytest.raises(ValueError, match=r"export_parts='everything': expected one of \['all', 'tokenizer'\]"):
        generate(compose_config("generate", ["mode=export", "export_parts=everything", f"out_dir={tmp_path / 'y'}"],
                                tmp_path / "b"))
    with pytest.raises(TypeError, match="holds a world_model"):
        export_alone([], gaia1_tiny["world_model_ckpt"], tmp_path / "z", tmp_path / "c")
