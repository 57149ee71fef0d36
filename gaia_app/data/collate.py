"""Batching of samples from `datasets.py`: stack tensors, pad agents with a mask, refuse mixed labels."""

from __future__ import annotations

from typing import Any

import torch

from gaia_app.data.clip import AgentBoxes, ClipError

_STACKED = ("video", "timestamps", "actions", "intrinsics", "extrinsics")


def collate_frames(samples: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """{"image": (k, 3, H, W), "agent_box"?: (k, H, W)} per sample → the same keys concatenated over samples."""
    return {key: torch.cat([s[key] for s in samples]) for key in samples[0]}


def pad_agents(per_sample: list[list[AgentBoxes]]) -> dict[str, torch.Tensor]:
    """Agents of b samples × t steps → padded (b, t, N, …) tensors plus a (b, t, N) bool mask."""
    b, t = len(per_sample), len(per_sample[0])
    n = max(1, max(len(a) for steps in per_sample for a in steps))
    out = {
        "agents_centre": torch.zeros(b, t, n, 3),
        "agents_size": torch.zeros(b, t, n, 3),
        "agents_yaw": torch.zeros(b, t, n),
        "agents_category": torch.zeros(b, t, n, dtype=torch.long),
        "agents_track_id": torch.full((b, t, n), -1, dtype=torch.long),
        "agents_mask": torch.zeros(b, t, n, dtype=torch.bool),
    }
    for i, steps in enumerate(per_sample):
        for j, a in enumerate(steps):
            k = len(a)
            out["agents_centre"][i, j, :k] = torch.from_numpy(a.centre)
            out["agents_size"][i, j, :k] = torch.from_numpy(a.size)
            out["agents_yaw"][i, j, :k] = torch.from_numpy(a.yaw)
            out["agents_category"][i, j, :k] = torch.from_numpy(a.category)
            out["agents_track_id"][i, j, :k] = torch.from_numpy(a.track_id)
            out["agents_mask"][i, j, :k] = True
    return out


def stack_labels(samples: list[dict[str, Any]], keys: tuple[str, ...], batch: dict[str, Any]) -> dict[str, Any]:
    """Add each of `keys` to `batch`: tensors stacked, "agents" padded, "text" listed; a label present in some
    samples but not others is an error naming the clips."""
    for key in keys:
        have = [key in s for s in samples]
        if not any(have):
            continue
        if not all(have):
            missing = [s["clip_id"] for s in samples if key not in s]
            raise ClipError(f"batch mixes clips with and without '{key}': missing in {missing}")
        values = [s[key] for s in samples]
        if key == "agents":
            batch.update(pad_agents(values))
        elif key == "text":
            batch["text"] = values
        else:
            batch[key] = torch.stack(values)
    return batch


def collate_clips(samples: list[dict[str, Any]]) -> dict[str, Any]:
    """Stack clip samples (`stack_labels`)."""
    batch: dict[str, Any] = {"clip_id": [s["clip_id"] for s in samples], "meta": [s["meta"] for s in samples]}
    return stack_labels(samples, (*_STACKED, "text", "agents"), batch)


def collate_token_windows(samples: list[dict[str, Any]]) -> dict[str, Any]:
    """Token windows → {"tokens": (b, t, n), "actions"?: (b, t, 2), "timestamps"?: (b, t), "text"?: b lists of t}.

    A key present in some windows but not others (e.g. one segment without captions) is an error.
    """
    batch: dict[str, Any] = {}
    for key in sorted(set().union(*samples)):
        have = [key in s for s in samples]
        if not all(have):
            raise ClipError(f"token batch mixes windows with and without '{key}' "
                            f"({sum(have)} of {len(samples)} have it)")
        values = [s[key] for s in samples]
        batch[key] = values if key == "text" else torch.stack(values)
    return batch
