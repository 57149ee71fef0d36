"""Agent fidelity of a tokenizer: does the round trip through the tokens keep the other road users?

Legend: N clips, t frames at the world model's rate, H × W images in [-1, 1].

GAIA-1 §7 and GAIA-2's agent results are about other road users, so the tokens must keep them. This module scores a
tokenizer's reconstructions against the real frames with the synthetic world's own labels:
- agent IoU of the segmentation probe (`agent_iou.py`) on real and on tokenized frames, and their ratio;
- PSNR (and LPIPS, with local VGG16 weights) inside the agents' 2D boxes and on the background;
- lead-vehicle presence: the share of frames with a vehicle within `LEAD_RANGE` m ahead in the ego lane
  (`frame_meta["lead_agent"]`, GAIA-1 §7.3's "vehicle in front") in which the probe covers most of it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch

from gaia_app.data.clip import Clip
from gaia_app.data.synthetic.simulate import FrameState
from gaia_app.data.transforms import resample_indices, to_float
from gaia_app.eval.intervals import Estimate, mean_interval, ratio_interval

LEAD_RANGE = 30.0
"""A lead vehicle counts when its gap (front bumper to its rear) is at most this many metres."""
VEHICLES = ("car", "bus", "truck")
"""Lead agents of these categories count as lead vehicles."""
FOUND_SHARE = 0.5
"""The probe finds the lead vehicle when its agent mask covers at least this share of the vehicle's visible pixels."""


class LabelledSample(Protocol):
    """What the protocol needs of a clip: the clip, its simulation states and instance masks (SyntheticSample)."""

    clip: Clip
    states: list[FrameState]

    def instance_ids(self, frame: int, camera: str | int = 0) -> np.ndarray: ...


@dataclass
class FidelityFrames:
    """The first camera of N labelled clips at the world model's rate.

    frames (N, t, 3, H, W) in [-1, 1]; agents (N, t, H, W) bool, any agent; boxes (N, t, H, W) bool, the union of
    the agents' 2D boxes (the bounding rectangle of each agent's visible pixels); lead (N, t, H, W) bool, the
    visible pixels of the lead vehicle within LEAD_RANGE (all false where there is none)."""

    clip_ids: list[str]
    frames: torch.Tensor
    agents: torch.Tensor
    boxes: torch.Tensor
    lead: torch.Tensor


def check_labels(sample: Any) -> None:
    """Refuse a clip that lacks what the protocol reads, naming the clip and what is missing."""
    clip = getattr(sample, "clip", sample)
    name = getattr(clip, "clip_id", "?")
    missing = []
    if not callable(getattr(sample, "instance_ids", None)) or getattr(sample, "states", None) is None:
        missing.append("agent masks (instance ids from the world's simulation)")
    if getattr(clip, "agents", None) is None:
        missing.append("agent boxes (clip.agents)")
    if getattr(clip, "frame_meta", None) is None or any("lead_agent" not in m for m in clip.frame_meta):
        missing.append("the lead agent of every frame (frame_meta['lead_agent'])")
    if missing:
        raise ValueError(f"agent fidelity: clip '{name}' has no " + " and no ".join(missing)
                         + "; the protocol needs the synthetic world's labels (SyntheticClipDataset.sample)")


def box_mask(ids: np.ndarray) -> np.ndarray:
    """(H, W) bool: the union of each agent's 2D box, the bounding rectangle of its pixels in `ids` (−1 = none)."""
    out = np.zeros(ids.shape, dtype=bool)
    for track in np.unique(ids[ids >= 0]):
        rows, cols = np.nonzero(ids == track)
        out[rows.min() : rows.max() + 1, cols.min() : cols.max() + 1] = True
    return out


def lead_mask(ids: np.ndarray, meta: dict[str, Any], lead_range: float = LEAD_RANGE) -> np.ndarray:
    """(H, W) bool: the visible pixels of the frame's lead vehicle when it is within `lead_range` m."""
    lead = meta.get("lead_agent")
    if lead is None or lead["distance"] > lead_range or lead["category"] not in VEHICLES:
        return np.zeros(ids.shape, dtype=bool)
    return ids == lead["track_id"]


