"""Shared input handling of the frozen image networks: pixels in [-1, 1] → ImageNet statistics."""

from __future__ import annotations

import torch
from torch import nn

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class FrozenImageNetwork(nn.Module):
    """Base of the frozen networks: ImageNet normalisation buffers, and eval mode that `train()` cannot undo.

    The buffers are not persistent, so they never appear in (or are required from) a checkpoint.
    """

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def train(self, mode: bool = True) -> FrozenImageNetwork:
        # a parent's .train() must not switch a pretrained network out of eval mode
        return super().train(False)

    def normalize(self, image: torch.Tensor) -> torch.Tensor:
        """image: (b, 3, H, W) in [-1, 1] → ImageNet-normalised, in the network's dtype."""
        x = (image.to(self.mean.dtype) + 1) / 2
        return (x - self.mean) / self.std
