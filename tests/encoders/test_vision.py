"""DINO teacher (GAIA-1 §2.2): official key layout, local loading, clear errors, distillation semantics."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from gaia_app.encoders import StateDictMismatchError, distillation_loss, load_vision_teacher
from gaia_app.models.gaia1.tokenizer import ImageTokenizer
from gaia_app.nn.vit import LayerScale, VisionTransformer

SMALL = dict(embed_dim=32, depth=2, num_heads=2)
DINOV2 = dict(image_size=518, patch_size=14, layer_scale=True, mask_token=True)  # hub dinov2_*14 layout


@pytest.fixture(scope="module")
def vits16(tmp_path_factory) -> tuple[VisionTransformer, Path]:
    """A randomly initialised ViT-S/16 (the real dino_vits16 architecture) saved like an official checkpoint."""
    torch.manual_seed(0)
    vit = VisionTransformer(embed_dim=384, depth=12, num_heads=6).eval()
    path = tmp_path_factory.mktemp("dino") / "dino_vits16.pth"
    torch.save(vit.state_dict(), path)
    return vit, path


def test_parameter_names_follow_official_dino(vits16) -> None:
    state = vits16[0].state_dict()
    for key in ("cls_token", "pos_embed", "patch_embed.proj.weight", "blocks.11.norm1.weight", "blocks.0.attn.qkv.bias",
                "blocks.0.attn.proj.weight", "blocks.0.norm2.bias", "blocks.0.mlp.fc1.weight", "blocks.0.mlp.fc2.bias",
                "norm.weight"):
        assert key in state
    assert state["pos_embed"].shape == (1, 197, 384) and state["blocks.0.attn.qkv.weight"].shape == (1152, 384)
    # ViT-S/16 of DINO: 21.7M parameters
    assert sum(v.numel() for v in state.values()) == pytest.approx(21.7e6, rel=0.01)


def test_loaded_vits16_gives_identical_outputs(vits16) -> None:
    vit, path = vits16
    teacher = load_vision_teacher(kind="dino_vits16", checkpoint=path)
    x = torch.randn(2, 3, 224, 224)
    assert torch.equal(teacher.vit(x), vit(x))
    image = torch.rand(2, 3, 64, 96) * 2 - 1
    features = teacher(image)
    assert features.shape == (2, 384, 4, 6)
    assert torch.equal(features, vit.patch_features(teacher.normalize(image)))


def test_teacher_is_frozen_and_stays_in_eval_mode(vits16) -> None:
    teacher = load_vision_teacher(kind="dino_vits16", checkpoint=vits16[1])
    teacher.train()
    assert not teacher.training and not teacher.vit.training
    assert not any(p.requires_grad for p in teacher.parameters())


def test_positional_embedding_interpolates_to_other_grids() -> None:
    torch.manual_seed(0)
    vit = VisionTransformer(image_size=64, **SMALL)  # stored grid 4×4
    assert vit.positional_embedding(4, 4) is vit.pos_embed
    wide = vit.positional_embedding(3, 8)
    assert wide.shape == (1, 1 + 24, 32)
    assert torch.equal(wide[:, 0], vit.pos_embed[:, 0])  # cls position untouched
    assert vit.patch_features(torch.randn(1, 3, 48, 128)).shape == (1, 32, 3, 8)


def test_teacher_resizes_images_to_whole_patches(tmp_path: Path) -> None:
    torch.manual_seed(0)
    torch.save(VisionTransformer(**SMALL).state_dict(), tmp_path / "small.pth")
    teacher = load_vision_teacher(checkpoint=tmp_path / "small.pth", **SMALL)
    assert teacher(torch.zeros(1, 3, 70, 100)).shape == (1, 32, 4, 6)  # 70/16 → 4, 100/16 → 6


def test_missing_file_names_key_path_and_switch(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere" / "dino_vits16.pth"
    with pytest.raises(FileNotFoundError) as err:
        load_vision_teacher(kind="dino_vits16", checkpoint=missing)
    message = str(err.value)
    assert str(missing) in message and "model.dino" in message and "model.dino=none" in message


def test_wrong_keys_are_listed(tmp_path: Path) -> None:
    torch.manual_seed(0)
    state = VisionTransformer(**SMALL).state_dict()
    state["blocks.0.attention.qkv.weight"] = state.pop("blocks.0.attn.qkv.weight")
    torch.save(state, tmp_path / "renamed.pth")
    with pytest.raises(StateDictMismatchError) as err:
        load_vision_teacher(checkpoint=tmp_path / "renamed.pth", **SMALL)
    assert "missing keys (1): ['blocks.0.attn.qkv.weight']" in str(err.value)
    assert "unexpected keys (1): ['blocks.0.attention.qkv.weight']" in str(err.value)


def test_wrong_architecture_reports_shapes(vits16) -> None:
    with pytest.raises(StateDictMismatchError, match="shape mismatches"):
        load_vision_teacher(kind="dino_vitb16", checkpoint=vits16[1])


def test_training_run_prefixes_and_head_are_handled(tmp_path: Path) -> None:
    torch.manual_seed(0)
    vit = VisionTransformer(**SMALL)
    exported = {f"module.backbone.{k}": v for k, v in vit.state_dict().items()}
    exported["module.head.last_layer.weight"] = torch.zeros(3)  # the DINO projection head: dropped
    torch.save(exported, tmp_path / "teacher.pth")
    teacher = load_vision_teacher(checkpoint=tmp_path / "teacher.pth", **SMALL)
    assert torch.equal(teacher.vit.cls_token, vit.cls_token)


def test_unknown_kind_is_named(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="dino_vits16"):
        load_vision_teacher(kind="dinov3_giant", checkpoint=tmp_path / "x.pth")


def test_distillation_loss_is_one_minus_cosine() -> None:
    torch.manual_seed(0)
    features = torch.randn(2, 8, 3, 5)
    assert distillation_loss(features, features).abs().item() < 1e-6
    assert distillation_loss(features, 3.0 * features).abs().item() < 1e-6  # scale-free
    assert distillation_loss(features, -features).item() == pytest.approx(2.0)
    # teacher on a coarser grid is resized (bilinear) to the student's token grid
    assert distillation_loss(torch.ones(1, 4, 6, 6), torch.ones(1, 4, 2, 2)).abs().item() < 1e-6


def test_distillation_gradient_reaches_the_tokenizer_projection_not_the_teacher(tmp_path: Path) -> None:
    torch.manual_seed(0)
    torch.save(VisionTransformer(**SMALL).state_dict(), tmp_path / "small.pth")
    teacher = load_vision_teacher(checkpoint=tmp_path / "small.pth", **SMALL)
    tokenizer = ImageTokenizer(channels=8, channel_mults=(1, 2, 2), blocks_per_stage=1, latent_dim=16,
                               codebook_size=32, code_dim=8, distill_dim=32)
    image = torch.rand(2, 3, 32, 32) * 2 - 1
    out = tokenizer(image)
    distillation_loss(tokenizer.distill(out.quantized), teacher(image)).backward()
    assert tokenizer.distill_head.weight.grad.abs().sum() > 0
    assert tokenizer.encoder.stem.weight.grad.abs().sum() > 0  # through the straight-through quantiser
    assert all(p.grad is None for p in tokenizer.decoder.parameters())
    assert all(p.grad is None and not p.requires_grad for p in teacher.parameters())


# --- DINOv2 (facebookresearch/dinov2 hub backbones: patch 14, 518-pixel training, LayerScale, mask_token) ---


def test_dinov2_parameter_names_follow_official_hub_layout() -> None:
    torch.manual_seed(0)
    state = VisionTransformer(embed_dim=384, depth=12, num_heads=6, **DINOV2).state_dict()
    for key in ("cls_token", "pos_embed", "mask_token", "patch_embed.proj.weight", "patch_embed.proj.bias",
                "blocks.0.norm1.weight", "blocks.0.attn.qkv.bias", "blocks.0.attn.proj.weight", "blocks.0.ls1.gamma",
                "blocks.0.norm2.bias", "blocks.0.mlp.fc1.weight", "blocks.0.mlp.fc2.bias", "blocks.11.ls2.gamma",
                "norm.weight", "norm.bias"):
        assert key in state
    assert state["pos_embed"].shape == (1, 1 + 37 * 37, 384) and state["mask_token"].shape == (1, 384)
    assert state["patch_embed.proj.weight"].shape == (384, 3, 14, 14) and state["blocks.0.ls1.gamma"].shape == (384,)
    assert torch.equal(state["blocks.3.ls2.gamma"], torch.ones(384))  # hub models use init_values=1.0
    # dinov2_vits14 has exactly 22,056,576 parameters
    assert sum(v.numel() for v in state.values()) == 22_056_576


def test_dino_v1_layout_has_no_dinov2_keys() -> None:
    state = VisionTransformer(**SMALL).state_dict()
    assert not any(".ls" in k or k == "mask_token" for k in state)


def test_loaded_dinov2_gives_identical_outputs(tmp_path: Path) -> None:
    torch.manual_seed(0)
    vit = VisionTransformer(**SMALL, **DINOV2).eval()
    with torch.no_grad():  # non-trivial gammas and mask token, so loading them is checked too
        for block in vit.blocks:
            block.ls1.gamma.uniform_(0.5, 1.5)
            block.ls2.gamma.uniform_(0.5, 1.5)
        vit.mask_token.normal_()
    torch.save(vit.state_dict(), tmp_path / "dinov2_vits14.pth")
    teacher = load_vision_teacher(kind="dinov2_vits14", checkpoint=tmp_path / "dinov2_vits14.pth", **SMALL)
    assert teacher.vit.base_grid == 37 and teacher.vit.patch_size == 14
    assert all(torch.equal(a, b) for a, b in zip(teacher.vit.state_dict().values(), vit.state_dict().values()))
    image = torch.rand(2, 3, 56, 84) * 2 - 1
    features = teacher(image)
    assert features.shape == (2, 32, 4, 6)  # (b, d, H/14, W/14)
    assert torch.equal(features, vit.patch_features(teacher.normalize(image)))
    cls = teacher.embed(image)
    assert cls.shape == (2, 32)
    assert torch.equal(cls, vit(teacher.normalize(image))[:, 0])
    # at the stored 518-pixel grid no interpolation happens
    x = torch.randn(1, 3, 518, 518)
    assert teacher.vit.positional_embedding(37, 37) is teacher.vit.pos_embed
    assert torch.equal(teacher.vit(x), vit(x))


def test_dinov2_teacher_is_frozen(tmp_path: Path) -> None:
    torch.manual_seed(0)
    torch.save(VisionTransformer(**SMALL, **DINOV2).state_dict(), tmp_path / "v2.pth")
    teacher = load_vision_teacher(kind="dinov2_vitb14", checkpoint=tmp_path / "v2.pth", **SMALL)
    teacher.train()
    assert not teacher.training and not any(p.requires_grad for p in teacher.parameters())
    assert teacher(torch.zeros(1, 3, 70, 100)).shape == (1, 32, 5, 7)  # 70/14 → 5, 100/14 → 7


def test_dino_v1_checkpoint_given_as_dinov2_is_rejected(tmp_path: Path) -> None:
    torch.manual_seed(0)
    torch.save(VisionTransformer(**SMALL).state_dict(), tmp_path / "dino_v1.pth")
    with pytest.raises(StateDictMismatchError) as err:
        load_vision_teacher(kind="dinov2_vits14", checkpoint=tmp_path / "dino_v1.pth", **SMALL)
    message = str(err.value)
    assert "missing keys (5): ['blocks.0.ls1.gamma', 'blocks.0.ls2.gamma'" in message and "'mask_token'" in message
    assert "patch_embed.proj.weight: checkpoint (32, 3, 16, 16) vs model (32, 3, 14, 14)" in message


def test_dinov2_checkpoint_given_as_dino_v1_is_rejected(tmp_path: Path) -> None:
    torch.manual_seed(0)
    torch.save(VisionTransformer(**SMALL, **DINOV2).state_dict(), tmp_path / "dinov2.pth")
    with pytest.raises(StateDictMismatchError, match=r"unexpected keys \(5\): \['blocks.0.ls1.gamma'"):
        load_vision_teacher(kind="dino_vits16", checkpoint=tmp_path / "dinov2.pth", **SMALL)


def test_layer_scale_gammas_scale_the_residual_branches() -> None:
    torch.manual_seed(0)
    vit = VisionTransformer(**SMALL, **DINOV2).eval()
    x = torch.randn(2, 3, 28, 42)
    with torch.no_grad():
        embedding = torch.cat([vit.cls_token.expand(2, -1, -1), vit.patch_embed(x)], dim=1)
        embedding = embedding + vit.positional_embedding(2, 3)
        assert not torch.allclose(vit(x), vit.norm(embedding))  # gammas 1: the blocks act
        for module in vit.modules():
            if isinstance(module, LayerScale):
                module.gamma.zero_()
        assert torch.equal(vit(x), vit.norm(embedding))  # gammas 0: every block is the identity
        # placement: x + ls1(attn(norm1(x))), then + ls2(mlp(norm2(·))), gammas per channel
        block, tokens = vit.blocks[0], torch.randn(2, 7, 32)
        block.ls1.gamma.copy_(torch.linspace(-1.0, 2.0, 32))
        block.ls2.gamma.fill_(0.5)
        h = tokens + block.ls1.gamma * block.attn(block.norm1(tokens))
        assert torch.allclose(block(tokens), h + 0.5 * block.mlp(block.norm2(h)), atol=1e-6)


def test_dinov2_mask_token_does_not_affect_features() -> None:
    torch.manual_seed(0)
    vit = VisionTransformer(**SMALL, **DINOV2).eval()
    x = torch.randn(1, 3, 28, 28)
    before = vit(x)
    with torch.no_grad():
        vit.mask_token.fill_(100.0)
    assert torch.equal(vit(x), before)
