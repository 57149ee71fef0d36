"""The gap to the lead vehicle, read from an agent mask: what the futures-with-agents protocol measures (issue 49).

GAIA-1 §7.2–7.3 show other road users that behave differently in different futures and react to the ego. A
generated frame has no labels, so the lead vehicle is read from the agent segmentation probe's mask: each
pixel on the lower edge of a masked region is where a road user meets the road, and the ground plane (a flat road
seen by the front camera of the synthetic rig, whose mount is known) gives how far ahead and to the side that
point lies. The lead vehicle is the nearest such point inside the ego's lane band; its gap is measured like the
world's own `lead_agent` label, from the ego's front bumper to the vehicle's rear, and the band is the label's: along
the road, through the ego's position. On real clips the ego follows the road (`following`: the road bends with the
ego's curvature); under a command the road keeps its curvature (the context's) and the command turns the ego across
it (`commanded_pose`), so the band still runs along the road when the ego steers away.

The ground plane makes far gaps coarse: on the 64×112 front camera one pixel row is about 6 m at 30 m and
0.6 m at 10 m; `protocols/agent_futures.py` reports how well the reading agrees with the world's labels on real
frames (the reader's ceiling) beside every score.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from gaia_app.data.clip import CameraSpec
from gaia_app.eval.intervals import Estimate, mean_interval

EGO_FRONT = 3.7
"""Metres from the ego frame's origin to its front bumper (the synthetic ego, data/synthetic/world.py)."""
LANE_HALF_WIDTH = 1.75
"""Half the ego lane (m) around its centre line: a road user whose road contact lies inside is in the ego's lane."""
LEAD_RANGE = 30.0
"""A lead vehicle counts when its labelled gap is at most this many metres (issue 49)."""
READ_RANGE = 45.0
"""A masked road user in the lane is read as the lead vehicle up to this gap: one pixel row spans several metres
near 30 m on the 64×112 front camera, so a vehicle labelled at 30 m may read a row farther."""


@dataclass(frozen=True)
class GroundPlane:
    """Where each pixel's ray meets the road: forward (H, W) and left (H, W) metres in the ego frame, NaN above the
    horizon."""

    forward: np.ndarray
    left: np.ndarray


