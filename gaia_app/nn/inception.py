"""Inception-v3 feature trunk for FID (Szegedy et al. 2016; Heusel et al. 2017), weights from a local file.

Legend: b batch, images resized to 299 × 299.

Module names follow torchvision's `Inception3` (`Conv2d_1a_3x3.conv.weight`, `Mixed_5b.branch1x1.bn.running_mean`,
...), which is also the layout of the FID reference weights `pt_inception-2015-12-05` that pytorch-fid distributes;
either state dict loads after dropping `fc.*` and `AuxLogits.*`. `fid_variant=True` reproduces the reference
network's pooling quirks (the TensorFlow graph FID was defined with): average pools that exclude padding in the
A, C and first E blocks, and a max pool in the last E block's pool branch. The output is the 2048-d `pool3`
feature FID is computed on.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

FEATURE_DIM = 2048


class BasicConv2d(nn.Module):
    """Conv (no bias) → BatchNorm (ε = 0.001) → ReLU."""

    def __init__(self, in_channels: int, out_channels: int, **conv: int | tuple[int, int]):
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, bias=False, **conv)
        self.bn = nn.BatchNorm2d(out_channels, eps=0.001)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.bn(self.conv(x)))


def _avg_pool(x: torch.Tensor, fid_variant: bool) -> torch.Tensor:
    return F.avg_pool2d(x, 3, stride=1, padding=1, count_include_pad=not fid_variant)


class InceptionA(nn.Module):
    """35×35 block: 1×1 | 1×1→5×5 | 1×1→3×3→3×3 | pool→1×1; out 224 + pool_features channels."""

    def __init__(self, in_channels: int, pool_features: int, fid_variant: bool):
        super().__init__()
        self.fid_variant = fid_variant
        self.branch1x1 = BasicConv2d(in_channels, 64, kernel_size=1)
        self.branch5x5_1 = BasicConv2d(in_channels, 48, kernel_size=1)
        self.branch5x5_2 = BasicConv2d(48, 64, kernel_size=5, padding=2)
        self.branch3x3dbl_1 = BasicConv2d(in_channels, 64, kernel_size=1)
        self.branch3x3dbl_2 = BasicConv2d(64, 96, kernel_size=3, padding=1)
        self.branch3x3dbl_3 = BasicConv2d(96, 96, kernel_size=3, padding=1)
        self.branch_pool = BasicConv2d(in_channels, pool_features, kernel_size=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([
            self.branch1x1(x),
            self.branch5x5_2(self.branch5x5_1(x)),
            self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x))),
            self.branch_pool(_avg_pool(x, self.fid_variant)),
        ], dim=1)


class InceptionB(nn.Module):
    """35 → 17 reduction: 3×3 s2 | 1×1→3×3→3×3 s2 | max pool s2; out 480 + in channels."""

    def __init__(self, in_channels: int):
        super().__init__()
        self.branch3x3 = BasicConv2d(in_channels, 384, kernel_size=3, stride=2)
        self.branch3x3dbl_1 = BasicConv2d(in_channels, 64, kernel_size=1)
        self.branch3x3dbl_2 = BasicConv2d(64, 96, kernel_size=3, padding=1)
        self.branch3x3dbl_3 = BasicConv2d(96, 96, kernel_size=3, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([
            self.branch3x3(x),
            self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x))),
            F.max_pool2d(x, 3, stride=2),
        ], dim=1)


def _seven(channels_in: int, channels_out: int, vertical: bool) -> BasicConv2d:
    """A factorised 7-tap convolution, (7, 1) when vertical else (1, 7), same padding."""
    kernel, padding = ((7, 1), (3, 0)) if vertical else ((1, 7), (0, 3))
    return BasicConv2d(channels_in, channels_out, kernel_size=kernel, padding=padding)


class InceptionC(nn.Module):
    """17×17 block with factorised 7×7 convolutions of width c7; out 768 channels."""

    def __init__(self, in_channels: int, channels_7x7: int, fid_variant: bool):
        super().__init__()
        c7, self.fid_variant = channels_7x7, fid_variant
        self.branch1x1 = BasicConv2d(in_channels, 192, kernel_size=1)
        self.branch7x7_1 = BasicConv2d(in_channels, c7, kernel_size=1)
        self.branch7x7_2 = _seven(c7, c7, vertical=False)
        self.branch7x7_3 = _seven(c7, 192, vertical=True)
        self.branch7x7dbl_1 = BasicConv2d(in_channels, c7, kernel_size=1)
        self.branch7x7dbl_2 = _seven(c7, c7, vertical=True)
        self.branch7x7dbl_3 = _seven(c7, c7, vertical=False)
        self.branch7x7dbl_4 = _seven(c7, c7, vertical=True)
        self.branch7x7dbl_5 = _seven(c7, 192, vertical=False)
        self.branch_pool = BasicConv2d(in_channels, 192, kernel_size=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        double = x
        for layer in (self.branch7x7dbl_1, self.branch7x7dbl_2, self.branch7x7dbl_3, self.branch7x7dbl_4,
                      self.branch7x7dbl_5):
            double = layer(double)
        return torch.cat([
            self.branch1x1(x),
            self.branch7x7_3(self.branch7x7_2(self.branch7x7_1(x))),
            double,
            self.branch_pool(_avg_pool(x, self.fid_variant)),
        ], dim=1)


class InceptionD(nn.Module):
    """17 → 8 reduction: 1×1→3×3 s2 | 1×1→1×7→7×1→3×3 s2 | max pool s2; out 512 + in channels."""

    def __init__(self, in_channels: int):
        super().__init__()
        self.branch3x3_1 = BasicConv2d(in_channels, 192, kernel_size=1)
        self.branch3x3_2 = BasicConv2d(192, 320, kernel_size=3, stride=2)
        self.branch7x7x3_1 = BasicConv2d(in_channels, 192, kernel_size=1)
        self.branch7x7x3_2 = _seven(192, 192, vertical=False)
        self.branch7x7x3_3 = _seven(192, 192, vertical=True)
        self.branch7x7x3_4 = BasicConv2d(192, 192, kernel_size=3, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        seven = self.branch7x7x3_3(self.branch7x7x3_2(self.branch7x7x3_1(x)))
        return torch.cat([self.branch3x3_2(self.branch3x3_1(x)), self.branch7x7x3_4(seven),
                          F.max_pool2d(x, 3, stride=2)], dim=1)


class InceptionE(nn.Module):
    """8×8 block with split 1×3 / 3×1 branches; out 2048 channels. pool: 'avg', 'avg_no_pad' or 'max'."""

    def __init__(self, in_channels: int, pool: str):
        super().__init__()
        self.pool = pool
        self.branch1x1 = BasicConv2d(in_channels, 320, kernel_size=1)
        self.branch3x3_1 = BasicConv2d(in_channels, 384, kernel_size=1)
        self.branch3x3_2a = BasicConv2d(384, 384, kernel_size=(1, 3), padding=(0, 1))
        self.branch3x3_2b = BasicConv2d(384, 384, kernel_size=(3, 1), padding=(1, 0))
        self.branch3x3dbl_1 = BasicConv2d(in_channels, 448, kernel_size=1)
        self.branch3x3dbl_2 = BasicConv2d(448, 384, kernel_size=3, padding=1)
        self.branch3x3dbl_3a = BasicConv2d(384, 384, kernel_size=(1, 3), padding=(0, 1))
        self.branch3x3dbl_3b = BasicConv2d(384, 384, kernel_size=(3, 1), padding=(1, 0))
        self.branch_pool = BasicConv2d(in_channels, 192, kernel_size=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        single = self.branch3x3_1(x)
        double = self.branch3x3dbl_2(self.branch3x3dbl_1(x))
        if self.pool == "max":
            pooled = F.max_pool2d(x, 3, stride=1, padding=1)
        else:
            pooled = _avg_pool(x, fid_variant=self.pool == "avg_no_pad")
        return torch.cat([
            self.branch1x1(x),
            self.branch3x3_2a(single), self.branch3x3_2b(single),
            self.branch3x3dbl_3a(double), self.branch3x3dbl_3b(double),
            self.branch_pool(pooled),
        ], dim=1)


class InceptionV3Features(nn.Module):
    """Images (b, 3, H, W) in [-1, 1] → pool3 features (b, 2048). Resized to 299 × 299 (bilinear) first."""

    def __init__(self, fid_variant: bool = True, size: int = 299):
        super().__init__()
        self.size = size
        self.Conv2d_1a_3x3 = BasicConv2d(3, 32, kernel_size=3, stride=2)
        self.Conv2d_2a_3x3 = BasicConv2d(32, 32, kernel_size=3)
        self.Conv2d_2b_3x3 = BasicConv2d(32, 64, kernel_size=3, padding=1)
        self.Conv2d_3b_1x1 = BasicConv2d(64, 80, kernel_size=1)
        self.Conv2d_4a_3x3 = BasicConv2d(80, 192, kernel_size=3)
        self.Mixed_5b = InceptionA(192, 32, fid_variant)
        self.Mixed_5c = InceptionA(256, 64, fid_variant)
        self.Mixed_5d = InceptionA(288, 64, fid_variant)
        self.Mixed_6a = InceptionB(288)
        self.Mixed_6b = InceptionC(768, 128, fid_variant)
        self.Mixed_6c = InceptionC(768, 160, fid_variant)
        self.Mixed_6d = InceptionC(768, 160, fid_variant)
        self.Mixed_6e = InceptionC(768, 192, fid_variant)
        self.Mixed_7a = InceptionD(768)
        self.Mixed_7b = InceptionE(1280, "avg_no_pad" if fid_variant else "avg")
        self.Mixed_7c = InceptionE(2048, "max" if fid_variant else "avg")

    def stages(self) -> Sequence[nn.Module]:
        return (self.Mixed_5b, self.Mixed_5c, self.Mixed_5d, self.Mixed_6a, self.Mixed_6b, self.Mixed_6c, self.Mixed_6d,
                self.Mixed_6e, self.Mixed_7a, self.Mixed_7b, self.Mixed_7c)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x = F.interpolate(image.float(), size=(self.size, self.size), mode="bilinear", align_corners=False)
        x = self.Conv2d_2b_3x3(self.Conv2d_2a_3x3(self.Conv2d_1a_3x3(x)))
        x = self.Conv2d_4a_3x3(self.Conv2d_3b_1x1(F.max_pool2d(x, 3, stride=2)))
        x = F.max_pool2d(x, 3, stride=2)
        for stage in self.stages():
            x = stage(x)
        return F.adaptive_avg_pool2d(x, 1).flatten(1)
