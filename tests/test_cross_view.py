"""Cross-view consistency metric (gaia_app/eval/cross_view.py): the seam error of overlapping rig cameras."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from gaia_app.data.synthetic import generate_clip
from gaia_app.data.transforms import to_float
from gaia_app.eval.cross_view import infinity_homography, overlap_grid, overlapping_pairs, seam_errors


def rig(clip) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.tensor(np.stack([c.intrinsics for c in clip.cameras])).float(),
            torch.tensor(np.stack([c.extrinsics for c in clip.cameras])).float())


def test_only_adjacent_views_overlap() -> None:
    clip = generate_clip(seed=0, height=64, width=112, cameras=5, clip_len=1, fps=12.5)
    names = [c.name for c in clip.cameras]
    pairs = {(names[a], names[b]) for a, b in overlapping_pairs(*rig(clip), 64, 112)}
    assert ("front", "front_left") in pairs and ("front", "front_right") in pairs
    assert ("front", "rear_left") not in pairs and ("front_left", "front_right") not in pairs


def test_a_view_warped_from_its_neighbour_has_no_seam_error() -> None:
    """Camera b made of camera a's pixels seen through the homography at infinity agrees exactly on the overlap."""
    clip = generate_clip(seed=0, height=64, width=112, cameras=2, clip_len=1, fps=12.5)
    intrinsics, extrinsics = rig(clip)
    a = F.interpolate(torch.rand(1, 3, 8, 14) * 2 - 1, size=(64, 112), mode="bilinear", align_corners=False)
    grid, inside = overlap_grid(infinity_homography(intrinsics[0], extrinsics[0], intrinsics[1], extrinsics[1]),
                                64, 112)
    b = F.grid_sample(a, grid[None], mode="bilinear", align_corners=False)
    b = torch.where(inside, b, torch.rand_like(b))  # what b sees outside the overlap does not count
    video = torch.stack([a, b])  # (v, T=1, 3, H, W)
    assert 0.05 < inside.float().mean() < 0.5
    assert seam_errors(video, intrinsics, extrinsics, [(0, 1)], scale=1).item() < 1e-5
    assert seam_errors(torch.stack([a, -b]), intrinsics, extrinsics, [(0, 1)], scale=1).item() > 0.1


def test_real_rig_frames_agree_far_better_than_views_of_different_scenes() -> None:
    clips = [generate_clip(seed=s, height=64, width=112, cameras=3, clip_len=4, fps=12.5) for s in range(3)]
    intrinsics, extrinsics = rig(clips[0])
    pairs = overlapping_pairs(intrinsics, extrinsics, 64, 112)
    real = [seam_errors(to_float(torch.from_numpy(c.frames)), intrinsics, extrinsics, pairs).mean() for c in clips]
    mixed = [seam_errors(torch.stack([to_float(torch.from_numpy(clips[(i + v) % 3].frames[v])) for v in range(3)]),
                         intrinsics, extrinsics, pairs).mean() for i in range(3)]
    assert max(real) < 0.5 * min(mixed)
