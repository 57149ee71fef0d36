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
from pathlib import Path

import numpy as np
import torch
import yaml
from einops import rearrange
from tqdm.auto import tqdm

from gaia_app.data.clip import Clip
from gaia_app.data.transforms import resample_clip, to_float
from gaia_app.models.probes import ATTRIBUTES, InverseDynamicsProbe, SceneAttributeProbe
from gaia_app.utils.run_dir import atomic_write_bytes, atomic_write_text

PROBE_WEIGHTS, PROBE_INFO = "probes.safetensors", "probes.yaml"


@dataclass
class ProbeClips:
    """frames (N, t, 3, H, W) in [-1, 1] (one camera) or (N, t, k, 3, H, W) (k cameras of a rig), actions (N, t, 2),
    labels {attribute: (N, t) class index}."""

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


def probe_clips(clips: Sequence[Clip], rate: float, frames: int, cameras: Sequence[int] | None = None) -> ProbeClips:
    """Each clip resampled to `rate`, its first `frames` frames (all clips need as many): the first camera
    (frames (N, t, 3, H, W)), or with `cameras` those camera indices in that order (frames (N, t, k, 3, H, W))."""
    out = {"frames": [], "actions": [], "labels": []}
    for clip in clips:
        clip = resample_clip(clip, rate)
        if clip.frames.shape[1] < frames or clip.actions is None:
            raise ValueError(f"probe clip '{clip.clip_id}': {clip.frames.shape[1]} frames at {rate:g} Hz "
                             f"(need {frames}) and actions are required")
        if cameras is not None and not all(0 <= c < clip.num_views for c in cameras):
            raise ValueError(f"probe clip '{clip.clip_id}': camera indices {list(cameras)}, "
                             f"the clip has {clip.num_views}")
        if cameras is None:
            views = clip.frames[0, :frames]
        else:
            views = rearrange(clip.frames[list(cameras), :frames], "k t ... -> t k ...")
        out["frames"].append(to_float(torch.from_numpy(np.ascontiguousarray(views))))
        out["actions"].append(torch.from_numpy(clip.actions[:frames]))
        out["labels"].append(attribute_labels(clip))
    labels = {name: torch.from_numpy(np.stack([lab[name][:frames] for lab in out["labels"]])) for name in ATTRIBUTES}
    return ProbeClips(torch.stack(out["frames"]), torch.stack(out["actions"]), labels)


def phase_clips(clip: Clip, rate: float, frames: int) -> ProbeClips:
    """Every phase of a clip at `rate`, first camera: with stride s = clip fps / rate (an integer), sequence o
    takes source frames o, o + s, …, o + (frames − 1) s, for o = 0 … s − 1. Each step's action is the mean of the s
    source actions it spans, which is what moves the ego from one frame to the next. For probe training: s times
    the frame pairs of one rendered clip."""
    stride = clip.fps / rate
    if abs(stride - round(stride)) > 1e-6:
        raise ValueError(f"phase_clips: clip '{clip.clip_id}' at {clip.fps:g} Hz "
                         f"is not a whole multiple of {rate:g} Hz")
    stride = round(stride)
    if clip.actions is None or clip.num_frames < frames * stride:
        raise ValueError(f"phase_clips: clip '{clip.clip_id}' needs actions and {frames * stride} frames "
                         f"({frames} at {rate:g} Hz, every phase), has {clip.num_frames}")
    labels, source = attribute_labels(clip), torch.from_numpy(clip.actions.astype(np.float32))
    out = {"frames": [], "actions": [], "labels": []}
    for offset in range(stride):
        index = offset + stride * np.arange(frames)
        out["frames"].append(to_float(torch.from_numpy(clip.frames[0, index])))
        # the action between frames index[k] and index[k + 1]: the mean over the s source frames in between
        out["actions"].append(torch.stack([source[i : i + stride].mean(dim=0) for i in index]))
        out["labels"].append({name: torch.from_numpy(values[index]) for name, values in labels.items()})
    return ProbeClips(torch.stack(out["frames"]), torch.stack(out["actions"]),
                      {name: torch.stack([lab[name] for lab in out["labels"]]) for name in ATTRIBUTES})


