"""GAIA-2 video tokenizer training (GAIA-2 report, tokenizer): stage 1 learns, stage 2 fine-tunes only the decoder
with a 3-D GAN."""

from __future__ import annotations

import functools
from pathlib import Path

import lightning as L
import pytest
import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader, Dataset

from gaia_app.encoders import load_vision_teacher
from gaia_app.lit.gaia2_video_tokenizer import VideoTokenizerModule, latent_mosaic
from gaia_app.models.gaia2.video_tokenizer import VideoTokenizer
from gaia_app.nn.discriminator import PatchDiscriminator3d
from gaia_app.nn.vit import VisionTransformer

VIT = dict(embed_dim=24, depth=1, num_heads=2)
TINY_NET = functools.partial(VideoTokenizer, spatial_downsampling=8, temporal_downsampling=4, latent_channels=8,
                             chunk_latents=2, conv_mults=(), encoder_dim=48, encoder_depth=1,
                             encoder_heads=2, decoder_dim=64, decoder_depth=2, decoder_heads=2,
                             distill_dim=VIT["embed_dim"])
TINY_DISC = functools.partial(PatchDiscriminator3d, channels=8, num_layers=2)


class FixedClips(Dataset):
    """The same two smooth 2-camera clips of 8 frames at 32×64 forever: a slowly panning low-resolution pattern."""

    def __init__(self) -> None:
        low = torch.rand(2, 2, 3, 4, 12, generator=torch.Generator().manual_seed(0)) * 2 - 1
        wide = F.interpolate(low.flatten(0, 1), size=(32, 96), mode="bilinear", align_corners=False)
        wide = wide.unflatten(0, (2, 2))  # (clip, v, 3, 32, 96)
        self.clips = torch.stack([wide[..., 4 * k : 4 * k + 64] for k in range(8)], dim=2)  # (clip, v, T, 3, 32, 64)

    def __len__(self) -> int:
        return 1_000_000

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {"video": self.clips[i % 2]}


class RecordSteps(L.Callback):
    def __init__(self) -> None:
        self.terms: list[dict[str, float]] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.terms.append({k: float(v) for k, v in outputs.items()})


def make_module(**kw) -> VideoTokenizerModule:
    torch.manual_seed(0)
    args = dict(net=TINY_NET, optim=functools.partial(torch.optim.AdamW, lr=2e-3, weight_decay=0.0),
                discriminator=TINY_DISC)
    return VideoTokenizerModule(**{**args, **kw})


def fit(module: VideoTokenizerModule, steps: int, **trainer_kw) -> tuple[L.Trainer, RecordSteps]:
    record = RecordSteps()
    trainer = L.Trainer(max_steps=steps, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, callbacks=[record], **trainer_kw)
    trainer.fit(module, DataLoader(FixedClips(), batch_size=2))
    return trainer, record


