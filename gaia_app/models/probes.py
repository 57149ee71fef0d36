"""Controllability probes: small CNNs that read conditions back from frames (not in GAIA-1; see docs/generate.md).

Legend: b batch, H × W images in [-1, 1], d feature width.

An inverse-dynamics probe maps two consecutive frames at the world model's rate to the ego's (speed,
curvature) over that step; a scene-attribute probe maps one frame to weather, time of day and the state of
the traffic light ahead. Trained on the synthetic world's ground truth, they score how well generated
futures follow the commanded actions and the text prompt (GAIA-1 §7 shows this only qualitatively).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from einops import rearrange
from torch import nn

WEATHER = ("clear", "rain", "fog", "snow")
TIME_OF_DAY = ("day", "dusk", "night")
TRAFFIC_LIGHT = ("none", "red", "amber", "green")
ATTRIBUTES: dict[str, tuple[str, ...]] = {"weather": WEATHER, "time_of_day": TIME_OF_DAY, "traffic_light": TRAFFIC_LIGHT}
# curvature is ~100× smaller than speed: the probe predicts it in 1/(100 m) so both losses weigh alike
CURVATURE_SCALE = 100.0


class FrameEncoder(nn.Module):
    """Strided conv stack with GroupNorm and SiLU, global average pool: (b, c, H, W) → (b, d)."""

    def __init__(self, in_channels: int = 3, widths: Sequence[int] = (16, 32, 64, 64)):
        super().__init__()
        layers, prev = [], in_channels
        for width in widths:
            layers += [nn.Conv2d(prev, width, 3, stride=2, padding=1), nn.GroupNorm(8, width), nn.SiLU()]
            prev = width
        self.net = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(1), nn.Flatten())
        self.dim = prev

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class InverseDynamicsProbe(nn.Module):
    """Two consecutive frames → the ego's (speed m/s, curvature 1/m) between them."""

    def __init__(self, widths: Sequence[int] = (16, 32, 64, 64)):
        super().__init__()
        self.encoder = FrameEncoder(6, widths)
        self.head = nn.Linear(self.encoder.dim, 2)

    def forward(self, pair: torch.Tensor) -> torch.Tensor:
        """pair: (b, 2, 3, H, W), earlier frame first → (b, 2) speed and curvature in physical units."""
        out = self.head(self.encoder(rearrange(pair, "b t c h w -> b (t c) h w")))
        return out / torch.tensor([1.0, CURVATURE_SCALE], device=out.device)

    def loss(self, pair: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Smooth-L1 on speed and on curvature × CURVATURE_SCALE; actions: (b, 2)."""
        scale = torch.tensor([1.0, CURVATURE_SCALE], device=actions.device)
        return nn.functional.smooth_l1_loss(self(pair) * scale, actions * scale)


class SceneAttributeProbe(nn.Module):
    """One frame → logits per attribute of `ATTRIBUTES` (weather, time of day, traffic light)."""

    def __init__(self, widths: Sequence[int] = (16, 32, 64, 64)):
        super().__init__()
        self.encoder = FrameEncoder(3, widths)
        self.heads = nn.ModuleDict({name: nn.Linear(self.encoder.dim, len(values)) for name, values in ATTRIBUTES.items()})

    def forward(self, frames: torch.Tensor) -> dict[str, torch.Tensor]:
        """frames (b, 3, H, W) → {attribute: (b, classes) logits}."""
        h = self.encoder(frames)
        return {name: head(h) for name, head in self.heads.items()}

    def loss(self, frames: torch.Tensor, labels: dict[str, torch.Tensor]) -> torch.Tensor:
        """Sum of cross-entropies; labels: {attribute: (b,) class indices}."""
        logits = self(frames)
        return sum(nn.functional.cross_entropy(logits[name], labels[name]) for name in ATTRIBUTES)


class AgentSegmentationProbe(nn.Module):
    """One frame → per-pixel logits of "an agent (vehicle, pedestrian, cyclist) is here", (b, 3, H, W) → (b, H, W).

    A small encoder-decoder with skip connections (U-Net style, three scales); H and W multiples of 8. Trained on
    the synthetic world's instance masks, it scores where generated frames put agents (agent IoU, GAIA-2 §6).
    """

    def __init__(self, widths: Sequence[int] = (16, 32, 64)):
        super().__init__()
        self.down = nn.ModuleList()
        prev = 3
        for width in widths:
            self.down.append(nn.Sequential(nn.Conv2d(prev, width, 3, stride=2, padding=1), nn.GroupNorm(8, width), nn.SiLU(),
                                           nn.Conv2d(width, width, 3, padding=1), nn.GroupNorm(8, width), nn.SiLU()))
            prev = width
        self.up = nn.ModuleList()
        for skip in (*reversed(widths[:-1]), 3):
            self.up.append(nn.Sequential(nn.Conv2d(prev + skip, max(skip, 16), 3, padding=1), nn.GroupNorm(8, max(skip, 16)),
                                         nn.SiLU()))
            prev = max(skip, 16)
        self.head = nn.Conv2d(prev, 1, 1)

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """frames (b, 3, H, W) in [-1, 1] → logits (b, H, W)."""
        if frames.shape[-2] % 8 or frames.shape[-1] % 8:
            raise ValueError(f"AgentSegmentationProbe needs H and W divisible by 8, got {tuple(frames.shape[-2:])}")
        skips, x = [frames], frames
        for block in self.down:
            x = block(x)
            skips.append(x)
        skips.pop()
        for block in self.up:
            x = nn.functional.interpolate(x, scale_factor=2, mode="nearest")
            x = block(torch.cat([x, skips.pop()], dim=1))
        return self.head(x)[:, 0]

    def loss(self, frames: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
        """Binary cross-entropy against masks (b, H, W) bool."""
        return nn.functional.binary_cross_entropy_with_logits(self(frames), masks.float())