def cat_probe_clips(parts: Sequence[ProbeClips]) -> ProbeClips:
    """The clips of several ProbeClips, in order."""
    return ProbeClips(torch.cat([p.frames for p in parts]), torch.cat([p.actions for p in parts]),
                      {name: torch.cat([p.labels[name] for p in parts]) for name in ATTRIBUTES})


def augment_pairs(pair: torch.Tensor, actions: torch.Tensor, generator: torch.Generator,
                  mirror: Sequence[int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Mirror half of the pairs left–right and negate their curvature: a left turn seen in a mirror is a right turn,
    so every scene teaches both signs (weather, time of day and lights are unchanged). pair (b, 2, 3, H, W), or
    (b, 2, k, 3, H, W) for a rig whose mirror image puts camera `mirror[j]` where camera j was (a left-right
    symmetric rig: front stays, front_left and front_right swap)."""
    if pair.dim() == 6 and (mirror is None or sorted(mirror) != list(range(pair.shape[2]))):
        raise ValueError(f"augment_pairs: a rig of {pair.shape[2]} cameras needs its mirror order "
                         f"(a permutation), got {mirror}")
    mirrored = pair.flip(-1) if pair.dim() == 5 else pair.flip(-1)[:, :, list(mirror)]
    flip = torch.rand(len(pair), generator=generator) < 0.5
    pair = torch.where(flip.view(-1, *[1] * (pair.dim() - 1)), mirrored, pair)
    return pair, torch.where(flip[:, None], actions * torch.tensor([1.0, -1.0]), actions)


def jitter(pair: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Random gain and offset per pair (both frames alike): the inverse-dynamics probe must read motion, not the
    brightness of a scene it has memorised. Not for the scene probe, for which brightness is time of day."""
    shape = (len(pair), *[1] * (pair.dim() - 1))  # one gain and offset per pair, every frame and camera of it alike
    gain = torch.empty(shape).uniform_(0.6, 1.4, generator=generator)
    offset = torch.empty(shape).uniform_(-0.2, 0.2, generator=generator)
    return ((pair + 1) * gain - 1 + offset).clamp(-1, 1)


def train_probes(data: ProbeClips, steps: int = 1500, batch: int = 32, lr: float = 2e-3, seed: int = 0,
                 progress: bool = True, stride: int = 1,
                 mirror: Sequence[int] | None = None,
                 ) -> tuple[InverseDynamicsProbe, SceneAttributeProbe, dict[str, float]]:
    """Fit both probes on random frame pairs / frames of `data` (AdamW, cosine decay to lr/20); returns them in
    eval mode and their first/last losses. The inverse-dynamics probe reads pairs `stride` frames apart and learns
    the mean action over the steps between them (`strided_actions`). With a rig's frames (N, t, k, 3, H, W) it reads
    all k cameras (mirrored with the order `mirror`, `augment_pairs`) and the scene probe the first one."""
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    rig = data.frames.dim() == 6
    dynamics, scene = InverseDynamicsProbe(cameras=data.frames.shape[2] if rig else 1), SceneAttributeProbe()
    optim = torch.optim.AdamW([*dynamics.parameters(), *scene.parameters()], lr=lr, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optim, max(1, steps), eta_min=lr / 20)
    n, t = data.frames.shape[:2]
    if not 1 <= stride < t:
        raise ValueError(f"probe stride {stride}: expected 1 ≤ stride < {t} (the probe clips' frames)")
    moves = strided_actions(data.actions, stride)
    losses = []
    for _ in tqdm(range(steps), desc="probes", disable=not progress):
        clip = torch.randint(n, (batch,), generator=generator)
        step = torch.randint(stride, t, (batch,), generator=generator)
        pair = torch.stack([data.frames[clip, step - stride], data.frames[clip, step]], dim=1)
        labels = {name: data.labels[name][clip, step] for name in ATTRIBUTES}
        pair, actions = augment_pairs(pair, moves[clip, step - 1], generator, mirror)
        loss = (dynamics.loss(jitter(pair, generator), actions)
                + scene.loss(pair[:, 1, 0] if rig else pair[:, 1], labels))
        optim.zero_grad()
        loss.backward()
        optim.step()
        schedule.step()
        losses.append(float(loss.detach()))
    return dynamics.eval(), scene.eval(), {"first_loss": float(np.mean(losses[:10])),
                                           "last_loss": float(np.mean(losses[-10:]))}


def strided_actions(actions: torch.Tensor, stride: int) -> torch.Tensor:
    """(b, t, 2) per-step actions (a_{i-1} leads to frame i) → the same layout for pairs `stride` frames apart: row
    i − 1 holds the mean of a_{i-stride} … a_{i-1}, what moves frame i − stride to frame i (rows before stride − 1
    keep their own step's action). Stride 1 returns `actions`."""
    if stride == 1:
        return actions
    windows = actions.unfold(1, stride, 1).mean(dim=-1)  # (b, t − stride + 1, 2): window j covers a_j … a_{j+stride-1}
    return torch.cat([actions[:, : stride - 1], windows], dim=1)


@torch.no_grad()
def probed_actions(probe: InverseDynamicsProbe, frames: torch.Tensor, start: int, stride: int = 1) -> torch.Tensor:
    """(b, t - start, 2) probed (speed, curvature) moving frame i − stride to frame i, for i = start..t-1;
    frames (b, t, 3, H, W), or (b, t, k, 3, H, W) for a rig probe; start ≥ stride."""
    t = frames.shape[1]
    if not stride <= start < t:  # a pair must start inside the clip; a negative index would wrap around silently
        raise ValueError(f"probed_actions: start {start} must lie in [stride {stride}, frames {t})")
    # (b, t - start, 2, 3, H, W)
    pairs = torch.stack([frames[:, start - stride : t - stride], frames[:, start:]], dim=2)
    return probe(pairs.flatten(0, 1)).view(*pairs.shape[:2], 2)


def action_errors(probe: InverseDynamicsProbe, frames: torch.Tensor, commanded: torch.Tensor,
                  start: int) -> torch.Tensor:
    """(b, 2) mean absolute error per sequence of the probed (speed, curvature) against `commanded`, over the
    steps into frames start..t-1. frames: (b, t, 3, H, W); commanded: (b, t, 2) (a_{i-1} leads to frame i); start ≥ 1.
    """
    return (probed_actions(probe, frames, start) - commanded[:, start - 1 : -1]).abs().mean(dim=1)


def contrast_pairs(commanded: torch.Tensor) -> list[tuple[int, int]]:
    """Per channel (speed, curvature), the (high, low) commands furthest apart: commanded (C, N, s, 2) → 2 pairs.
    Refuses commands that do not differ in a channel (nothing to contrast)."""
    means = commanded.mean(dim=(1, 2))  # (C, 2)
    pairs = [(int(means[:, k].argmax()), int(means[:, k].argmin())) for k in range(2)]
    for k, (high, low) in enumerate(pairs):
        if means[high, k] - means[low, k] < 1e-6:
            raise ValueError(f"controllability.commands: every command has the same {('speed', 'curvature')[k]}; "
                             "the contrast needs two that differ")
    return pairs


def realised_contrasts(probed: torch.Tensor, commanded: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 2) probed and (N, 2) commanded differences (high − low) of the horizon-mean speed and curvature per
    context, for the pairs of `contrast_pairs`; probed, commanded (C, N, s, 2). Signed: how much of a command shows,
    where `contrast_errors` says only how far off it is."""
    probed_mean, commanded_mean = probed.mean(dim=2), commanded.mean(dim=2)  # (C, N, 2)
    pairs = contrast_pairs(commanded)

    def difference(x: torch.Tensor) -> torch.Tensor:
        return torch.stack([x[high, :, k] - x[low, :, k] for k, (high, low) in enumerate(pairs)], dim=1)

    return difference(probed_mean), difference(commanded_mean)


def contrast_errors(probed: torch.Tensor, commanded: torch.Tensor) -> torch.Tensor:
    """(N, 2) per context: |(probed high − probed low) − (commanded high − commanded low)| of the horizon-mean speed
    (high/low: accelerate/brake) and curvature (left/right), the pairs of `contrast_pairs`.

    probed, commanded: (C, N, s, 2) of C commands × N contexts over s scored steps. The probe's error on a scene is
    mostly a bias shared by every future of that scene (it misjudges the depth of the road), which the difference
    of two futures of one context cancels; a model that ignores the commands scores the commanded difference.
    """
    realised, wanted = realised_contrasts(probed, commanded)
    return (realised - wanted).abs()


@torch.no_grad()
def attribute_shares(probe: SceneAttributeProbe, frames: torch.Tensor,
                     targets: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Per sequence, the share of its frames (b, f, 3, H, W) whose probed class equals targets {attribute: (b,)}
    → {attribute: (b,) in [0, 1]}."""
    logits = probe(frames.flatten(0, 1))
    return {name: (logits[name].argmax(-1).view(frames.shape[:2]) == target[:, None]).float().mean(dim=1)
            for name, target in targets.items()}


def save_probes(folder: str | Path, dynamics: InverseDynamicsProbe, scene: SceneAttributeProbe, info: dict) -> None:
    """Write both probes as `probes.safetensors` (weights only) and `probes.yaml` (what they were trained on)."""
    from safetensors.torch import save as save_tensors

    state = {f"{name}.{key}": value.contiguous() for name, probe in (("dynamics", dynamics), ("scene", scene))
             for key, value in probe.state_dict().items()}
    folder = Path(folder)
    atomic_write_bytes(folder / PROBE_WEIGHTS, save_tensors(state))
    atomic_write_text(folder / PROBE_INFO, yaml.safe_dump(info, sort_keys=False))


def load_probes(folder: str | Path, image_size: tuple[int, int],
                rate: float) -> tuple[InverseDynamicsProbe, SceneAttributeProbe, dict]:
    """Probes saved by `save_probes`; they must have been trained at this image size and rate."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    folder = Path(folder)
    weights, info_path = folder / PROBE_WEIGHTS, folder / PROBE_INFO
    for path in (weights, info_path):
        if not path.is_file():
            raise FileNotFoundError(f"controllability.probes={folder}: {path.name} is missing (train probes by leaving "
                                    f"controllability.probes=null; the run dir's probes/ folder can be reused)")
    info = yaml.safe_load(info_path.read_text()) or {}
    if tuple(info.get("image_size", ())) != tuple(image_size) or float(info.get("rate", -1)) != float(rate):
        raise ValueError(f"{info_path}: probes trained for image size {info.get('image_size')} "
                         f"at {info.get('rate')} Hz; "
                         f"this pipeline needs {list(image_size)} at {rate:g} Hz")
    try:
        state = load_file(str(weights))
    except (SafetensorError, OSError) as error:
        raise ValueError(f"{weights}: not a readable safetensors file ({error})") from error
    probes = (InverseDynamicsProbe(), SceneAttributeProbe())
    for name, probe in zip(("dynamics", "scene"), probes):
        part = {key[len(name) + 1:]: value for key, value in state.items() if key.startswith(f"{name}.")}
        try:
            probe.load_state_dict(part)
        except RuntimeError as error:
            raise ValueError(f"{weights}: the {name} probe does not match this version's architecture "
                             f"({error})") from error
        probe.eval()
    return probes[0], probes[1], info


def action_error(probe: InverseDynamicsProbe, frames: torch.Tensor, commanded: torch.Tensor,
                 start: int) -> dict[str, float]:
    """`action_errors` averaged over the sequences: {"speed_mae": m/s, "curvature_mae": 1/m}."""
    errors = action_errors(probe, frames, commanded, start)
    return {"speed_mae": float(errors[:, 0].mean()), "curvature_mae": float(errors[:, 1].mean())}