def snapshot(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def changed(before: dict[str, torch.Tensor], after: torch.nn.Module) -> set[str]:
    return {k for k, v in after.state_dict().items() if not torch.equal(before[k], v)}


def test_stage_one_learns_a_fixed_batch() -> None:
    """Overfitting two clips: the reconstruction loss (L1 + L2) falls at least 5× in 100 steps."""
    module = make_module(optim=functools.partial(torch.optim.AdamW, lr=3e-3, weight_decay=0.0))
    _, record = fit(module, 100)
    first = record.terms[0]["l1"] + record.terms[0]["l2"]
    last = sum(t["l1"] + t["l2"] for t in record.terms[-10:]) / 10
    assert last < first / 5, f"reconstruction loss {first:.3f} → {last:.3f}"
    assert "gan" not in record.terms[-1] and "kl" in record.terms[-1]
    assert module.discriminator is None  # stage 1 builds no discriminator


def test_stage_two_updates_only_the_decoder_and_the_discriminator(tmp_path: Path) -> None:
    stage1 = make_module()
    trainer, _ = fit(stage1, 2)
    ckpt = tmp_path / "stage1.ckpt"
    trainer.save_checkpoint(ckpt)

    module = make_module(stage="gan", init_from=str(ckpt))
    module.configure_model()
    module.load_init_weights()
    torch.testing.assert_close(module.net.state_dict(), stage1.net.state_dict())  # starts from stage 1
    net_before, disc_before = snapshot(module.net), snapshot(module.discriminator)
    _, record = fit(module, 3)  # fit loads init_from again at fit start: the same weights
    moved = changed(net_before, module.net)
    assert moved and all(k.startswith("decoder.") for k in moved), sorted(moved)[:5]
    assert len(moved) == len(module.net.decoder.state_dict())  # every decoder tensor trained
    assert changed(disc_before, module.discriminator)
    assert {"gan", "disc_loss", "adaptive_weight"} <= set(record.terms[-1]) and "kl" not in record.terms[-1]


def test_stage_two_optimises_decoder_parameters_only() -> None:
    module = make_module(stage="gan")
    module.configure_model()
    generator = {id(p) for p in module.generator_parameters()}
    assert generator == {id(p) for p in module.net.decoder.parameters()}
    assert not any(p.requires_grad for p in module.net.encoder.parameters())


def test_dinov2_distillation_of_the_latents(tmp_path: Path) -> None:
    """With a (small, random) DINOv2-layout teacher the distillation term is on and trains the projection."""
    torch.manual_seed(0)
    torch.save(VisionTransformer(patch_size=14, layer_scale=True, mask_token=True, image_size=518, **VIT).state_dict(),
               tmp_path / "dinov2.pth")
    teacher = functools.partial(load_vision_teacher, kind="dinov2_vits14", checkpoint=tmp_path / "dinov2.pth", **VIT)
    module = make_module(dino=teacher)
    head_before = module.tokenizer.distill_head.weight.detach().clone()
    _, record = fit(module, 2)
    assert record.terms[0]["dino"] > 0
    assert not torch.equal(head_before, module.tokenizer.distill_head.weight)
    assert all(k.startswith("net.") for k in module.state_dict())  # the teacher stays out of the checkpoint


def test_perceptual_term_compares_every_frame(tmp_path: Path) -> None:
    """With a (small, random) VGG16-layout perceptual network the reconstruction terms get a perceptual term, frame
    by frame over every camera, that is zero for a perfect reconstruction."""
    from types import SimpleNamespace

    from gaia_app.encoders import load_perceptual
    from gaia_app.nn.vgg import VGG16Features

    torch.manual_seed(0)
    torch.save(VGG16Features(base_width=4).state_dict(), tmp_path / "vgg16.pth")
    module = make_module(perceptual=functools.partial(load_perceptual, checkpoint=tmp_path / "vgg16.pth",
                                                      base_width=4))
    module.load_frozen_networks()  # what fit's setup does
    video = FixedClips().clips[:1]  # (1, v, T, 3, 32, 64)
    noisy = SimpleNamespace(reconstruction=video + 0.3 * torch.randn_like(video))
    terms = module.reconstruction_terms(video, noisy)
    assert terms["perceptual"] > 0 and {"l1", "l2"} <= set(terms)
    exact = module.reconstruction_terms(video, SimpleNamespace(reconstruction=video.clone()))
    assert float(exact["perceptual"]) == pytest.approx(0.0, abs=1e-6)


def test_step_frames_are_the_middle_frame_of_each_latent_step() -> None:
    module = make_module()
    clip = torch.arange(8.0).view(1, 1, 8, 1, 1, 1).expand(1, 1, 8, 3, 2, 2)
    assert module.step_frames(clip)[:, 0, 0, 0].tolist() == [2.0, 6.0]


def test_unknown_stage_and_missing_init_checkpoint_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="model.stage='decoder'"):
        make_module(stage="decoder")
    module = make_module(stage="gan", init_from=str(tmp_path / "missing.ckpt"))
    with pytest.raises(FileNotFoundError, match="model.init_from=.*missing.ckpt"):
        fit(module, 1)


