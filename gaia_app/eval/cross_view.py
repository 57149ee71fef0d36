"""Cross-view consistency of multi-camera video: do adjacent cameras agree where their views overlap?

Legend: v cameras, T frames, H W image size; K (3, 3) intrinsics at H × W; E (4, 4) camera → ego extrinsics
(OpenCV camera axes, DESIGN.md §4).

Rig cameras sit within a metre of each other, so distant content (sky, far road, buildings) appears in two
overlapping views related by the homography at infinity, which depends on the rotations alone:
    x_a ~ K_a R_aᵀ R_b K_b⁻¹ x_b        (R: the extrinsics' rotation, camera → ego)
Camera a is warped into camera b's pixel grid by it, and the mean absolute difference over the pixels both cameras
see is the seam error of the pair. Near content has parallax (a 0.5 m baseline shifts a car 10 m away by about
3°), which the comparison at reduced resolution (`scale`) mostly absorbs; what is left is the same for real and
generated frames, so the metric is read between a ceiling (real frames) and a floor (cameras generated
independently of each other), as GAIA-2's report asks of multi-view generation (spatial consistency).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from einops import rearrange


def infinity_homography(k_a: torch.Tensor, e_a: torch.Tensor, k_b: torch.Tensor, e_b: torch.Tensor) -> torch.Tensor:
    """(3, 3) map from pixels of camera b to pixels of camera a for points at infinity (homogeneous, (x, y, 1))."""
    rotation = e_a[:3, :3].T @ e_b[:3, :3]  # camera b axes → camera a axes
    return k_a @ rotation @ torch.linalg.inv(k_b)


def overlap_grid(homography: torch.Tensor, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each pixel centre of camera b lands in camera a: a grid_sample grid (H, W, 2) in [-1, 1] and the mask
    (H, W) of pixels that land inside camera a's image, in front of it."""
    ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    pixels = torch.stack([xs, ys, torch.ones_like(xs)], dim=-1).to(homography)  # (H, W, 3)
    mapped = pixels @ homography.T
    depth = mapped[..., 2]
    xy = mapped[..., :2] / depth.clamp(min=1e-6)[..., None]
    inside = (depth > 1e-6) & (xy[..., 0] >= 0) & (xy[..., 0] <= width) & (xy[..., 1] >= 0) & (xy[..., 1] <= height)
    grid = torch.stack([xy[..., 0] / width * 2 - 1, xy[..., 1] / height * 2 - 1], dim=-1)
    return grid, inside


def overlapping_pairs(intrinsics: torch.Tensor, extrinsics: torch.Tensor, height: int, width: int,
                      min_share: float = 0.02) -> list[tuple[int, int]]:
    """Ordered camera pairs (a, b), a < b, whose overlap at infinity covers at least `min_share` of camera b."""
    pairs = []
    for a in range(len(intrinsics)):
        for b in range(a + 1, len(intrinsics)):
            homography = infinity_homography(intrinsics[a], extrinsics[a], intrinsics[b], extrinsics[b])
            if overlap_grid(homography, height, width)[1].float().mean() >= min_share:
                pairs.append((a, b))
    return pairs


def seam_errors(video: torch.Tensor, intrinsics: torch.Tensor, extrinsics: torch.Tensor,
                pairs: list[tuple[int, int]], scale: int = 4) -> torch.Tensor:
    """(len(pairs),) mean absolute difference between camera b and camera a warped onto it, over their overlap and
    every frame, at 1/`scale` resolution. video: (v, T, 3, H, W) in [-1, 1]."""
    v, t, _, height, width = video.shape
    small = F.avg_pool2d(rearrange(video.float(), "v t c h w -> (v t) c h w"), scale)
    small = rearrange(small, "(v t) c h w -> v t c h w", v=v)
    h, w = small.shape[-2:]
    k = intrinsics.float().clone()
    k[:, :2] /= scale  # the same cameras at the reduced resolution
    errors = []
    for a, b in pairs:
        grid, inside = overlap_grid(infinity_homography(k[a], extrinsics[a].float(), k[b], extrinsics[b].float()), h, w)
        warped = F.grid_sample(small[a], grid.expand(t, h, w, 2), mode="bilinear", align_corners=False)
        difference = (warped - small[b]).abs().mean(dim=1)  # (T, h, w)
        errors.append(difference[:, inside].mean())
    return torch.stack(errors) if errors else video.new_zeros(0)
