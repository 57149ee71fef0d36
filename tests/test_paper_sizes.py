"""Paper presets built on the meta device (no memory): parameter counts within 10% of the papers."""

from __future__ import annotations

import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from tests.conftest import CONF_DIR

# GAIA-1 §4.1, §4.2, §4.3
PAPER_SIZES = {"gaia1_tokenizer_paper": 0.3e9, "gaia1_world_model_paper": 6.5e9, "gaia1_video_decoder_paper": 2.6e9}


@pytest.mark.parametrize("preset", sorted(PAPER_SIZES))
def test_paper_preset_parameter_count(preset: str) -> None:
    cfg = OmegaConf.load(CONF_DIR / "model" / "net" / f"{preset}.yaml")
    with torch.device("meta"):
        net = instantiate(cfg)()
    count = sum(p.numel() for p in net.parameters())
    assert count == pytest.approx(PAPER_SIZES[preset], rel=0.10), f"{preset}: {count / 1e6:.1f}M parameters"


def test_world_model_paper_sequence_length() -> None:
    """GAIA-1 §4.2: T × (m + n + l) = 26 × (32 + 576 + 2) = 15 860 positions."""
    cfg = OmegaConf.load(CONF_DIR / "model" / "net" / "gaia1_world_model_paper.yaml")
    with torch.device("meta"):
        net = instantiate(cfg)()
    assert net.frames * net.step_len == 15_860


def test_video_decoder_paper_reads_the_paper_tokenizer() -> None:
    """GAIA-1 §4.1, §4.3: T' = 7 frames of 288×512, tokens on the tokenizer's 18×32 grid from K = 8192 codes."""
    net_dir = CONF_DIR / "model" / "net"
    with torch.device("meta"):
        decoder = instantiate(OmegaConf.load(net_dir / "gaia1_video_decoder_paper.yaml"))()
        tokenizer = instantiate(OmegaConf.load(net_dir / "gaia1_tokenizer_paper.yaml"))()
    assert decoder.frames == 7 and decoder.image_size == (288, 512) and decoder.token_grid == (18, 32)
    assert decoder.vocab_size == tokenizer.codebook_size
    assert decoder.downsampling == (tokenizer.downsampling, tokenizer.downsampling)


def test_gaia2_video_tokenizer_paper_preset() -> None:
    """GAIA-2 report, tokenizer: encoder ≈ 85M and a larger decoder ≈ 200M; 448×960 → 14×30 per step, 8 frames per
    step, 64 channels, 3 latent steps (24 frames) decoded together."""
    cfg = OmegaConf.load(CONF_DIR / "model" / "net" / "gaia2_video_tokenizer_paper.yaml")
    with torch.device("meta"):
        net = instantiate(cfg)()
    encoder = sum(p.numel() for p in net.encoder.parameters())
    decoder = sum(p.numel() for p in net.decoder.parameters())
    assert encoder == pytest.approx(85e6, rel=0.10), f"encoder {encoder / 1e6:.1f}M"
    assert decoder == pytest.approx(200e6, rel=0.10), f"decoder {decoder / 1e6:.1f}M"
    assert net.latent_shape(24, 448, 960) == (3, 64, 14, 30) and net.chunk_latents == 3


def test_gaia2_world_model_paper_preset() -> None:
    """GAIA-2 report, world model: 22 layers, ≈ 8.4B parameters."""
    cfg = OmegaConf.load(CONF_DIR / "model" / "net" / "gaia2_world_model_paper.yaml")
    with torch.device("meta"):
        net = instantiate(cfg)()
    count = sum(p.numel() for p in net.parameters())
    assert len(net.blocks) == 22
    assert count == pytest.approx(8.4e9, rel=0.10), f"{count / 1e9:.2f}B parameters"


# GAIA-1 §4.1–4.3: (global batch, steps, lr, weight decay, betas, warm-up, decay, final lr, strategy)
PAPER_RUNS = {
    "gaia1/tokenizer_paper": (160, 200_000, 1e-4, 0.01, [0.5, 0.9], 5_000, 10_000, 1e-5, "DDPStrategy"),
    "gaia1/world_model_paper": (128, 100_000, 1e-4, 0.1, [0.9, 0.95], 2_500, 97_500, 1e-5, "DeepSpeedStrategy"),
    "gaia1/video_decoder_paper": (64, 300_000, 5e-5, 0.01, [0.9, 0.99], 2_500, 5_000, 1e-6, "DDPStrategy"),
}


@pytest.mark.parametrize("experiment", sorted(PAPER_RUNS))
def test_paper_experiments_carry_the_papers_training_settings(experiment: str, tmp_path) -> None:
    from tests.conftest import compose_config

    batch, steps, lr, wd, betas, warmup, decay, final_lr, strategy = PAPER_RUNS[experiment]
    cfg = compose_config("train", [f"experiment={experiment}"], tmp_path)
    t = cfg.trainer
    assert cfg.data.batch_size * t.devices * t.num_nodes == batch
    assert t.max_steps == steps and t.strategy._target_.endswith(strategy)
    optim, sched = cfg.model.optim, cfg.model.sched
    assert (optim.lr, optim.weight_decay, list(optim.betas)) == (lr, wd, betas)
    assert (sched.warmup_steps, sched.decay_steps, sched.final_lr) == (warmup, decay, final_lr)
    if experiment == "gaia1/world_model_paper":
        net = cfg.model.net
        assert net.frames * (net.text_tokens + net.image_tokens + net.action_tokens) == 15_860 and net.checkpointing
        assert t.strategy.stage == 2 and t.gradient_clip_val == 1.0
