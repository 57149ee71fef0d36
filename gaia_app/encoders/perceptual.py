"""Frozen perceptual distance for the tokenizer's reconstruction loss (GAIA-1 §2.2, ref. [32]), local weights only.

Legend: b batch, c channels, H W image size.

LPIPS-style "VGG feature distance": VGG16 activations at relu1_2 … relu5_3, each unit-normalised
over channels, squared differences summed over channels (or weighted by LPIPS's learned linear
heads when given), averaged over space, then averaged over the five layers. With the official
LPIPS heads this is LPIPS(vgg) / 5.
"""

from __future__ import annotations

import re
from pathlib import Path

import torch
from torch import nn

from gaia_app.encoders.checkpoints import StateDict, freeze, load_exact, read_state_dict
from gaia_app.encoders.images import FrozenImageNetwork
from gaia_app.nn.vgg import VGG16Features

PERCEPTUAL_KINDS = ("vgg16",)


def unit_normalize(features: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    """(b, c, h, w) → each spatial feature vector scaled to unit L2 norm over c (LPIPS)."""
    return features / (features.pow(2).sum(dim=1, keepdim=True).sqrt() + eps)


class PerceptualDistance(FrozenImageNetwork):
    """Distance between two image batches in frozen VGG16 feature space.

    Args:
        trunk: the VGG16 feature trunk (weights loaded).
        heads: LPIPS's per-layer 1×1 channel weightings (c_k → 1, no bias), or None for the plain
            channel sum ("VGG feature distance").
    """

    def __init__(self, trunk: VGG16Features, heads: nn.ModuleList | None = None):
        super().__init__()
        self.trunk = trunk
        self.heads = heads

    def forward(self, x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """x, target: (b, 3, H, W) in [-1, 1] → (b,) distances. Gradients flow to x only."""
        features = self.trunk(self.normalize(x))
        with torch.no_grad():
            target_features = self.trunk(self.normalize(target))
        per_layer = [self.layer_distance(k, f, t) for k, (f, t) in enumerate(zip(features, target_features))]
        return torch.stack(per_layer).mean(dim=0)

    @torch.no_grad()
    def distance_map(self, x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """x, target: (b, 3, H, W) in [-1, 1] → (b, H, W): each tap's per-pixel distance upsampled to the input size
        and averaged over taps (LPIPS's spatial output); its spatial mean is close to `forward`'s distance."""
        features, target_features = self.trunk(self.normalize(x)), self.trunk(self.normalize(target))
        maps = []
        for k, (f, t) in enumerate(zip(features, target_features)):
            diff = (unit_normalize(f) - unit_normalize(t)).pow(2)
            diff = self.heads[k](diff) if self.heads is not None else diff.sum(dim=1, keepdim=True)
            maps.append(nn.functional.interpolate(diff, size=x.shape[-2:], mode="bilinear", align_corners=False))
        return torch.stack(maps).mean(dim=0)[:, 0]

    def layer_distance(self, k: int, features: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """(b, c, h, w) pair at tap k → (b,) spatially averaged distance."""
        diff = (unit_normalize(features) - unit_normalize(target)).pow(2)
        diff = self.heads[k](diff) if self.heads is not None else diff.sum(dim=1, keepdim=True)
        return diff.mean(dim=(1, 2, 3))


def vgg_features_state_dict(state: StateDict) -> StateDict:
    """Accept torchvision's `vgg16().features` (keys `N.weight`) or `vgg16()` (keys `features.N.weight`,
    plus the classifier, which the perceptual loss does not use) and return `features.N.*` keys."""
    out = {}
    for key, value in state.items():
        if key.startswith("classifier."):
            continue
        out[key if key.startswith("features.") or not key[:1].isdigit() else f"features.{key}"] = value
    return out


def lpips_heads_state_dict(state: StateDict) -> StateDict:
    """Map the official LPIPS head keys `lin{k}.model.{0|1}.weight` (with/without dropout) to `{k}.weight`."""
    out = {}
    for key, value in state.items():
        match = re.fullmatch(r"lin(\d+)\.model\.\d+\.weight", key)
        out[f"{match.group(1)}.weight" if match else key] = value
    return out


def load_lpips_heads(trunk: VGG16Features, heads_checkpoint: str | Path, config_key: str) -> nn.ModuleList:
    """The five LPIPS linear heads from a local `vgg.pth` of richzhang/PerceptualSimilarity."""
    heads = nn.ModuleList(nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in trunk.tap_channels())
    state = lpips_heads_state_dict(read_state_dict(heads_checkpoint, f"{config_key}.heads_checkpoint"))
    load_exact(heads, state, f"{config_key}.heads_checkpoint '{heads_checkpoint}'")
    return heads


def load_perceptual(
    kind: str = "vgg16",
    checkpoint: str | Path = "",
    heads_checkpoint: str | Path | None = None,
    config_key: str = "model.perceptual",
    base_width: int = 64,
) -> PerceptualDistance:
    """Build the perceptual network `kind` and load its weights from local files; frozen, eval mode.

    checkpoint: VGG16 weights saved from torchvision (`vgg16().features` or `vgg16()` state dict).
    heads_checkpoint: optional LPIPS linear heads; None = plain VGG feature distance.
    base_width: 64 = VGG16; smaller values give test networks of the same layout.
    Raises FileNotFoundError (missing file) or StateDictMismatchError (wrong keys or shapes).
    """
    if kind not in PERCEPTUAL_KINDS:
        raise ValueError(f"{config_key}.kind={kind!r}: known perceptual networks are {list(PERCEPTUAL_KINDS)}; "
                         f"{config_key}=none switches the loss off")
    trunk = VGG16Features(base_width=base_width)
    state = vgg_features_state_dict(read_state_dict(checkpoint, config_key))
    load_exact(trunk, state, f"{config_key}.checkpoint '{checkpoint}' (kind {kind})")
    heads = load_lpips_heads(trunk, heads_checkpoint, config_key) if heads_checkpoint else None
    return freeze(PerceptualDistance(trunk, heads))