def test_media_shows_input_over_reconstruction_per_camera_and_latent_channels() -> None:
    module = make_module()
    media = module.media({"video": FixedClips().clips})
    assert media["val/input_over_reconstruction"].shape == (1, 2, 8, 3, 64, 64)
    torch.testing.assert_close(media["val/input_over_reconstruction"][..., :32, :], FixedClips().clips[:1])
    assert media["val/latent_channels"].shape == (2, 1, 4 * 1, 8 * 8)  # 2 steps, 8 channels in one row of 4×8 tiles


def test_latent_mosaic_pads_to_whole_rows() -> None:
    mosaic = latent_mosaic(torch.randn(3, 10, 2, 5), columns=4)
    assert mosaic.shape == (3, 1, 3 * 2, 4 * 5)
    assert mosaic[:, :, 4:, 10:].abs().max() == 0  # channels 11 and 12 of the 12 tiles are padding
    assert mosaic.abs().max() <= 1


def test_evaluation_pair_gives_one_video_per_camera() -> None:
    """EvaluationCallback (PSNR/SSIM/FVMD/FDD) sees each camera as its own clip: (b·v, T, 3, H, W) pairs."""
    module = make_module()
    real, generated = module.evaluation_pair({"video": FixedClips().clips})
    assert real.shape == generated.shape == (4, 8, 3, 32, 64)
    torch.testing.assert_close(real[1], FixedClips().clips[0, 1])
    assert generated.abs().max() <= 1


@pytest.fixture(scope="module")
def rig_clip():
    """One synthetic front-camera clip of 8 frames at 32 × 64 with its simulation, as a training batch."""
    import numpy as np

    from gaia_app.data.collate import pad_agents
    from gaia_app.data.synthetic import SyntheticClipDataset
    from gaia_app.data.transforms import to_float

    sample = SyntheticClipDataset(num_clips=1, seed=77, height=32, width=64, clip_len=8).sample(0)
    clip = sample.clip
    batch = {"video": to_float(torch.from_numpy(clip.frames))[None], **pad_agents([clip.agents]),
             "intrinsics": torch.tensor(np.stack([c.intrinsics for c in clip.cameras]), dtype=torch.float32)[None],
             "extrinsics": torch.tensor(np.stack([c.extrinsics for c in clip.cameras]), dtype=torch.float32)[None]}
    agents = torch.from_numpy(np.stack([sample.instance_ids(f, 0) >= 0 for f in range(8)]))
    return batch, agents


def test_agent_weight_covers_the_rendered_agents(rig_clip) -> None:
    batch, agents = rig_clip
    module = make_module(weights={"agents": 9.0})
    weights = module.pixel_weights(batch["video"], batch)
    assert weights.shape == (1, 1, 8, 1, 32, 64) and weights.mean().item() == pytest.approx(1.0)
    assert (weights.max() / weights.min()).item() == pytest.approx(10.0)
    boxed = weights[0, 0, :, 0] > weights.min()
    assert agents.any() and (boxed & agents).sum() / agents.sum() > 0.9  # the projected boxes hold the agents
    assert make_module().pixel_weights(batch["video"], batch) is None
    with pytest.raises(ValueError, match="needs agent boxes and camera specs"):
        module.pixel_weights(batch["video"], {"video": batch["video"]})


def test_agent_weight_buys_accuracy_inside_boxes(rig_clip) -> None:
    """The same tiny fit with and without the weight: the weighted run reconstructs the boxed pixels better."""
    batch, _ = rig_clip

    class Repeat(Dataset):
        def __len__(self) -> int:
            return 1_000_000

        def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
            return {k: v[0] for k, v in batch.items()}

    errors = {}
    for agents in (0.0, 30.0):
        module = make_module(discriminator=None, weights={"agents": agents}, sample_posterior=False)
        L.Trainer(max_steps=60, accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False,
                  enable_model_summary=False).fit(module, DataLoader(Repeat(), batch_size=1))
        boxed = make_module(weights={"agents": 1.0}).pixel_weights(batch["video"], batch)[:, :, :, 0] > 1.0
        with torch.no_grad():
            err = (module.tokenizer(batch["video"], sample=False).reconstruction - batch["video"]).pow(2).mean(dim=3)
        errors[agents] = float(err[boxed].mean())
    assert errors[30.0] < 0.7 * errors[0.0], errors


