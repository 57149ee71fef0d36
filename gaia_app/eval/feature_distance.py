"""Fréchet distances over frozen image features: FID (Inception-v3), FDD (DINO, GAIA-2 §6), any other extractor.

An extractor maps images (b, 3, H, W) in [-1, 1] to features (b, d). Real and generated images stream in by
batches; the moments live in `FrechetStatistics` (float64, all-reduced over DDP ranks at `compute`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch

from gaia_app.encoders.inception import load_inception
from gaia_app.encoders.vision import load_vision_teacher
from gaia_app.eval.frechet import FrechetStatistics, frechet_distance
from gaia_app.nn.inception import FEATURE_DIM as INCEPTION_DIM

Extractor = Callable[[torch.Tensor], torch.Tensor]


class FeatureFrechetDistance:
    """Streaming Fréchet distance of `extractor` features between real and generated images."""

    def __init__(self, extractor: Extractor, dim: int, batch: int = 64):
        self.extractor, self.batch = extractor, batch
        self.real = FrechetStatistics(dim)
        self.generated = FrechetStatistics(dim)

    @torch.no_grad()
    def update(self, images: torch.Tensor, real: bool) -> FeatureFrechetDistance:
        """Add images (b, 3, H, W) in [-1, 1], or frames (b, t, 3, H, W) taken one by one; returns self."""
        if images.ndim == 5:
            images = images.flatten(0, 1)
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"expected images (b, 3, H, W) or videos (b, t, 3, H, W), got {tuple(images.shape)}")
        stats = self.real if real else self.generated
        for chunk in images.split(self.batch):
            stats.update(self.extractor(chunk))
        return self

    def compute(self) -> float:
        return frechet_distance(self.real.all_reduce(), self.generated.all_reduce())

    def fresh(self) -> FeatureFrechetDistance:
        """A new, empty metric over the same (already loaded) extractor."""
        return FeatureFrechetDistance(self.extractor, self.real.dim, self.batch)


def fdd(checkpoint: str | Path, kind: str = "dino_vits16", config_key: str = "eval.fdd", batch: int = 64,
        **arch_overrides: int | None) -> FeatureFrechetDistance:
    """Fréchet DINO Distance over the class-token embedding of a local DINO checkpoint (the DINO teacher's
    loader: a missing file raises FileNotFoundError naming `config_key` and the path)."""
    teacher = load_vision_teacher(kind, checkpoint, config_key, **arch_overrides)
    return FeatureFrechetDistance(teacher.embed, teacher.feature_dim, batch)


def fid(checkpoint: str | Path, config_key: str = "eval.fid", batch: int = 32,
        fid_variant: bool = True) -> FeatureFrechetDistance:
    """Fréchet Inception Distance over the pool3 features of a local Inception-v3 checkpoint (the FID reference
    weights, or torchvision's with fid_variant=False); frames are resized to 299 × 299."""
    network = load_inception(checkpoint, config_key, fid_variant)
    return FeatureFrechetDistance(network, INCEPTION_DIM, batch)
