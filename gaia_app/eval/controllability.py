"""Controllability of GAIA-1 rollouts, measured with probes trained on the synthetic world's ground truth.

Legend: N clips, t frames at the world model's rate, k futures, H × W images in [-1, 1].

GAIA-1 §7 shows action and text control qualitatively. Here two probes (gaia_app/models/probes.py) read
the conditions back from frames:
- action adherence: mean |probe(frame_{t-1}, frame_t) − commanded a_{t-1}| over the generated steps,
  speed in m/s and curvature in 1/m (a_{t-1} is the action that leads from frame t-1 to frame t, as in eq. 1);
- text adherence: the share of generated frames whose probed weather / time of day is the prompt's.
Each model number sits next to two references from the same run: the ceiling (real synthetic clips: for
actions the same scenes re-simulated with the commanded actions) and the floor (rollouts with the
condition dropped, scored against the same commands or prompts).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from tqdm.auto import tqdm

from gaia_app.data.clip import Clip
from gaia_app.data.transforms import resample_clip, to_float
from gaia_app.models.probes import ATTRIBUTES, InverseDynamicsProbe, SceneAttributeProbe


@dataclass
class ProbeClips:
    """frames (N, t, 3, H, W) in [-1, 1], actions (N, t, 2), labels {attribute: (N, t) class index}."""

    frames: torch.Tensor
    actions: torch.Tensor
    labels: dict[str, torch.Tensor]


def attribute_labels(clip: Clip) -> dict[str, np.ndarray]:
    """(t,) class indices per attribute from the clip's metadata (no traffic light ahead: 'none')."""
    t = clip.frames.shape[1]
    meta, frames = clip.meta, clip.frame_meta or [{}] * t
    lights = [fm.get("traffic_light") or "none" for fm in frames]
    return {"weather": np.full(t, ATTRIBUTES["weather"].index(meta["weather"])),
            "time_of_day": np.full(t, ATTRIBUTES["time_of_day"].index(meta["time_of_day"])),
            "traffic_light": np.array([ATTRIBUTES["traffic_light"].index(s) for s in lights])}


def probe_clips(clips: Sequence[Clip], rate: float, frames: int) -> ProbeClips:
    """The first camera of each clip, resampled to `rate`, its first `frames` frames (all clips need as many)."""
    out = {"frames": [], "actions": [], "labels": []}
    for clip in clips:
        clip = resample_clip(clip, rate)
        if clip.frames.shape[1] < frames or clip.actions is None:
            raise ValueError(f"probe clip '{clip.clip_id}': {clip.frames.shape[1]} frames at {rate:g} Hz "
                             f"(need {frames}) and actions are required")
        out["frames"].append(to_float(torch.from_numpy(clip.frames[0, :frames])))
        out["actions"].append(torch.from_numpy(clip.actions[:frames]))
        out["labels"].append(attribute_labels(clip))
    labels = {name: torch.from_numpy(np.stack([lab[name][:frames] for lab in out["labels"]])) for name in ATTRIBUTES}
    return ProbeClips(torch.stack(out["frames"]), torch.stack(out["actions"]), labels)


def train_probes(data: ProbeClips, steps: int = 300, batch: int = 32, lr: float = 2e-3, seed: int = 0,
                 progress: bool = True) -> tuple[InverseDynamicsProbe, SceneAttributeProbe, dict[str, float]]:
    """Fit both probes on random frame pairs / frames of `data`; returns them (eval mode) and their first/last losses."""
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    dynamics, scene = InverseDynamicsProbe(), SceneAttributeProbe()
    optim = torch.optim.AdamW([*dynamics.parameters(), *scene.parameters()], lr=lr, weight_decay=1e-4)
    n, t = data.frames.shape[:2]
    losses = []
    for _ in tqdm(range(steps), desc="probes", disable=not progress):
        clip = torch.randint(n, (batch,), generator=generator)
        step = torch.randint(1, t, (batch,), generator=generator)
        pair = torch.stack([data.frames[clip, step - 1], data.frames[clip, step]], dim=1)
        labels = {name: data.labels[name][clip, step] for name in ATTRIBUTES}
        loss = dynamics.loss(pair, data.actions[clip, step - 1]) + scene.loss(data.frames[clip, step], labels)
        optim.zero_grad()
        loss.backward()
        optim.step()
        losses.append(float(loss.detach()))
    return dynamics.eval(), scene.eval(), {"first_loss": float(np.mean(losses[:10])), "last_loss": float(np.mean(losses[-10:]))}


@torch.no_grad()
def action_error(probe: InverseDynamicsProbe, frames: torch.Tensor, commanded: torch.Tensor, start: int) -> dict[str, float]:
    """Mean absolute error of the probed actions against `commanded`, over the steps into frames start..t-1.

    frames: (b, t, 3, H, W); commanded: (b, t, 2) per-step actions (a_{i-1} leads to frame i); start ≥ 1.
    """
    pairs = torch.stack([frames[:, start - 1 : -1], frames[:, start:]], dim=2)  # (b, t - start, 2, 3, H, W)
    probed = probe(pairs.flatten(0, 1)).view(*pairs.shape[:2], 2)
    error = (probed - commanded[:, start - 1 : -1]).abs()
    return {"speed_mae": float(error[..., 0].mean()), "curvature_mae": float(error[..., 1].mean())}


@torch.no_grad()
def attribute_accuracy(probe: SceneAttributeProbe, frames: torch.Tensor, targets: dict[str, torch.Tensor]) -> dict[str, float]:
    """Share of frames (b, f, 3, H, W) whose probed class equals targets {attribute: (b,) class index}."""
    logits = probe(frames.flatten(0, 1))
    out = {}
    for name, target in targets.items():
        predicted = logits[name].argmax(-1).view(frames.shape[:2])
        out[name] = float((predicted == target[:, None]).float().mean())
    return out