def test_a_refiner_fine_tune_starts_from_weights_without_it_and_learns(tmp_path: Path) -> None:
    """Stage 2 with a decoder refiner (docs/tokenizer.md, "Road users"): it loads a refiner-less stage-1
    checkpoint, starts from its reconstructions exactly, trains only the decoder, and overfitting two clips lowers
    the reconstruction loss at least 1.5× in 50 steps. Weights missing any other tensor are still refused."""
    stage1 = make_module()
    trainer, _ = fit(stage1, 2)
    ckpt = tmp_path / "stage1.ckpt"
    trainer.save_checkpoint(ckpt)

    refined_net = functools.partial(TINY_NET, refiner_channels=8, refiner_blocks=1, refiner_features=4)
    module = make_module(net=refined_net, stage="gan", init_from=str(ckpt), discriminator=None,
                         optim=functools.partial(torch.optim.AdamW, lr=3e-3, weight_decay=0.0))
    module.configure_model()
    module.load_init_weights()
    clips = FixedClips().clips
    with torch.no_grad():
        latents = stage1.net.encode(clips).mode()
        torch.testing.assert_close(module.net.decode(latents), stage1.net.decode(latents))
    encoder_before = snapshot(module.net.encoder)
    _, record = fit(module, 50)
    assert not changed(encoder_before, module.net.encoder)
    first = record.terms[0]["l1"] + record.terms[0]["l2"]
    last = sum(t["l1"] + t["l2"] for t in record.terms[-10:]) / 10
    assert last < first / 1.5, f"reconstruction loss {first:.3f} → {last:.3f}"

    state = {k: v for k, v in stage1.state_dict().items() if "decoder.stem" not in k}
    torch.save({"state_dict": state}, tmp_path / "partial.ckpt")
    broken = make_module(net=refined_net, stage="gan", init_from=str(tmp_path / "partial.ckpt"), discriminator=None)
    broken.configure_model()
    with pytest.raises(ValueError, match=r"missing \['decoder.stem"):
        broken.load_init_weights()


def test_widen_latents_starts_a_wider_tokenizer_from_narrow_weights(tmp_path: Path) -> None:
    """model.widen_latents (docs/tokenizer.md, "Road users"): 8-channel stage-1 weights start a 12-channel net that
    decodes the narrow net's latents as it did; without the flag the shapes are refused with the key."""
    stage1 = make_module()
    trainer, _ = fit(stage1, 1)
    trainer.save_checkpoint(tmp_path / "narrow.ckpt")
    wider = functools.partial(TINY_NET, latent_channels=12)
    module = make_module(net=wider, init_from=str(tmp_path / "narrow.ckpt"), widen_latents="unread")
    module.load_init_weights()
    clips = FixedClips().clips
    with torch.no_grad():
        narrow = stage1.net.encode(clips).mode()
        padded = torch.cat([narrow, torch.zeros(*narrow.shape[:3], 4, *narrow.shape[-2:])], dim=3)
        torch.testing.assert_close(module.net.decode(padded), stage1.net.decode(narrow))
    read = make_module(net=wider, init_from=str(tmp_path / "narrow.ckpt"), widen_latents="read")
    read.load_init_weights()
    assert read.net.decoder.stem.weight[:, 8:].abs().sum() > 0  # the new channels are read from the first step
    plain = make_module(net=wider, init_from=str(tmp_path / "narrow.ckpt"))
    with pytest.raises(ValueError, match="does not fit model.net"):
        plain.load_init_weights()
    with pytest.raises(ValueError, match="model.widen_latents=True"):
        make_module(widen_latents=True)
