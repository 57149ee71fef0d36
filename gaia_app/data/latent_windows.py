"""Windows of a latent cache (latent_cache.py) for the GAIA-2 latent world model, with per-step conditions.

Legend: v cameras, t latent steps per window, τ frames per step, C h w latent channels and grid, N agents.

Per-frame labels become per-step ones: actions are averaged over the τ frames of a step, the timestamp
and agents are those of the step's first frame, the caption that of its middle frame.

Training windows start uniformly in their clip (`window_sampling="uniform"`, the report's protocol as far as it says),
or where the ego's command changes (`"action_change"`, ours): a start is drawn with probability proportional to the
square of how far the mean command of the window's steps from `change_after` on differs from that of the steps
before, each component in units of its spread over the training cache. The command is (acceleration, curvature), the
speed's rate of change rather than the speed: a constant braking lowers the speed in every window after its onset,
but its acceleration changes only at the onset. A command's onset is rare in driving logs (in the synthetic world an
open-loop switch falls in the generated half of about a sixth of the windows), yet it is what a rollout asked to turn
or brake must produce from a context that does not (docs/paper_faithful.md, "Where the GAIA-2 curvature goes").
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from gaia_app.data.clip import ClipError
from gaia_app.data.collate import stack_labels
from gaia_app.data.latent_cache import LatentClip, find_latent_clips, read_latent_clip
from gaia_app.data.metadata import MetadataEncoder
from gaia_app.data.resumable import train_loader

WINDOW_SAMPLING = ("uniform", "action_change")


class LatentWindows(Dataset):
    """Item: `steps` consecutive latent steps of one cached clip (random start when `random_window`, drawn as
    `window_sampling` says; the module docstring). `change_after`: the latent steps before the action change that
    "action_change" looks for (a rollout's context steps), in [1, steps − 1].

    Returns {"mean", "logvar": (v, t, C, h, w), "timestamps": (t,), "actions"?: (t, 2), "agents"?: t AgentBoxes,
    "text"?: str, "intrinsics"/"extrinsics"?: (v, 3, 3)/(v, 4, 4), "image_size": (H, W), "metadata": {field: int},
    "clip_id"}. Absent labels stay absent.
    """

    def __init__(self, folders: Sequence[Path], steps: int, metadata: MetadataEncoder, random_window: bool = True,
                 window_sampling: str = "uniform", change_after: int = 2):
        self.clips: list[LatentClip] = [read_latent_clip(f) for f in folders]
        short = [c.clip_id for c in self.clips if c.mean.shape[1] < steps]
        if short:
            raise ClipError(f"latent clips {short[:5]} have fewer than steps={steps} latent steps")
        if window_sampling not in WINDOW_SAMPLING:
            raise ValueError(f"window_sampling={window_sampling!r}: expected one of {WINDOW_SAMPLING}")
        self.steps, self.metadata, self.random_window = steps, metadata, random_window
        self.start_weights: list[torch.Tensor] | None = None
        if window_sampling == "action_change" and random_window:
            self.start_weights = action_change_weights(self.clips, steps, change_after)

    def __len__(self) -> int:
        return len(self.clips)

    def __getitem__(self, index: int) -> dict[str, Any]:
        clip = self.clips[index]
        if self.start_weights is None:
            return random_latent_window(clip, self.steps, self.metadata, self.random_window)
        start = int(torch.multinomial(self.start_weights[index], 1).item())
        return latent_window(clip, start, self.steps, self.metadata)


def clips_where(folders: Sequence[Path], where: Mapping[str, Any], cache: Path) -> list[Path]:
    """The clip folders whose conditions.json `meta` holds every key of `where` at its value (all of them when `where`
    is empty; a clip without the key does not match). ClipError naming the cache when a key is in no clip's meta (a
    misspelt key would otherwise select nothing, or everything) or when no clip matches."""
    if not where:
        return list(folders)
    metas = [json.loads((f / "conditions.json").read_text()).get("meta") or {} for f in folders]
    unknown = sorted(k for k in where if not any(k in m for m in metas))
    if unknown:
        raise ClipError(f"data.train_meta: key(s) {unknown} appear in no clip's meta under '{cache}' "
                        f"(keys there: {sorted(set().union(*metas))})")
    chosen = [f for f, m in zip(folders, metas, strict=True) if all(k in m and m[k] == v for k, v in where.items())]
    if not chosen:
        raise ClipError(f"data.train_meta={dict(where)}: none of the {len(folders)} clips under '{cache}' match")
    return chosen


def step_commands(clip: LatentClip) -> np.ndarray:
    """(t, 2) per latent step: (acceleration m/s², curvature 1/m), each the mean over the step's τ frames (as
    `latent_window` averages actions); a frame's acceleration is its speed minus the previous frame's times the frame
    rate (the first frame takes the second's), so a command that starts within a step shows in that step's share."""
    speed = clip.actions[:, 0].astype(np.float64)
    acceleration = np.diff(speed, prepend=speed[0] if len(speed) < 2 else 2 * speed[0] - speed[1]) * clip.fps
    per_frame = np.stack([acceleration, clip.actions[:, 1].astype(np.float64)], axis=1)
    return per_frame.reshape(-1, clip.temporal_downsampling, 2).mean(1)


def action_changes(commands: np.ndarray, steps: int, change_after: int, spread: np.ndarray) -> np.ndarray:
    """commands (t, 2) per latent step → (t − steps + 1,) per window start: the L1 distance between the mean command
    of the window's steps from `change_after` on and that of its steps before, each component divided by `spread`."""
    windows = np.lib.stride_tricks.sliding_window_view(commands, steps, axis=0)  # (starts, 2, steps)
    before, after = windows[..., :change_after].mean(-1), windows[..., change_after:].mean(-1)
    return (np.abs(after - before) / spread).sum(-1)


def start_probabilities(clips: Sequence[LatentClip], steps: int, window_sampling: str,
                        change_after: int = 2) -> list[torch.Tensor]:
    """Per clip, (starts,) float64 probability of each training window start under `window_sampling` (uniform, or
    `action_change_weights`)."""
    if window_sampling not in WINDOW_SAMPLING:
        raise ValueError(f"window_sampling={window_sampling!r}: expected one of {WINDOW_SAMPLING}")
    if window_sampling == "action_change":
        return action_change_weights(clips, steps, change_after)
    return [torch.full((c.mean.shape[1] - steps + 1,), 1 / (c.mean.shape[1] - steps + 1), dtype=torch.float64)
            for c in clips]


def action_change_weights(clips: Sequence[LatentClip], steps: int, change_after: int) -> list[torch.Tensor]:
    """Per clip, (starts,) probabilities of its window starts ∝ the square of `action_changes` of its `step_commands`
    (the module docstring): squared, the start whose generated steps begin where the command changes outweighs the
    two starts that hold half the change (its onset in their last context or last generated step) 4 : 1 each. A clip
    whose command never changes gets uniform starts. ClipError naming a clip without actions."""
    if not 1 <= change_after < steps:
        raise ValueError(f"change_after={change_after}: expected a number of latent steps in [1, steps − 1 = "
                         f"{steps - 1}]")
    missing = [c.clip_id for c in clips if c.actions is None]
    if missing:
        raise ClipError(f"window_sampling=action_change needs actions; latent clips {missing[:5]} have none")
    return change_probabilities([step_commands(c) for c in clips], steps, change_after)


def change_probabilities(per_clip: Sequence[np.ndarray], steps: int, change_after: int) -> list[torch.Tensor]:
    """Per clip's commands (t, 2), (t − steps + 1,) float64 start probabilities ∝ `action_changes` ** 2, each component
    in units of its spread over all clips; uniform where the command never changes. Shared by the latent windows and
    GAIA-1's token windows (token_cache.py)."""
    spread = np.concatenate(per_clip).std(0) + 1e-6
    weights = []
    for commands in per_clip:
        change = action_changes(commands, steps, change_after, spread) ** 2
        total = change.sum()
        weights.append(torch.from_numpy(change / total if total > 0 else np.full_like(change, 1 / len(change))))
    return weights


def random_latent_window(clip: LatentClip, steps: int, metadata: MetadataEncoder,
                         random_window: bool) -> dict[str, Any]:
    """A window of `steps` latent steps of `clip` at a random start (random_window) or at its start."""
    last = clip.mean.shape[1] - steps
    if last < 0:
        raise ClipError(f"latent clip '{clip.clip_id}' has {clip.mean.shape[1]} latent steps, fewer than steps={steps}")
    start = int(torch.randint(0, last + 1, ()).item()) if random_window and last > 0 else 0
    return latent_window(clip, start, steps, metadata)


def latent_window(clip: LatentClip, start: int, steps: int, metadata: MetadataEncoder) -> dict[str, Any]:
    """Latent steps start..start+steps-1 of `clip` with their per-step conditions (the `LatentWindows` item)."""
    if start < 0 or start + steps > clip.mean.shape[1]:
        raise ClipError(f"latent clip '{clip.clip_id}': steps {start}..{start + steps - 1} requested, "
                        f"it has {clip.mean.shape[1]} latent steps")
    tau = clip.temporal_downsampling
    frames = slice(start * tau, (start + steps) * tau)
    first = np.arange(start, start + steps) * tau
    middle = first[steps // 2] + tau // 2
    sample: dict[str, Any] = {
        "clip_id": clip.clip_id,
        "mean": torch.from_numpy(clip.mean[:, start : start + steps]),
        "logvar": torch.from_numpy(clip.logvar[:, start : start + steps]),
        "timestamps": torch.from_numpy(clip.timestamps[first] - clip.timestamps[first[0]]).float(),
        "image_size": clip.image_size,
        "metadata": metadata.encode(clip.meta, clip.frame_meta[middle] if clip.frame_meta else None),
    }
    if clip.actions is not None:
        sample["actions"] = torch.from_numpy(clip.actions[frames].reshape(steps, tau, 2).mean(1))
    if clip.agents is not None:
        sample["agents"] = [clip.agents[i] for i in first]
    if clip.text is not None:
        sample["text"] = clip.text[middle] or ""
    if clip.cameras is not None:
        sample["intrinsics"] = torch.tensor(np.stack([c.intrinsics for c in clip.cameras]), dtype=torch.float32)
        sample["extrinsics"] = torch.tensor(np.stack([c.extrinsics for c in clip.cameras]), dtype=torch.float32)
    return sample


def collate_latent_windows(samples: list[dict[str, Any]]) -> dict[str, Any]:
    """Stack windows; a label present in some windows only is an error naming the clips."""
    batch: dict[str, Any] = {"clip_id": [s["clip_id"] for s in samples], "image_size": samples[0]["image_size"]}
    sizes = {tuple(s["image_size"]) for s in samples}
    if len(sizes) > 1:
        raise ClipError(f"latent batch mixes image sizes {sorted(sizes)}")
    stack_labels(samples, ("mean", "logvar", "timestamps", "actions", "intrinsics", "extrinsics", "agents", "text"),
                 batch)
    fields = samples[0]["metadata"].keys()
    batch["metadata"] = {name: torch.tensor([s["metadata"][name] for s in samples]) for name in fields}
    return batch


class LatentCacheDataModule(L.LightningDataModule):
    """Latent-cache windows for the GAIA-2 world model: `<path>/train` and `<path>/val` from `generate.py mode=encode`.

    Args:
        path: the cache root (out_dir of mode=encode).
        steps: latent steps per window. metadata_fields: the model's metadata fields (MetadataEncoder).
        batch_size, num_workers: loader settings.
        window_sampling, change_after: how training windows start (`LatentWindows`; validation windows start at
            their clip's start).
        train_meta: train only on the clips whose clip-level metadata holds every key at its value (`clips_where`),
            e.g. {open_loop: true} for the clips driven off their policy; validation keeps every clip.
    """

    def __init__(self, path: str, steps: int = 4, metadata_fields: Sequence[str] = (), batch_size: int = 4,
                 num_workers: int = 0, window_sampling: str = "uniform", change_after: int = 2,
                 train_meta: Mapping[str, Any] | None = None):
        super().__init__()
        self.path, self.steps, self.metadata_fields = Path(path), steps, list(metadata_fields)
        self.batch_size, self.num_workers = batch_size, num_workers
        self.window_sampling, self.change_after = window_sampling, change_after
        self.train_meta = dict(train_meta or {})
        self.train_set: LatentWindows | None = None

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        encoder = MetadataEncoder(self.metadata_fields)
        train = clips_where(find_latent_clips(self.path / "train"), self.train_meta, self.path / "train")
        self.train_set = LatentWindows(train, self.steps, encoder, random_window=True,
                                       window_sampling=self.window_sampling, change_after=self.change_after)
        self.val_set = LatentWindows(find_latent_clips(self.path / "val"), self.steps, encoder, random_window=False)

    def train_dataloader(self) -> DataLoader:
        # persistent workers: an epoch is one window per clip, so short that re-forking workers each epoch shows
        return train_loader(self, self.train_set, self.batch_size, num_workers=self.num_workers,
                            drop_last=len(self.train_set) >= self.batch_size,
                            collate_fn=collate_latent_windows, persistent_workers=self.num_workers > 0)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.val_set, batch_size=self.batch_size, num_workers=self.num_workers,
                          collate_fn=collate_latent_windows)
