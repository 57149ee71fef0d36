"""Every `experiment=*_paper` runs one training step (issue 22, item 5).

Each paper experiment keeps its data layout (frame size, clip length, token grid, latent grid), its conditioning
(text encoder kind, metadata, agents, actions) and its losses' frozen networks, and only its width and depth are
shrunk by overrides, with a one-process CPU trainer instead of its cluster strategy. So a shape mismatch between a
paper preset and its data or encoder (e.g. a text width that disagrees with the encoder) fails here, not on the
first batch of a cluster job. The frozen networks (VGG16, DINO, DINOv2) are random ones of the real layout, shrunk
in width or depth, saved like their official checkpoints; T5 and CLIP are tiny random models in local directories.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from gaia_app.data.clip import AgentBoxes, CameraSpec
from gaia_app.data.clip_writer import write_clip
from gaia_app.data.latent_cache import LatentClip, write_latent_clip
from gaia_app.data.synthetic import generate_clip
from gaia_app.data.synthetic.rig import build_rig
from gaia_app.data.token_cache import TokenSegment, write_segment
from gaia_app.nn.vgg import VGG16Features
from gaia_app.nn.vit import VisionTransformer
from gaia_app.tasks.train import train
from tests.conftest import CLIP_PROJECTION, T5_WIDTH, compose_config, save_tiny_t5

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.rehearsal]

# one CPU process, one step, no validation: the cluster strategies of the paper runs are tested in test_paper_sizes
ONE_STEP = ["trainer=tiny", "trainer.devices=1", "trainer.num_nodes=1", "trainer.max_steps=1",
            "trainer.limit_val_batches=0", "logger=csv", "extras.print_config=false"]
CAPTIONS = ["It is night.", "It is raining.", "The weather is clear."]


@pytest.fixture(scope="module")
def pretrained(tmp_path_factory) -> dict[str, Path]:
    """Random frozen networks of the paper layouts, shrunk: VGG16 at base width 4, DINO ViT-S/16 and DINOv2
    ViT-S/14 with one block (embed 384 = the tokenizers' distill_dim), and tiny T5 / CLIP directories."""
    root = tmp_path_factory.mktemp("pretrained")
    torch.manual_seed(0)
    torch.save(VGG16Features(base_width=4).state_dict(), root / "vgg16.pth")
    torch.save(VisionTransformer(embed_dim=384, depth=1, num_heads=6).state_dict(), root / "dino_vits16.pth")
    torch.save(VisionTransformer(embed_dim=384, depth=1, num_heads=6, image_size=518, patch_size=14, layer_scale=True,
                                 mask_token=True).state_dict(), root / "dinov2_vits14.pth")
    from tests.conftest import save_tiny_clip

    return {"root": root, "t5": save_tiny_t5(root / "t5", CAPTIONS), "clip": save_tiny_clip(root / "clip")}


@pytest.fixture(scope="module")
def clips(tmp_path_factory) -> Path:
    """Two labelled synthetic clips of 32 frames (long enough for every paper window), small: the data modules
    resize them to each paper's frame size."""
    root = tmp_path_factory.mktemp("clips")
    for seed in (1, 2):
        write_clip(generate_clip(seed=seed, height=64, width=112, cameras=["front"], clip_len=32, fps=25.0), root)
    return root


def frozen(pretrained: dict[str, Path], dino: str) -> list[str]:
    return [f"model.perceptual.checkpoint={pretrained['root'] / 'vgg16.pth'}", "+model.perceptual.base_width=4",
            f"model.dino.checkpoint={pretrained['root'] / (dino + '.pth')}", "+model.dino.depth=1"]


def run(experiment: str, overrides: list[str], run_dir: Path) -> dict:
    results = train(compose_config("train", [f"experiment={experiment}", *ONE_STEP, *overrides], run_dir))
    assert results["trainer"].global_step >= 1
    assert (run_dir / "checkpoints" / "last.ckpt").is_file()
    return results


@pytest.fixture(scope="module")
def gaia1_tokenizer(pretrained, clips, tmp_path_factory) -> Path:
    """experiment=gaia1/tokenizer_paper, one step: 288×512 frames, 16× downsampling (18×32 tokens), 8192 codes."""
    run_dir = tmp_path_factory.mktemp("gaia1_tokenizer_paper")
    run("gaia1/tokenizer_paper", [f"data.source.root={clips}", "data.batch_size=2", "model.net.channels=8",
                                  "model.net.blocks_per_stage=1", "model.net.latent_dim=16",
                                  *frozen(pretrained, "dino_vits16")], run_dir)
    return run_dir / "checkpoints" / "last.ckpt"


def test_gaia1_tokenizer_paper_runs_one_step(gaia1_tokenizer: Path) -> None:
    from gaia_app.weights.checkpoints import read_checkpoint

    config = read_checkpoint(gaia1_tokenizer)["hyper_parameters"]["model_cfg"]
    assert config["net"]["codebook_size"] == 8192 and config["net"]["channel_mults"] == [1, 2, 4, 4, 8]


def test_gaia1_world_model_paper_runs_one_step(pretrained, tmp_path: Path) -> None:
    """26 frames of 576 tokens (18×32) with T5 captions and actions: the paper's 15,860-position sequence."""
    rng = np.random.default_rng(0)
    for i in range(2):
        frames = 30
        write_segment(tmp_path / "tokens", TokenSegment(
            name=f"clip{i}_front", tokens=rng.integers(0, 8192, (frames, 18, 32)),
            actions=np.tile(np.float32([10.0, 0.01]), (frames, 1)), timestamps=np.arange(frames) / 6.25,
            text=[CAPTIONS[i]] * frames))
    run("gaia1/world_model_paper", [f"data.path={tmp_path / 'tokens'}", "model.net.dim=32", "model.net.depth=1",
                                    "model.net.heads=2", f"model.text_encoder.path={pretrained['t5']}",
                                    f"model.text_encoder.dim={T5_WIDTH}"], tmp_path / "run")


def test_gaia1_video_decoder_paper_runs_one_step(gaia1_tokenizer: Path, clips: Path, tmp_path: Path) -> None:
    """Clips of 25 frames at 288×512 decoded from the paper tokenizer's 18×32 tokens, 7-frame windows."""
    run("gaia1/video_decoder_paper", [f"data.source.root={clips}", f"model.tokenizer_ckpt={gaia1_tokenizer}",
                                      "data.batch_size=1", "model.net.channels=8", "model.net.res_blocks=1",
                                      "model.net.heads=2", "model.net.token_dim=16"], tmp_path)


def test_gaia2_video_tokenizer_paper_runs_one_step(pretrained, clips: Path, tmp_path: Path) -> None:
    """24 frames at 448×960 → 3 latent steps of 64 channels on a 14×30 grid (32× spatial, 8× temporal)."""
    run("gaia2/video_tokenizer_paper", [f"data.source.root={clips}", "model.net.conv_channels=4",
                                        "model.net.encoder_dim=32", "model.net.encoder_depth=1",
                                        "model.net.encoder_heads=2", "model.net.decoder_dim=32",
                                        "model.net.decoder_depth=1", "model.net.decoder_heads=2",
                                        "model.net.decoder_conv_channels=4", *frozen(pretrained, "dinov2_vits14")],
        tmp_path)


def test_gaia2_world_model_paper_runs_one_step(pretrained, tmp_path: Path) -> None:
    """Three cameras of 64-channel 14×30 latents with every condition, text through the (tiny) local CLIP."""
    rig = [CameraSpec(c.name, c.intrinsics, c.extrinsics, c.width, c.height) for c in build_rig(3, 448, 960)]
    rng = np.random.default_rng(0)
    for split in ("train", "val"):
        for i in range(2):
            steps, frames = 4, 32
            write_latent_clip(tmp_path / "latents" / split, LatentClip(
                clip_id=f"clip_{i}", mean=rng.normal(size=(3, steps, 64, 14, 30)).astype(np.float32),
                logvar=np.full((3, steps, 64, 14, 30), -6, np.float32), temporal_downsampling=8, fps=25.0,
                image_size=(448, 960), timestamps=np.arange(frames) / 25.0, cameras=rig,
                meta={"weather": "rain", "time_of_day": "night"}, actions=np.tile(np.float32([10, 0.01]), (frames, 1)),
                text=[CAPTIONS[i]] * frames,
                agents=[AgentBoxes([[12.0, 0.5, 0.8]], [[4.5, 1.8, 1.6]], [0.0], [0], [1]) for _ in range(frames)]))
    results = run("gaia2/world_model_paper", [f"data.path={tmp_path / 'latents'}", "model.net.dim=56",
                                              "model.net.depth=1", "model.net.heads=2",
                                              f"model.text_encoder.path={pretrained['clip']}",
                                              f"model.text_encoder.dim={CLIP_PROJECTION}"], tmp_path / "run")
    assert results["model"].model.conditioner.text.in_features == CLIP_PROJECTION
