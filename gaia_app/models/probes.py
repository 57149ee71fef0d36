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
ATTRIBUTES: dict[str, tuple[str, ...]] = {"weather": WEATHER, "time_of_day": TIME_OF_DAY,
                                          "traffic_light": TRAFFIC_LIGHT}
# curvature is ~100× smaller than speed: the probe predicts it in 1/(100 m) so both losses weigh alike
CURVATURE_SCALE = 100.0


class FrameEncoder(nn.Module):
    """Strided conv stack with GroupNorm and SiLU, average-pooled to a `grid` of cells: (b, c, H, W) → (b, d).

    grid (1, 1) is a global pool; a coarser pool keeps *where* things happen, which an inverse-dynamics probe
    needs (a turn shifts the whole image sideways, a speed change moves the lower image more than the horizon).
    """

    def __init__(self, in_channels: int = 3, widths: Sequence[int] = (16, 32, 64, 64), grid: tuple[int, int] = (1, 1)):
        super().__init__()
        layers, prev = [], in_channels
        for width in widths:
            layers += [nn.Conv2d(prev, width, 3, stride=2, padding=1), nn.GroupNorm(8, width), nn.SiLU()]
            prev = width
        self.net = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(tuple(grid)), nn.Flatten())
        self.dim = prev * grid[0] * grid[1]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


@torch.no_grad()
def cost_volume(a: torch.Tensor, b: torch.Tensor, radius: int = 3) -> torch.Tensor:
    """Block-matching costs of frame b against frame a shifted by every (dy, dx) with |dy|, |dx| ≤ radius:
    (n, 3, h, w) × 2 → (n, (2r + 1)², h, w), the 3 × 3 local mean of |grey_b(x) − grey_a(x + d)|, divided by its mean
    over shifts. Fixed (not learned) features: the cost is lowest at the image motion whatever the scene looks like,
    so a probe trained on a few hundred scenes still finds the motion in scenes it has never seen."""
    grey_a, grey_b = a.mean(dim=1, keepdim=True), b.mean(dim=1, keepdim=True)
    h, w = grey_a.shape[-2:]
    padded = nn.functional.pad(grey_a, (radius,) * 4, mode="replicate")
    side = 2 * radius + 1
    costs = torch.cat([(grey_b - padded[:, :, dy : dy + h, dx : dx + w]).abs()
                       for dy in range(side) for dx in range(side)], dim=1)
    costs = nn.functional.avg_pool2d(costs, 3, stride=1, padding=1)
    return costs / (costs.mean(dim=1, keepdim=True) + 1e-3)


