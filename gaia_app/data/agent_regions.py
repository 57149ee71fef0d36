"""Where the agents are in each image: their 3D boxes projected through the rig, as pixel masks.

Legend: v cameras, t frames, H × W pixels.

A tokenizer trained on plain L1/L2 spends its bits on the road and the sky, which cover most pixels, and erases the
few pixels of a car 30 m ahead (docs/tokenizer.md, "Road users"). The masks here let its reconstruction loss weigh
the agents' pixels more (`model.weights.agents`); they come from the clip's own labels (`clip.agents`, 3D boxes in
the ego frame, and `clip.cameras`), so real data with boxes (PandaSet) gets them as the synthetic world does.
"""

from __future__ import annotations

import numpy as np

from gaia_app.data.clip import AgentBoxes, CameraSpec, Clip

NEAR = 0.1
"""Corners closer than this (m) in front of a camera do not count as seen."""


def box_corners(boxes: AgentBoxes) -> np.ndarray:
    """(n, 8, 3) corners of n yawed boxes in the ego frame (x forward, y left, z up)."""
    signs = np.array([[sx, sy, sz] for sx in (-0.5, 0.5) for sy in (-0.5, 0.5) for sz in (-0.5, 0.5)])
    local = signs[None] * boxes.size[:, None, :]
    cos, sin = np.cos(boxes.yaw)[:, None], np.sin(boxes.yaw)[:, None]
    x = cos * local[..., 0] - sin * local[..., 1]
    y = sin * local[..., 0] + cos * local[..., 1]
    return np.stack([x, y, local[..., 2]], axis=-1) + boxes.centre[:, None, :]


def box_mask(boxes: AgentBoxes, camera: CameraSpec, height: int, width: int) -> np.ndarray:
    """(H, W) bool: the union of the image rectangles that bound each box's corners in front of `camera`."""
    out = np.zeros((height, width), dtype=bool)
    if len(boxes) == 0:
        return out
    ego_to_cam = np.linalg.inv(camera.extrinsics)
    cam = np.einsum("ij,nkj->nki", ego_to_cam[:3, :3], box_corners(boxes)) + ego_to_cam[:3, 3]
    sx, sy = width / camera.width, height / camera.height  # intrinsics are in the camera's own pixels
    for corners in cam:
        ahead = corners[corners[:, 2] > NEAR]
        if len(ahead) == 0:
            continue
        pix = ahead @ camera.intrinsics.T
        u, v = pix[:, 0] / pix[:, 2] * sx, pix[:, 1] / pix[:, 2] * sy
        x0, x1 = int(np.clip(np.floor(u.min()), 0, width)), int(np.clip(np.ceil(u.max()), 0, width))
        y0, y1 = int(np.clip(np.floor(v.min()), 0, height)), int(np.clip(np.ceil(v.max()), 0, height))
        out[y0:y1, x0:x1] = True
    return out


def agent_box_masks(clip: Clip) -> np.ndarray:
    """(v, t, H, W) bool: every agent box of each frame projected into each camera of the clip.

    Raises ValueError naming the clip when it has no agent boxes or no camera specs to project them with."""
    missing = [what for what, value in (("agent boxes (clip.agents)", clip.agents),
                                        ("camera specs (clip.cameras)", clip.cameras)) if value is None]
    if missing:
        raise ValueError(f"clip '{clip.clip_id}' has no {' and no '.join(missing)}: data.agent_boxes=true needs both "
                         "to weigh the agents' pixels (or set model.weights.agents=0 and data.agent_boxes=false)")
    height, width = clip.frames.shape[-2:]
    return np.stack([np.stack([box_mask(boxes, camera, height, width) for boxes in clip.agents])
                     for camera in clip.cameras])