def ground_plane(camera: CameraSpec) -> GroundPlane:
    """The flat-road position of the middle of every pixel's lower edge of `camera` (intrinsics, ego-from-camera
    extrinsics): a road user's lowest pixel touches the road along that edge."""
    u, v = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 1.0)
    pixels = np.stack([u, v, np.ones_like(u)], axis=-1)  # (H, W, 3)
    rays = pixels @ np.linalg.inv(camera.intrinsics).T @ camera.extrinsics[:3, :3].T  # camera rays in the ego frame
    origin = camera.extrinsics[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = np.where(rays[..., 2] < 0, -origin[2] / rays[..., 2], np.nan)
    return GroundPlane(origin[0] + reach * rays[..., 0], origin[1] + reach * rays[..., 1])


def road_contacts(masks: torch.Tensor) -> torch.Tensor:
    """(…, H, W) bool: the masked pixels whose lower neighbour is not masked (the bottom row counts as unmasked
    below): where a road user stands on the road."""
    below = torch.zeros_like(masks)
    below[..., :-1, :] = masks[..., 1:, :]
    return masks & ~below


@dataclass(frozen=True)
class LanePose:
    """The ego relative to the road at each frame (N, t): heading (rad, the ego turned left of the road's direction)
    and the road's curvature (1/m). The lane searched is the band along the road through the ego's own position,
    as the world's `lead_agent` label takes it (agents whose lateral road coordinate is within the corridor of the
    ego's)."""

    heading: torch.Tensor
    curvature: torch.Tensor


def following(curvature: torch.Tensor) -> LanePose:
    """The pose of an ego that follows the road, the road bending with the ego's curvature (N, t)."""
    return LanePose(torch.zeros_like(curvature, dtype=torch.float32), curvature.float())


def commanded_pose(actions: torch.Tensor, road_curvature: torch.Tensor, rate: float) -> LanePose:
    """The ego's heading relative to a road of constant curvature (N,) 1/m (the road the context drove on) after
    each commanded step (N, t, 2) (speed m/s, curvature 1/m) at `rate` Hz, starting along the road: a command that
    turns more or less than the road turns the ego across it (small-angle kinematics)."""
    speed, turn = actions[..., 0].float(), actions[..., 1].float() - road_curvature[:, None].float()
    heading = torch.cumsum(speed * turn / rate, dim=1)
    return LanePose(heading, road_curvature[:, None].float().expand_as(heading))


def lead_gaps(masks: torch.Tensor, pose: LanePose, ground: GroundPlane, max_gap: float = READ_RANGE) -> np.ndarray:
    """(N, t) gap (m) to the nearest masked road user in the ego lane, from agent masks (N, t, H, W) bool and the
    ego's pose in its lane at each frame; NaN where no road contact lies in the lane within `max_gap`."""
    forward = torch.from_numpy(ground.forward).float()
    left = torch.from_numpy(ground.left).float()
    at = lambda x: x[..., None, None]  # noqa: E731  (N, t) → (N, t, 1, 1)
    # the band's centre line in the ego frame: along the road (turned by the ego's heading, bent by the road)
    lane_centre = -at(pose.heading) * forward + at(pose.curvature) * forward.square() / 2
    in_lane = (left - lane_centre).abs() <= LANE_HALF_WIDTH
    gap = forward - EGO_FRONT
    usable = road_contacts(masks) & in_lane & torch.isfinite(gap) & (gap > -0.5)
    nearest = torch.where(usable, gap, torch.full_like(gap, float("inf"))).flatten(-2).min(-1).values
    nearest = nearest.numpy().astype(np.float64)
    return np.where(nearest <= max_gap, nearest, np.nan)


def labelled_gaps(frame_meta: Sequence[dict], vehicles: Sequence[str], max_gap: float = LEAD_RANGE) -> np.ndarray:
    """(t,) the world's own lead-vehicle gap of each frame (`frame_meta[i]["lead_agent"]`), NaN where there is no
    lead vehicle within `max_gap`."""
    out = np.full(len(frame_meta), np.nan)
    for i, meta in enumerate(frame_meta):
        lead = meta.get("lead_agent")
        if lead is not None and lead["category"] in vehicles and lead["distance"] <= max_gap:
            out[i] = float(lead["distance"])
    return out


def persistence(found: np.ndarray, present: np.ndarray, resamples: int = 2000, seed: int = 0) -> Estimate:
    """Pooled share of the frames with a lead vehicle `present` (N, t) bool in which one is `found` (N, t) bool,
    with a bootstrap interval over contexts (the frames of one context are not independent)."""
    hits, counts = (found & present).sum(1).astype(float), present.sum(1).astype(float)
    if counts.sum() == 0:
        raise ValueError("persistence: no frame has a lead vehicle (choose contexts with one)")
    rng = np.random.default_rng(seed)
    index = rng.integers(0, len(counts), (resamples, len(counts)))
    shares = hits[index].sum(1) / np.maximum(counts[index].sum(1), 1)
    low, high = np.percentile(shares, [2.5, 97.5])
    return Estimate(float(hits.sum() / counts.sum()), float(low), float(high), len(counts))


def closer_under(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """(N,) bool: the gap at the horizon under the first command is smaller than under the second; a vehicle the
    reader does not find counts as out of range, so two missing readings are a tie (not closer)."""
    return np.nan_to_num(first, nan=np.inf) < np.nan_to_num(second, nan=np.inf)


def spread(gaps: np.ndarray) -> float | None:
    """Standard deviation (m) of the gaps read in several futures, over the futures in which the vehicle is read
    (None when fewer than two are): how differently the lead vehicle moves, not whether it is kept."""
    found = gaps[np.isfinite(gaps)]
    return float(np.std(found)) if len(found) >= 2 else None


def gap_error(read: np.ndarray, labelled: np.ndarray) -> Estimate | None:
    """Mean |read − labelled| gap (m) over the frames where both have a lead vehicle, with its t interval over
    those frames (None when none has both): how well `lead_gaps` reads the world's labels."""
    both = np.isfinite(read) & np.isfinite(labelled)
    return mean_interval(np.abs(read[both] - labelled[both]).tolist()) if both.any() else None
