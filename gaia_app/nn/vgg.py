"""VGG16 convolutional trunk with torchvision's `vgg16().features` layout (the perceptual network).

Legend: b batch, c channels, h w spatial size.

`features` is an nn.Sequential whose indices match torchvision's, so the parameter names are
`features.N.weight` / `features.N.bias` (N in 0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28) and a
state dict saved from torchvision's VGG16 loads unchanged. Pure torch: torchvision must not be
installed next to the CPU torch build (shared/ECOSYSTEM.md §0).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

# conv widths of VGG configuration "D" (Simonyan & Zisserman 2015); "M" = 2×2 max-pool
VGG16_LAYOUT: tuple[int | str, ...] = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M",
                                       512, 512, 512, "M")
# `features` indices of the ReLUs after conv1_2, conv2_2, conv3_3, conv4_3, conv5_3: the LPIPS taps
LPIPS_TAPS: tuple[int, ...] = (3, 8, 15, 22, 29)


def vgg_layers(layout: Sequence[int | str], base_width: int) -> list[nn.Module]:
    """Conv3×3 + ReLU per width and MaxPool per "M"; widths scale by base_width / 64 (64 = real VGG16)."""
    layers: list[nn.Module] = []
    prev = 3
    for item in layout:
        if item == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
            continue
        width = int(item) * base_width // 64
        # not in-place (torchvision's are): tapped activations must stay intact for the loss
        layers += [nn.Conv2d(prev, width, kernel_size=3, padding=1), nn.ReLU()]
        prev = width
    return layers


class VGG16Features(nn.Module):
    """VGG16 trunk returning the activations at `taps`.

    Args:
        base_width: channels of the first stage; 64 is the real VGG16 (smaller values give test nets
            of the same layout).
        taps: `features` indices whose outputs are returned (default: the five LPIPS layers).
    """

    def __init__(self, base_width: int = 64, taps: Sequence[int] = LPIPS_TAPS):
        super().__init__()
        self.features = nn.Sequential(*vgg_layers(VGG16_LAYOUT, base_width))
        if not taps or max(taps) >= len(self.features):
            raise ValueError(f"VGG16Features: taps must index features[0..{len(self.features) - 1}], got {tuple(taps)}")
        self.taps = tuple(sorted(taps))

    def tap_channels(self) -> list[int]:
        """Channels of each tapped activation, in tap order."""
        channels, width = [], 3
        for i, layer in enumerate(self.features):
            width = layer.out_channels if isinstance(layer, nn.Conv2d) else width
            if i in self.taps:
                channels.append(width)
        return channels

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """x: (b, 3, h, w) ImageNet-normalised → [(b, c_k, h / 2^k, w / 2^k)] at each tap."""
        outputs = []
        for i, layer in enumerate(self.features[: self.taps[-1] + 1]):
            x = layer(x)
            if i in self.taps:
                outputs.append(x)
        return outputs
