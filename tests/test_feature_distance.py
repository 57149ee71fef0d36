"""FDD over a (random, small) DINO checkpoint and FID over a random Inception-v3 in the reference layout:
zero on itself, grow as images change, name a missing file."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from gaia_app.eval.feature_distance import FeatureFrechetDistance, fdd, fid
from gaia_app.nn.inception import InceptionV3Features
from gaia_app.nn.vit import VisionTransformer

SMALL = dict(embed_dim=32, depth=2, num_heads=2)


@pytest.fixture(scope="module")
def dino_checkpoint(tmp_path_factory) -> Path:
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("dino") / "small_dino.pth"
    torch.save(VisionTransformer(**SMALL).state_dict(), path)
    return path


def test_fdd_is_zero_on_itself_and_grows_with_darkening(dino_checkpoint: Path) -> None:
    g = torch.Generator().manual_seed(1)
    images = torch.nn.functional.avg_pool2d(torch.rand(48, 3, 64, 96, generator=g) * 2 - 1, 5, 1, 2)
    same = fdd(dino_checkpoint, batch=16, **SMALL).update(images, True).update(images, False).compute()
    assert same == pytest.approx(0, abs=1e-6)
    distances = [fdd(dino_checkpoint, **SMALL).update(images, True).update((images + 1) * k - 1, False).compute()
                 for k in (0.9, 0.6, 0.3)]
    assert 0 < distances[0] < distances[1] < distances[2]


def test_videos_are_scored_frame_by_frame_and_bad_shapes_are_named() -> None:
    metric = FeatureFrechetDistance(lambda x: x.mean((2, 3)), dim=3)
    metric.update(torch.rand(2, 5, 3, 8, 8), real=True)
    assert int(metric.real.count) == 10
    with pytest.raises(ValueError, match=r"got \(2, 1, 8, 8\)"):
        metric.update(torch.rand(2, 1, 8, 8), real=False)


def test_a_missing_checkpoint_is_named(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"eval.fdd: checkpoint '.*nowhere.pth' does not exist"):
        fdd(tmp_path / "nowhere.pth")


@pytest.fixture(scope="module")
def inception_checkpoint(tmp_path_factory) -> Path:
    """A random Inception-v3 saved like the FID reference weights: trunk + a 1008-way `fc` (dropped on load)."""
    torch.manual_seed(0)
    state = InceptionV3Features().state_dict()
    state |= {"fc.weight": torch.zeros(1008, 2048), "fc.bias": torch.zeros(1008),
              "AuxLogits.conv0.conv.weight": torch.zeros(128, 768, 1, 1)}
    path = tmp_path_factory.mktemp("inception") / "pt_inception.pth"
    torch.save(state, path)
    return path


def test_inception_trunk_follows_the_torchvision_layout() -> None:
    net = InceptionV3Features()
    state = net.state_dict()
    # torchvision inception_v3 minus fc and AuxLogits: 21,785,568 parameters
    assert sum(p.numel() for p in net.parameters()) == 21_785_568
    assert state["Conv2d_1a_3x3.conv.weight"].shape == (32, 3, 3, 3) and "Conv2d_1a_3x3.bn.running_var" in state
    assert state["Mixed_6b.branch7x7dbl_5.conv.weight"].shape == (192, 128, 1, 7)
    assert state["Mixed_7c.branch3x3dbl_3b.conv.weight"].shape == (384, 384, 3, 1)
    assert net.eval()(torch.zeros(1, 3, 64, 112)).shape == (1, 2048)


def test_fid_loads_reference_layout_and_is_zero_on_itself(inception_checkpoint: Path) -> None:
    g = torch.Generator().manual_seed(2)
    images = torch.nn.functional.avg_pool2d(torch.rand(4, 3, 64, 96, generator=g) * 2 - 1, 5, 1, 2)
    metric = fid(inception_checkpoint).update(images, real=True).update(images, real=False)
    assert metric.compute() == pytest.approx(0, abs=1e-6)
    assert metric.update(images * 0.2, real=False).compute() > 0  # darker frames join the generated set
    with pytest.raises(FileNotFoundError, match=r"eval.fid: checkpoint '.*missing.pth' does not exist"):
        fid(inception_checkpoint.parent / "missing.pth")
