"""The road-users weights (issue 49): gaia_app/weights/gaia1_road_users (the D = 4 GAIA-1 tokenizer, 448 tokens per
frame, ahead of its world model) and gaia_app/weights/gaia2_road_users (the s = 4 GAIA-2 video tokenizer, 16 × 28
latent positions per latent step, and a latent world model on its latents with no raster). Their MANIFESTs list every
file, and the headline claim, that they keep the road users the shipped tokenizers erase, holds on clips of a world
used for nothing else."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from gaia_app.weights.folders import WEIGHTS_ROOT, load_nets
from tests.conftest import load_benchmark

pytestmark = pytest.mark.usefixtures("one_thread")

GAIA1 = WEIGHTS_ROOT / "gaia1_road_users"
GAIA2 = WEIGHTS_ROOT / "gaia2_road_users"
# version 2 meets the 0.8 target over 128 clips of world 5101 (0.810); 0.740 [0.510, 0.893] on the test's 12 clips
GAIA2_RATIO_BAR = 0.6


def listed_files(folder: Path) -> dict[str, str]:
    text = (folder / "MANIFEST.md").read_text()
    return dict(re.findall(rf"^\| {folder.name}/(\S+) \| (\d+) \|$", text, re.MULTILINE))


def test_the_gaia1_manifest_lists_every_file_and_the_tokenizer_has_the_finer_grid() -> None:
    shipped = {p.name: str(p.stat().st_size) for p in GAIA1.iterdir() if p.suffix in (".safetensors", ".yaml")}
    assert listed_files(GAIA1) == shipped == {k: shipped[k] for k in ("tokenizer.safetensors", "tokenizer.yaml")}
    assert sum(int(n) for n in shipped.values()) < 25e6  # the GAIA-1 size budget
    net = load_nets(GAIA1, "tokenizer")[0]["net"]
    with torch.no_grad():
        assert net.encode(torch.zeros(1, 3, 64, 112)).shape[-2:] == (16, 28)  # D = 4: 448 tokens per frame


@pytest.mark.slow
def test_the_gaia1_road_users_tokenizer_keeps_the_agents_the_shipped_one_loses(tmp_path: Path) -> None:
    """16 clips of world 6101 (used for nothing else), side by side with the shipped tokenizer and its paired
    interval; measured over 128 clips of world 5071 (docs/tokenizer.md): agent_iou_ratio 0.818 against the shipped
    tokenizer's 0.388 (0.854 against 0.434 on the test's clips, paired +0.42 [+0.33, +0.52]). Bars below those, so
    that only a real loss of road users fails."""
    result = load_benchmark("agent_fidelity").main(["--weights", str(GAIA1), "--against", "gaia1", "--clips", "16",
                                                    "--world-seed", "6101", "--real-dir", str(tmp_path / "none")])
    assert result["agent_iou_ratio"] > 0.7
    assert result["against"]["agent_iou_ratio_difference"]["low"] > 0.15


def test_the_gaia2_manifest_lists_every_file_and_the_latents_have_the_finer_grid() -> None:
    shipped = {p.name: str(p.stat().st_size) for p in GAIA2.iterdir() if p.suffix in (".safetensors", ".yaml")}
    assert listed_files(GAIA2) == shipped
    assert set(shipped) == {f"{part}.{ext}" for part in ("video_tokenizer", "latent_world_model")
                            for ext in ("safetensors", "yaml")}
    assert sum(int(n) for n in shipped.values()) < 40e6  # the GAIA-2 size budget
    net = load_nets(GAIA2, "video_tokenizer")[0]["net"]
    with torch.no_grad():
        assert net.encode(torch.zeros(1, 1, 4, 3, 64, 112)).mean.shape[-2:] == (16, 28)  # s = 4


def test_the_gaia2_road_users_world_model_reads_agents_by_cross_attention_only() -> None:
    """Its YAML paints nothing on the grid (no agent or ego-flow raster): the agents reach it through the box-masked
    cross-attention, the ego action through AdaLN; it reads the tokenizer's 16 × 28 latents in 2 × 2 patches."""
    nets, info = load_nets(GAIA2, "latent_world_model")
    net = nets["net"]
    assert net.conditioner.agent_raster is None and net.conditioner.action_raster is None
    assert net.agent_box_attention and info["latent_scale"] == 0.375


@pytest.mark.slow
def test_the_gaia2_road_users_tokenizer_keeps_more_agents_than_the_shipped_one(tmp_path: Path) -> None:
    """12 clips of world 6111 (used for nothing else), side by side with the shipped GAIA-2 tokenizer; measured over
    128 clips of world 5101 (docs/tokenizer.md, gaia_app/weights/gaia2_road_users/MANIFEST.md): 0.810 against the
    shipped 0.445. Bars below the measured values, so that only a real loss of road users fails."""
    result = load_benchmark("agent_fidelity").main(["--weights", str(GAIA2), "--against", "gaia2", "--clips", "12",
                                                    "--world-seed", "6111", "--real-dir", str(tmp_path / "none")])
    assert result["agent_iou_ratio"] > GAIA2_RATIO_BAR
    assert result["against"]["agent_iou_ratio_difference"]["low"] > 0.15  # measured +0.367 [+0.277, +0.507]
