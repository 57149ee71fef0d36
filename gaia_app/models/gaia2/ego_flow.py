"""Ego-motion flow of each latent grid cell: where a commanded action moves the static scene seen by every camera.

Legend: b batch, t latent steps, v cameras, gh gw token cells per camera.

The GAIA-2 report feeds ego actions through AdaLN only: one vector per step, the same for every token. For the image
to move, the network must work out from that vector, per camera and per position, where each piece of the scene goes,
which a small model trained for minutes does not do (docs/latent_world_model.md, "Actions painted on the grid"). This
module computes it by geometry instead, as `agent_raster` does for agents: the ego moves by its speed and yaw rate over
one latent step, each cell's ray meets the ground (or lies at `FAR` metres when it looks above the horizon), and the
point is projected into the same camera after the move. The flow (in cells) is what an optical-flow map of a static
world would read there. Ego frame: x forward, y left, z up, origin on the ground (DESIGN.md §4); cameras: OpenCV
(x right, y down, z forward), extrinsics camera → ego.
"""

from __future__ import annotations

import torch

FAR = 60.0  # m: depth of rays that meet the ground further away or never (sky, horizon)
LIMIT = 8.0  # cells: flows are clipped to this (points passing the camera)


def step_seconds(timestamps: torch.Tensor | None, steps: int) -> torch.Tensor:
    """(b, t) duration of each latent step from its timestamps (b, t); the first step takes the second's."""
    if timestamps is None or steps < 2:
        raise ValueError("the action raster (model.net.action_raster) needs the timestamps of at least two latent "
                         "steps to turn speeds into distances; "
                         f"got {'no timestamps' if timestamps is None else f'{steps} step'}")
    gaps = timestamps[:, 1:] - timestamps[:, :-1]
    if (gaps <= 0).any():
        raise ValueError(f"timestamps must increase from step to step; got gaps {gaps.tolist()}")
    return torch.cat([gaps[:, :1], gaps], dim=1)


def cell_rays(intrinsics: torch.Tensor, image_size: tuple[int, int], grid: tuple[int, int]) -> torch.Tensor:
    """(b, v, gh, gw, 3) camera-frame rays (z = 1) through the centre of each cell. intrinsics (b, v, 3, 3)."""
    height, width = image_size
    gh, gw = grid
    rows = (torch.arange(gh, device=intrinsics.device, dtype=intrinsics.dtype) + 0.5) * height / gh
    cols = (torch.arange(gw, device=intrinsics.device, dtype=intrinsics.dtype) + 0.5) * width / gw
    pixels = torch.stack([cols[None, :].expand(gh, gw), rows[:, None].expand(gh, gw), torch.ones(gh, gw).to(rows)], -1)
    return torch.einsum("bvij,hwj->bvhwi", torch.linalg.inv(intrinsics), pixels)


def scene_points(rays: torch.Tensor, extrinsics: torch.Tensor) -> torch.Tensor:
    """(b, v, gh, gw, 3) ego-frame points where each ray meets the ground (z = 0), at most FAR metres deep."""
    rotation, origin = extrinsics[..., :3, :3], extrinsics[..., :3, 3]
    directions = torch.einsum("bvij,bvhwj->bvhwi", rotation, rays)
    height = origin[..., 2][:, :, None, None]
    down = -directions[..., 2]
    depth = torch.where(down > 1e-6, height / down.clamp_min(1e-6), torch.full_like(down, FAR)).clamp(max=FAR)
    return origin[:, :, None, None] + depth[..., None] * directions


def ego_motion_flow(actions: torch.Tensor, seconds: torch.Tensor, intrinsics: torch.Tensor, extrinsics: torch.Tensor,
                    image_size: tuple[int, int], grid: tuple[int, int]) -> torch.Tensor:
    """Flow (b, t, v, gh, gw, 2) in cells (x right, y down) of the static scene under each step's action.

    actions (b, t, 2) speed m/s and curvature 1/m (left positive), seconds (b, t) per step; the ego drives an arc of
    length speed · seconds turning by speed · curvature · seconds.
    """
    distance = actions[..., 0] * seconds
    yaw = distance * actions[..., 1]  # (b, t)
    move = torch.stack([distance * torch.cos(yaw / 2), distance * torch.sin(yaw / 2), torch.zeros_like(yaw)], -1)
    return pose_flow(move, yaw, intrinsics, extrinsics, image_size, grid)


def pose_flow(move: torch.Tensor, yaw: torch.Tensor, intrinsics: torch.Tensor, extrinsics: torch.Tensor,
              image_size: tuple[int, int], grid: tuple[int, int], limit: float | None = LIMIT) -> torch.Tensor:
    """Flow (b, t, v, gh, gw, 2) in cells of the static scene when the ego moves by `move` (b, t, 3) m in its own
    frame and turns by `yaw` (b, t) rad (left positive); 0 where the moved point lies behind the camera, clipped to
    ±`limit` cells (None: not clipped)."""
    height, width = image_size
    gh, gw = grid
    rays = cell_rays(intrinsics, image_size, grid)
    points = scene_points(rays, extrinsics)  # (b, v, gh, gw, 3)
    cos, sin = torch.cos(yaw), torch.sin(yaw)
    zero, one = torch.zeros_like(yaw), torch.ones_like(yaw)
    undo_turn = torch.stack([torch.stack([cos, sin, zero], -1), torch.stack([-sin, cos, zero], -1),
                             torch.stack([zero, zero, one], -1)], -2)  # R_z(−yaw): (b, t, 3, 3)
    moved = torch.einsum("btij,btvhwj->btvhwi", undo_turn, points[:, None] - move[:, :, None, None, None])
    rotation, origin = extrinsics[..., :3, :3], extrinsics[..., :3, 3]
    camera = torch.einsum("bvji,btvhwj->btvhwi", rotation, moved - origin[:, None, :, None, None])
    pixels = torch.einsum("bvij,btvhwj->btvhwi", intrinsics, camera)
    ahead = camera[..., 2] > 0.1
    uv = pixels[..., :2] / camera[..., 2:].clamp_min(0.1)
    start = torch.einsum("bvij,bvhwj->bvhwi", intrinsics, rays)[..., :2]
    flow = (uv - start[:, None]) / uv.new_tensor([width / gw, height / gh])
    if limit is not None:
        flow = flow.clamp(-limit, limit)
    return torch.where(ahead[..., None], flow, torch.zeros_like(flow))