def fidelity_frames(samples: Sequence[LabelledSample], rate: float, frames: int,
                    lead_range: float = LEAD_RANGE) -> FidelityFrames:
    """The first `frames` frames at `rate` of each sample with their agent, box and lead masks."""
    out: dict[str, list] = {"frames": [], "agents": [], "boxes": [], "lead": []}
    for sample in samples:
        check_labels(sample)
        clip = sample.clip
        picked = resample_indices(clip.timestamps, rate)[:frames]
        if len(picked) < frames:
            raise ValueError(f"agent fidelity: clip '{clip.clip_id}' has {len(picked)} frames at {rate:g} Hz, "
                             f"{frames} needed")
        times = np.array([s.t for s in sample.states])
        ids = [sample.instance_ids(int(np.abs(times - (clip.timestamps[i] - clip.timestamps[0])).argmin()), 0)
               for i in picked]
        out["frames"].append(to_float(torch.from_numpy(np.ascontiguousarray(clip.frames[0, picked]))))
        out["agents"].append(np.stack([i >= 0 for i in ids]))
        out["boxes"].append(np.stack([box_mask(i) for i in ids]))
        out["lead"].append(np.stack([lead_mask(i, clip.frame_meta[p], lead_range) for i, p in zip(ids, picked)]))
    masks = {k: torch.from_numpy(np.stack(v)) for k, v in out.items() if k != "frames"}
    return FidelityFrames([s.clip.clip_id for s in samples], torch.stack(out["frames"]), **masks)


def region_psnr(x: torch.Tensor, y: torch.Tensor, region: torch.Tensor) -> list[float]:
    """Per-clip PSNR (dB, peak 1 on the [0, 1] scale) of x against y (N, t, 3, H, W) over the pixels of region
    (N, t, H, W); nan for a clip whose region is empty."""
    err = ((x.clamp(-1, 1) - y.clamp(-1, 1)) / 2).pow(2).mean(dim=2)
    out = []
    for e, r in zip(err, region):
        mse = float(e[r].mean()) if r.any() else float("nan")
        out.append(10 * np.log10(1.0 / max(mse, 1e-10)) if np.isfinite(mse) else float("nan"))
    return out


@torch.no_grad()
def region_lpips(distance_map: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], x: torch.Tensor, y: torch.Tensor,
                 region: torch.Tensor, chunk: int = 32) -> list[float]:
    """Per-clip mean of a perceptual distance map (b, 3, H, W) × 2 → (b, H, W) over the pixels of region (N, t, H, W)
    (e.g. `PerceptualDistance.distance_map`, LPIPS with spatial output); nan for a clip whose region is empty."""
    out = []
    for a, b, r in zip(x, y, region):
        if not r.any():
            out.append(float("nan"))
            continue
        maps = torch.cat([distance_map(p, q) for p, q in zip(a.split(chunk), b.split(chunk))])
        out.append(float(maps[r].mean()))
    return out


def finite_interval(values: Sequence[float]) -> Estimate:
    """mean_interval over the finite values (clips whose region is empty drop out and n says how many stayed)."""
    kept = [v for v in values if np.isfinite(v)]
    return mean_interval(kept) if kept else Estimate(float("nan"), float("nan"), float("nan"), 0)


def iou_ratio(real: tuple[np.ndarray, np.ndarray], tokenized: tuple[np.ndarray, np.ndarray], resamples: int = 2000,
              seed: int = 0) -> Estimate:
    """(Σ I_tok / Σ U_tok) ÷ (Σ I_real / Σ U_real) over clips from per-clip (intersection, union) counts, with a 95 %
    percentile bootstrap over clips (both IoUs resampled together)."""
    i_r, u_r, i_t, u_t = overlap_counts(real, tokenized)
    return bootstrap(lambda index: pooled_iou(i_t, u_t, index) / pooled_iou(i_r, u_r, index, floor=1e-12),
                     len(i_r), resamples, seed)


def iou_ratio_difference(real: tuple[np.ndarray, np.ndarray], first: tuple[np.ndarray, np.ndarray],
                         second: tuple[np.ndarray, np.ndarray], resamples: int = 2000, seed: int = 0) -> Estimate:
    """agent_iou_ratio of `first` minus that of `second` (two tokenizers' round trips of the same clips), with a
    paired 95 % bootstrap: each draw resamples the clips once, for both tokenizers and the real frames they share."""
    i_r, u_r, i_a, u_a, i_b, u_b = overlap_counts(real, first, second)

    def difference(index: np.ndarray) -> np.ndarray:
        real_iou = pooled_iou(i_r, u_r, index, floor=1e-12)
        return (pooled_iou(i_a, u_a, index) - pooled_iou(i_b, u_b, index)) / real_iou

    return bootstrap(difference, len(i_r), resamples, seed)


