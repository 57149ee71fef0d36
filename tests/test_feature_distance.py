"""FDD over a (random, small) DINO checkpoint: zero on itself, grows as images darken, names a missing file."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from gaia_app.eval.feature_distance import FeatureFrechetDistance, fdd
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
    assert fdd(dino_checkpoint, batch=16, **SMALL).update(images, True).update(images, False).compute() == pytest.approx(0, abs=1e-6)
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