class InverseDynamicsProbe(nn.Module):
    """Two consecutive frames → the ego's (speed m/s, curvature 1/m) between them.

    At 6.25 Hz and 10 m/s a 0.02 1/m turn rotates the view by ~2°, a few pixels at 64 × 112, and the road moves a
    few pixels more near the bottom of the image than at the horizon. The encoder sees both frames and their
    difference at half resolution, plus block-matching cost volumes at ½ and ¼ resolution (motion up to ±6 and
    ±12 pixels), pooled to a 2 × 4 grid so the head knows where in the image the motion is. Without the cost
    volumes a probe trained on 256 scenes read curvature on new scenes no better than a constant (0.0132 vs 0.0148
    1/m mean error, benchmarks/probe_quality.py; docs/generate.md). H and W must be multiples of 4.

    With `cameras` = k > 1 it reads a rig: the same encoder runs on each camera's pair and the head sees the k
    encodings side by side in rig order. Side cameras see the road stream past (speed) where the front camera sees it
    only loom, and every view shifts sideways in a turn (GAIA-2's rig; docs/latent_world_model.md, "Evaluation").
    """

    def __init__(self, widths: Sequence[int] = (64, 96, 128), grid: tuple[int, int] = (2, 4), hidden: int = 128,
                 radius: int = 3, cameras: int = 1):
        super().__init__()
        if cameras < 1:
            raise ValueError(f"InverseDynamicsProbe: cameras={cameras}, expected ≥ 1")
        self.radius, self.cameras = radius, cameras
        self.encoder = FrameEncoder(9 + 2 * (2 * radius + 1) ** 2, widths, grid)
        # one encoder for every camera; the head sees them side by side in rig order, so it knows which view moved how
        self.head = nn.Sequential(nn.Linear(cameras * self.encoder.dim, hidden), nn.SiLU(), nn.Linear(hidden, 2))

    def features(self, pair: torch.Tensor) -> torch.Tensor:
        """pair (b, 2, 3, H, W) → (b, 9 + 2 (2r + 1)², H/2, W/2): frames, difference, cost volumes at ½ and ¼."""
        if pair.shape[-2] % 4 or pair.shape[-1] % 4:
            raise ValueError(f"InverseDynamicsProbe needs H and W divisible by 4, got {tuple(pair.shape[-2:])}")
        half = nn.functional.avg_pool2d(pair.flatten(0, 1), 2).unflatten(0, pair.shape[:2])  # (b, 2, 3, H/2, W/2)
        quarter = nn.functional.avg_pool2d(half.flatten(0, 1), 2).unflatten(0, pair.shape[:2])
        coarse = nn.functional.interpolate(cost_volume(quarter[:, 0], quarter[:, 1], self.radius),
                                           size=half.shape[-2:], mode="nearest")
        return torch.cat([rearrange(half, "b t c h w -> b (t c) h w"), half[:, 1] - half[:, 0],
                          cost_volume(half[:, 0], half[:, 1], self.radius), coarse], dim=1)

    def forward(self, pair: torch.Tensor) -> torch.Tensor:
        """pair: (b, 2, 3, H, W) for one camera or (b, 2, k, 3, H, W) for k = `cameras` of a rig, earlier frame first
        → (b, 2) speed and curvature in physical units."""
        if self.cameras == 1 and pair.dim() == 5:
            pair = pair.unsqueeze(2)
        if pair.dim() != 6 or pair.shape[2] != self.cameras:
            raise ValueError(f"InverseDynamicsProbe({self.cameras} camera(s)): "
                             f"expected pairs (b, 2, {self.cameras}, 3, H, W)"
                             f"{' or (b, 2, 3, H, W)' if self.cameras == 1 else ''}, got {tuple(pair.shape)}")
        views = rearrange(pair, "b t k c h w -> (b k) t c h w")
        encoded = rearrange(self.encoder(self.features(views)), "(b k) d -> b (k d)", k=self.cameras)
        out = self.head(encoded)
        return out / torch.tensor([1.0, CURVATURE_SCALE], device=out.device)

    def loss(self, pair: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Smooth-L1 on speed and on curvature × CURVATURE_SCALE; pair as in `forward`, actions: (b, 2)."""
        scale = torch.tensor([1.0, CURVATURE_SCALE], device=actions.device)
        return nn.functional.smooth_l1_loss(self(pair) * scale, actions * scale)


class TwinDisplacementProbe(InverseDynamicsProbe):
    """Two futures of one scene seen at the same instant → how much further (m, along the route) the ego of the
    second has travelled than the ego of the first.

    The inverse-dynamics probe reads speed from the motion between two frames of one clip: at 12.5 Hz and stride 2 a
    2 m/s speed difference moves the image by about a pixel, and the probe reads about half of an accelerate − brake
    contrast (docs/latent_world_model_notes.md, "Why the speed probe reads about half…"). Two futures of one context
    that differ only in their speed command drift apart by metres over the horizon, and seen at the same instant the
    rest of the world (the other road users) is where it is in both, so their frames differ only by the ego's
    displacement. Same encoder and cost volumes as the inverse-dynamics probe; the output is antisymmetric,
    ½ (g(a, b) − g(b, a)), so identical futures read exactly 0 and swapping them negates the reading.

    pair: (b, 2, k, 3, H, W) for k = `cameras` (or (b, 2, 3, H, W) for one camera), the first future first → (b,) m.
    """

    def __init__(self, widths: Sequence[int] = (64, 96, 128), grid: tuple[int, int] = (2, 4), hidden: int = 128,
                 radius: int = 3, cameras: int = 1):
        super().__init__(widths, grid, hidden, radius, cameras)
        self.head[-1] = nn.Linear(hidden, 1)

    def forward(self, pair: torch.Tensor) -> torch.Tensor:
        if self.cameras == 1 and pair.dim() == 5:
            pair = pair.unsqueeze(2)
        if pair.dim() != 6 or pair.shape[2] != self.cameras:
            raise ValueError(f"TwinDisplacementProbe({self.cameras} camera(s)): expected pairs "
                             f"(b, 2, {self.cameras}, 3, H, W), got {tuple(pair.shape)}")
        both = torch.cat([pair, pair.flip(1)])  # (2b, 2, k, 3, H, W): each pair in both orders, one batch
        views = rearrange(both, "b t k c h w -> (b k) t c h w")
        encoded = rearrange(self.encoder(self.features(views)), "(b k) d -> b (k d)", k=self.cameras)
        forward, backward = self.head(encoded)[:, 0].chunk(2)
        return 0.5 * (forward - backward)

    def loss(self, pair: torch.Tensor, displacement: torch.Tensor) -> torch.Tensor:
        """Smooth-L1 (m) against the true displacement (b,) of the second future over the first."""
        return nn.functional.smooth_l1_loss(self(pair), displacement)


class SceneAttributeProbe(nn.Module):
    """One frame → logits per attribute of `ATTRIBUTES` (weather, time of day, traffic light)."""

    def __init__(self, widths: Sequence[int] = (32, 64, 96, 128)):
        super().__init__()
        self.encoder = FrameEncoder(3, widths)
        self.heads = nn.ModuleDict({name: nn.Linear(self.encoder.dim, len(values))
                                    for name, values in ATTRIBUTES.items()})

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
        self.widths = tuple(int(w) for w in widths)
        self.down = nn.ModuleList()
        prev = 3
        for width in widths:
            self.down.append(nn.Sequential(nn.Conv2d(prev, width, 3, stride=2, padding=1), nn.GroupNorm(8, width),
                                           nn.SiLU(),
                                           nn.Conv2d(width, width, 3, padding=1), nn.GroupNorm(8, width), nn.SiLU()))
            prev = width
        self.up = nn.ModuleList()
        for skip in (*reversed(widths[:-1]), 3):
            self.up.append(nn.Sequential(nn.Conv2d(prev + skip, max(skip, 16), 3, padding=1),
                                         nn.GroupNorm(8, max(skip, 16)), nn.SiLU()))
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

    def loss(self, frames: torch.Tensor, masks: torch.Tensor, dice: bool = False) -> torch.Tensor:
        """Binary cross-entropy against masks (b, H, W) bool; dice adds 1 − soft Dice over the batch, which weighs the
        few agent pixels as much as the many background ones."""
        logits = self(frames)
        loss = nn.functional.binary_cross_entropy_with_logits(logits, masks.float())
        if dice:
            p = logits.sigmoid()
            loss = loss + 1 - (2 * (p * masks).sum() + 1) / (p.sum() + masks.sum() + 1)
        return loss
