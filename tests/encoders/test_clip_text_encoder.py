"""CLIP text conditioning (GAIA-2 report: CLIP embeddings) from a local directory, and GAIA-2's text width that
follows the configured encoder (issue: presets that disagree with their encoder crashed on the first batch)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra.utils import instantiate

from gaia_app.encoders.text import CLIPTextEncoder
from gaia_app.models.gaia2.conditioning import caption_vector
from tests.conftest import CLIP_PROJECTION, compose_config, save_tiny_clip

CAPTIONS = ["it is night.", "a winding road through the hills, heavy rain", ""]


def test_clip_features_live_in_the_joint_space_and_pooled_is_the_clip_embedding(tiny_clip_dir: Path) -> None:
    from transformers import CLIPTextModelWithProjection, CLIPTokenizer

    encoder = CLIPTextEncoder(tiny_clip_dir, dim=CLIP_PROJECTION, tokens=16)
    features = encoder([[c] for c in CAPTIONS])
    assert features.shape == (3, 1, 16, CLIP_PROJECTION)
    model = CLIPTextModelWithProjection.from_pretrained(tiny_clip_dir).eval()
    tokenizer = CLIPTokenizer.from_pretrained(tiny_clip_dir)
    with torch.no_grad():
        expected = torch.cat([model(**tokenizer([c], truncation=True, max_length=16, return_tensors="pt")).text_embeds
                              for c in CAPTIONS])  # the long caption is cut to m = 16 tokens, its end token kept
    torch.testing.assert_close(encoder.pooled(CAPTIONS), expected, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(caption_vector(encoder, CAPTIONS), expected, atol=1e-5, rtol=1e-4)
    real = tokenizer(CAPTIONS[0])["input_ids"]
    assert features[0, 0, len(real):].abs().max() == 0 and features[0, 0, len(real) - 1].abs().max() > 0
    assert not any(p.requires_grad for p in encoder.model.parameters()) and not list(encoder.parameters())


def test_a_whole_clip_directory_loads_its_text_tower(tmp_path: Path) -> None:
    """Users save the whole CLIPModel (model_type "clip"); only the text tower and its projection are read."""
    from transformers import CLIPConfig, CLIPModel, CLIPTextConfig, CLIPTokenizer

    text = save_tiny_clip(tmp_path / "text")
    whole = tmp_path / "whole"
    text_config = CLIPTextConfig.from_pretrained(text)
    vision = dict(hidden_size=16, intermediate_size=32, num_hidden_layers=1, num_attention_heads=2, image_size=32,
                  patch_size=16)
    config = CLIPConfig(text_config=text_config.to_dict(), vision_config=vision, projection_dim=CLIP_PROJECTION)
    CLIPModel(config).save_pretrained(whole)
    CLIPTokenizer.from_pretrained(text).save_pretrained(whole)
    encoder = CLIPTextEncoder(whole, dim=CLIP_PROJECTION, tokens=8)
    assert encoder.pooled(["stop"]).shape == (1, CLIP_PROJECTION)


def test_clip_errors_name_the_directory_and_the_width(tiny_clip_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError,
                       match=f"has output width {CLIP_PROJECTION}: set model.text_encoder.dim={CLIP_PROJECTION}"):
        CLIPTextEncoder(tiny_clip_dir, dim=768, tokens=16)
    with pytest.raises(FileNotFoundError, match=r"nowhere.*CLIP"):
        CLIPTextEncoder(tmp_path / "nowhere", dim=CLIP_PROJECTION)


@pytest.mark.parametrize("encoder", ["minilm", "clip", "none"])
def test_gaia2_text_width_follows_the_configured_encoder(encoder: str, tiny_clip_dir: Path, tmp_path: Path) -> None:
    overrides = {"minilm": [], "none": ["model.text_encoder=null"],
                 "clip": ["model/text_encoder=clip", f"model.text_encoder.path={tiny_clip_dir}",
                          f"model.text_encoder.dim={CLIP_PROJECTION}"]}[encoder]
    for net in ("gaia2_world_model_tiny", "gaia2_world_model_paper"):
        cfg = compose_config("train", ["experiment=gaia2/world_model_tiny", f"model/net={net}", *overrides], tmp_path)
        assert cfg.model.net.text_dim == {"minilm": 384, "clip": CLIP_PROJECTION, "none": 0}[encoder]
    cfg = compose_config("train", ["experiment=gaia2/world_model_tiny", *overrides], tmp_path)
    module = instantiate(cfg.model)
    module.configure_model()
    text = module.model.conditioner.text
    assert (text is None) if encoder == "none" else (text.in_features == cfg.model.net.text_dim)
    if encoder != "none":
        batch = {"text": ["It is night.", "It is snowing."], "mean": torch.zeros(2)}
        assert module.text_vector(batch).shape == (2, cfg.model.net.text_dim)