def overlap_counts(*pairs: tuple[np.ndarray, np.ndarray]) -> list[np.ndarray]:
    """Per-clip (intersection, union) pairs → one flat list [I, U, I, U, ...] of equal 1-D float arrays."""
    counts = [np.asarray(c, dtype=float) for pair in pairs for c in pair]
    if len({c.shape for c in counts}) != 1 or counts[0].ndim != 1:
        raise ValueError(f"iou_ratio needs equal 1-D per-clip counts, got {[c.shape for c in counts]}")
    return counts


def pooled_iou(intersection: np.ndarray, union: np.ndarray, index: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """Σ I / Σ U over the clips of each row of index (draws, n) → (draws,), at least `floor`."""
    return np.maximum(intersection[index].sum(-1) / np.maximum(union[index].sum(-1), 1e-12), floor)


def bootstrap(statistic: Callable[[np.ndarray], np.ndarray], n: int, resamples: int, seed: int) -> Estimate:
    """statistic over all n clips, with the 95 % percentile interval of `resamples` draws of n clips with
    replacement. statistic: index (draws, n) int → (draws,)."""
    point = float(statistic(np.arange(n)[None])[0])
    draws = statistic(np.random.default_rng(seed).integers(0, n, size=(resamples, n)))
    return Estimate(point, float(np.quantile(draws, 0.025)), float(np.quantile(draws, 0.975)), n)


def per_clip_overlap(predicted: torch.Tensor, masks: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Per-clip (intersection, union) pixel counts of predicted and true masks (N, t, H, W)."""
    if predicted.shape != masks.shape:
        raise ValueError(f"agent fidelity: predicted masks {tuple(predicted.shape)} and masks {tuple(masks.shape)} "
                         "differ")
    dims = tuple(range(1, masks.ndim))
    return (predicted & masks).sum(dims).numpy(), (predicted | masks).sum(dims).numpy()


def per_frame_overlap(predicted: torch.Tensor, masks: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(intersection, union) pixel counts (N, t) per clip and frame index of predicted and true masks (N, t, H, W):
    a tokenizer that compresses time (GAIA-2's 4-frame tubelets) may keep agents better in some frames of a latent
    step than in others."""
    if predicted.shape != masks.shape:
        raise ValueError(f"agent fidelity: predicted masks {tuple(predicted.shape)} and masks {tuple(masks.shape)} "
                         "differ")
    return (predicted & masks).sum((2, 3)).numpy(), (predicted | masks).sum((2, 3)).numpy()


def iou_ratio_by_frame(real: tuple[np.ndarray, np.ndarray], tokenized: tuple[np.ndarray, np.ndarray],
                       resamples: int = 2000) -> list[Estimate]:
    """iou_ratio of each frame index from (N, t) per-frame counts (per_frame_overlap): t estimates."""
    return [iou_ratio((real[0][:, k], real[1][:, k]), (tokenized[0][:, k], tokenized[1][:, k]), resamples)
            for k in range(real[0].shape[1])]


def lead_found(predicted: torch.Tensor, lead: torch.Tensor,
               share: float = FOUND_SHARE) -> tuple[np.ndarray, np.ndarray]:
    """Per clip: (frames where the probe covers ≥ `share` of the lead vehicle's pixels, frames with a lead vehicle),
    from predicted and lead masks (N, t, H, W)."""
    visible = lead.sum(dim=(2, 3))
    covered = (predicted & lead).sum(dim=(2, 3))
    present = visible > 0
    found = present & (covered >= share * visible)
    return found.sum(1).numpy(), present.sum(1).numpy()


def lead_share(found: np.ndarray, present: np.ndarray) -> Estimate:
    """Pooled share of lead frames found, with a bootstrap interval over clips (frames of one clip are not
    independent)."""
    if present.sum() == 0:
        return Estimate(float("nan"), float("nan"), float("nan"), 0)
    keep = present > 0
    return ratio_interval(found[keep], present[keep])
