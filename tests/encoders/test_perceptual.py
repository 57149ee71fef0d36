"""Perceptual network (GAIA-1 §2.2, ref. [32]): torchvision VGG16 layout, local loading, LPIPS-style distance."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from gaia_app.encoders import StateDictMismatchError, load_perceptual
from gaia_app.encoders.perceptual import unit_normalize
from gaia_app.nn.vgg import VGG16Features

# conv indices of torchvision's vgg16().features (configuration "D")
TORCHVISION_CONVS = (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28)


@pytest.fixture(scope="module")
def vgg16(tmp_path_factory) -> tuple[VGG16Features, Path]:
    """A randomly initialised full-size VGG16 trunk, saved as torchvision's `vgg16().features.state_dict()` (keys
    `N.weight`)."""
    torch.manual_seed(0)
    trunk = VGG16Features()
    path = tmp_path_factory.mktemp("vgg") / "vgg16_features.pth"
    torch.save({k.removeprefix("features."): v for k, v in trunk.state_dict().items()}, path)
    return trunk, path


def test_layout_matches_torchvision_vgg16_features(vgg16) -> None:
    state = vgg16[0].state_dict()
    assert sorted(state) == sorted(f"features.{i}.{p}" for i in TORCHVISION_CONVS for p in ("weight", "bias"))
    assert state["features.0.weight"].shape == (64, 3, 3, 3)
    assert state["features.28.weight"].shape == (512, 512, 3, 3)
    assert sum(v.numel() for v in state.values()) == 14_714_688  # torchvision vgg16().features
    assert vgg16[0].tap_channels() == [64, 128, 256, 512, 512]


def test_loaded_vgg16_gives_identical_distances(vgg16) -> None:
    trunk, path = vgg16
    distance = load_perceptual(kind="vgg16", checkpoint=path)
    x, y = torch.rand(2, 3, 32, 48) * 2 - 1, torch.rand(2, 3, 32, 48) * 2 - 1
    for mine, theirs in zip(distance.trunk(distance.normalize(x)), trunk(distance.normalize(x))):
        assert torch.equal(mine, theirs)
    expected = torch.stack([
        (unit_normalize(a) - unit_normalize(b)).pow(2).sum(1).mean((1, 2))
        for a, b in zip(trunk(distance.normalize(x)), trunk(distance.normalize(y)))
    ]).mean(0)
    assert torch.allclose(distance(x, y), expected, atol=1e-6)


def test_full_torchvision_state_dict_loads_without_classifier(vgg16, tmp_path: Path) -> None:
    trunk, _ = vgg16
    full = dict(trunk.state_dict()) | {"classifier.0.weight": torch.zeros(8, 4)}
    torch.save(full, tmp_path / "vgg16.pth")
    distance = load_perceptual(checkpoint=tmp_path / "vgg16.pth")
    assert torch.equal(distance.trunk.features[28].weight, trunk.features[28].weight)


def test_distance_properties_and_frozen_trunk(tmp_path: Path) -> None:
    torch.manual_seed(0)
    torch.save(VGG16Features(base_width=8).state_dict(), tmp_path / "small.pth")
    distance = load_perceptual(checkpoint=tmp_path / "small.pth", base_width=8)
    distance.train()
    assert not distance.training and not any(p.requires_grad for p in distance.parameters())
    x = (torch.rand(2, 3, 32, 32) * 2 - 1).requires_grad_()
    assert distance(x, x.detach()).abs().max().item() < 1e-6
    d = distance(x, torch.rand(2, 3, 32, 32) * 2 - 1)
    assert d.shape == (2,) and (d > 0).all()
    d.sum().backward()
    assert x.grad.abs().sum() > 0 and all(p.grad is None for p in distance.parameters())


def test_lpips_heads_load_from_official_key_names(tmp_path: Path) -> None:
    torch.manual_seed(0)
    trunk = VGG16Features(base_width=8)
    torch.save(trunk.state_dict(), tmp_path / "small.pth")
    weights = [torch.rand(1, c, 1, 1) for c in trunk.tap_channels()]
    torch.save({f"lin{k}.model.1.weight": w for k, w in enumerate(weights)}, tmp_path / "lpips_vgg.pth")
    distance = load_perceptual(checkpoint=tmp_path / "small.pth", heads_checkpoint=tmp_path / "lpips_vgg.pth",
                               base_width=8)
    x, y = torch.rand(1, 3, 32, 32) * 2 - 1, torch.rand(1, 3, 32, 32) * 2 - 1
    feats_x, feats_y = trunk(distance.normalize(x)), trunk(distance.normalize(y))
    per_layer = [((unit_normalize(a) - unit_normalize(b)).pow(2) * w).sum(1).mean()
                 for a, b, w in zip(feats_x, feats_y, weights)]
    expected = sum(per_layer) / 5
    assert distance(x, y).item() == pytest.approx(expected.item(), rel=1e-5)


def test_missing_file_names_key_path_and_switch(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError) as err:
        load_perceptual(kind="vgg16", checkpoint=tmp_path / "vgg16_features.pth")
    assert str(tmp_path / "vgg16_features.pth") in str(err.value) and "model.perceptual=none" in str(err.value)


def test_wrong_keys_are_listed(tmp_path: Path) -> None:
    state = VGG16Features(base_width=8).state_dict()
    state["features.99.weight"] = state.pop("features.28.weight")
    torch.save(state, tmp_path / "bad.pth")
    with pytest.raises(StateDictMismatchError) as err:
        load_perceptual(checkpoint=tmp_path / "bad.pth", base_width=8)
    assert "['features.28.weight']" in str(err.value) and "['features.99.weight']" in str(err.value)
