"""The `encoder` config group: every option composes at both mounts, and the paper run fails clearly without weights."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from gaia_app.encoders import VisionTeacher
from gaia_app.nn.vit import VisionTransformer
from tests.conftest import CONF_DIR, compose_config

OPTIONS = sorted(p.stem for p in (CONF_DIR / "encoder").glob("*.yaml"))


@pytest.mark.parametrize("mount", ["perceptual", "dino"])
@pytest.mark.parametrize("option", OPTIONS)
def test_every_encoder_option_composes_at_each_mount(option: str, mount: str, tmp_path: Path) -> None:
    cfg = compose_config("train", [f"encoder@model.{mount}={option}"], tmp_path)
    node = OmegaConf.to_container(cfg.model[mount], resolve=True)
    assert node == {} if option == "none" else node["kind"] == option


def test_paper_experiment_names_the_missing_checkpoint(tmp_path: Path) -> None:
    cfg = compose_config("train", ["experiment=gaia1/tokenizer_paper", "model/net=gaia1_tokenizer_tiny"], tmp_path)
    cfg.paths.root_dir = str(tmp_path)  # an empty project: no pretrained/ folder
    module = instantiate(cfg.model)
    expected = f"model.perceptual: checkpoint '{tmp_path}/pretrained/vgg16_features.pth'"
    with pytest.raises(FileNotFoundError, match=re.escape(expected)):
        module.load_frozen_networks()


def test_dino_option_loads_a_local_checkpoint(tmp_path: Path) -> None:
    """encoder@model.dino=dino_vits16 with its checkpoint in place: the module gets a frozen teacher."""
    (tmp_path / "pretrained").mkdir()
    torch.save(VisionTransformer(embed_dim=384, depth=12, num_heads=6).state_dict(),
               tmp_path / "pretrained" / "dino_vits16.pth")
    cfg = compose_config("train", ["encoder@model.dino=dino_vits16"], tmp_path)
    cfg.paths.root_dir = str(tmp_path)
    module = instantiate(cfg.model)
    module.load_frozen_networks()
    assert isinstance(module.frozen["dino"], VisionTeacher) and module.frozen["perceptual"] is None
    module.configure_model()
    assert module.tokenizer.distill_dim == module.frozen["dino"].feature_dim == 384
