"""LightningDataModules: frames (image tokenizers), clips (video models), token caches (world models)."""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any

import lightning as L
import numpy as np
from torch.utils.data import DataLoader, Dataset, Subset

from gaia_app.data.clip import ClipError
from gaia_app.data.collate import collate_clips, collate_frames, collate_token_windows
from gaia_app.data.datasets import ClipsDataset, ClipSource, FramesDataset
from gaia_app.data.resumable import train_loader
from gaia_app.data.sampling import BalancedSampler, balancing_weights, clip_features
from gaia_app.data.token_cache import TokenWindows, find_segments, load_segment, split_spans

log = logging.getLogger(__name__)


def check_count(value: Any, name: str, minimum: int = 1) -> int:
    """`value` as an int ≥ `minimum`, else a ValueError naming the setting (e.g. data.batch_size=abc)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name}={value!r}: expected an integer ≥ {minimum}")
    return int(value)


def split_by_clip(source: ClipSource, val_fraction: float, seed: int) -> tuple[Subset, Subset]:
    """Random clip-level split: every frame of a clip lands on one side only."""
    n = len(source)
    if n < 2:
        raise ValueError(f"split_by_clip: need at least 2 clips to split, got {n}; give val_source explicitly")
    order = np.random.default_rng(seed).permutation(n)
    n_val = min(n - 1, max(1, int(round(val_fraction * n))))
    return Subset(source, sorted(order[n_val:].tolist())), Subset(source, sorted(order[:n_val].tolist()))


# clip metadata that names the drive a clip was cut from, in order of preference (dashcam: source_video;
# PandaSet: sequence); a clip with none of them is a run of its own
RUN_KEYS = ("run_id", "source_video", "sequence")
SPLITS = ("run", "clip")


def clip_metadata(source: ClipSource) -> list[dict[str, Any]]:
    """Clip-level metadata of every clip, from a cheap `describe(i)` when the source has one."""
    describe = getattr(source, "describe", None)
    return [describe(i) if describe else dict(source[i].meta) for i in range(len(source))]


def clip_runs(metas: list[dict[str, Any]], run_keys: Sequence[str]) -> list[str]:
    """The run (drive) of each clip: its first `run_keys` value, else the clip alone (counted in the log)."""
    runs, alone = [], 0
    for i, meta in enumerate(metas):
        key = next((f"{k}={meta[k]}" for k in run_keys if meta.get(k) not in (None, "")), None)
        alone += key is None
        runs.append(key or f"clip#{i}")
    if alone:
        log.info("split by run: %d of %d clips name no run (%s); each is a run of its own", alone, len(metas),
                 ", ".join(run_keys))
    return runs


def in_region(meta: dict[str, Any], region: Sequence[float], gps_key: str, index: int) -> bool:
    """Whether a clip's `gps_key` [lat, lon] lies in region [lat_min, lat_max, lon_min, lon_max]."""
    position = meta.get(gps_key)
    if position is None or len(position) != 2:
        raise ValueError(f"data.val_region: clip {index} has no metadata '{gps_key}' [lat, lon] (the dashcam importer "
                         "writes it from a log with lat/lon); a geofenced split needs it on every clip")
    lat_min, lat_max, lon_min, lon_max = region
    return lat_min <= position[0] <= lat_max and lon_min <= position[1] <= lon_max


def split_by_run(source: ClipSource, val_fraction: float, seed: int, run_keys: Sequence[str] = RUN_KEYS,
                 val_region: Sequence[float] | None = None, gps_key: str = "gps_start") -> tuple[Subset, Subset]:
    """Split whole runs (GAIA-1 §3: validation drives and geofenced regions are held out), never segments of one:
    every clip of a run lands on the same side. Without `val_region` a random `val_fraction` of the runs is
    validation; with it ([lat_min, lat_max, lon_min, lon_max]), every run with a clip starting inside the box."""
    metas = clip_metadata(source)
    runs = clip_runs(metas, run_keys)
    names = sorted(set(runs))
    if val_region is not None:
        if len(val_region) != 4:
            raise ValueError(f"data.val_region={list(val_region)}: expected [lat_min, lat_max, lon_min, lon_max]")
        held = {runs[i] for i, meta in enumerate(metas) if in_region(meta, val_region, gps_key, i)}
        if not held or len(held) == len(names):
            raise ValueError(f"data.val_region={list(val_region)} holds {len(held)} of {len(names)} runs: both sides "
                             "need at least one")
    else:
        if len(names) < 2:
            raise ValueError(f"split by run: the {len(metas)} clips come from {len(names)} run; give at least two "
                             "drives, data.val_source, or data.split_by=clip")
        order = np.random.default_rng(seed).permutation(len(names))
        held = {names[j] for j in order[: min(len(names) - 1, max(1, int(round(val_fraction * len(names)))))]}
    train = [i for i, run in enumerate(runs) if run not in held]
    return Subset(source, train), Subset(source, [i for i, run in enumerate(runs) if run in held])


def source_features(source: ClipSource, names: Sequence[str]) -> dict[str, list]:
    """Balancing features of every clip; uses a cheap `describe(i)` when the source has one."""
    describe = getattr(source, "describe", None)
    rows = [describe(i) if describe else clip_features(source[i], names) for i in range(len(source))]
    return {name: [row[name] for row in rows] for name in names}


class ClipSourceDataModule(L.LightningDataModule, ABC):
    """Common part: train/val clip sources, the clip-level split, loaders and balancing.

    Args:
        source: clip source for training (and validation when val_source is None).
        val_source: separate validation source (e.g. the synthetic world with another seed).
        val_fraction, split_seed: the split of `source` when val_source is None.
        split_by: "clip" (random clips) or "run" (whole drives, `split_by_run`: run_keys name the drive in the
            clips' metadata; val_region [lat_min, lat_max, lon_min, lon_max] geofences validation by `gps_start`).
        batch_size, num_workers: loader settings.
        height, width: model resolution (paper 288×512); resize_mode 'crop' keeps the aspect.
        balance: None, or {"features": {name: bins}, "exponent": float} (GAIA-1 §3).
    """

    def __init__(self, source: ClipSource, val_source: ClipSource | None = None, val_fraction: float = 0.1,
                 split_seed: int = 0, batch_size: int = 8, num_workers: int = 0, height: int = 64, width: int = 112,
                 resize_mode: str = "crop", balance: dict[str, Any] | None = None, split_by: str = "clip",
                 run_keys: Sequence[str] = RUN_KEYS, val_region: Sequence[float] | None = None):
        super().__init__()
        if split_by not in SPLITS:
            raise ValueError(f"data.split_by={split_by!r}: expected one of {SPLITS}")
        if val_region is not None and split_by != "run":
            raise ValueError("data.val_region geofences whole runs: set data.split_by=run")
        self.split_by, self.run_keys, self.val_region = split_by, tuple(run_keys), val_region
        self.source, self.val_source = source, val_source
        self.val_fraction, self.split_seed = val_fraction, split_seed
        self.batch_size = check_count(batch_size, "data.batch_size")
        self.num_workers = check_count(num_workers, "data.num_workers", minimum=0)
        self.height, self.width, self.resize_mode = height, width, resize_mode
        self.balance = balance
        self.train_set: Dataset | None = None
        self.val_set: Dataset | None = None

    @abstractmethod
    def wrap(self, source: ClipSource, train: bool) -> Dataset:
        """The sample-producing dataset over a clip source."""

    @abstractmethod
    def collate(self, samples: list) -> Any:
        """Batch a list of samples."""

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        if self.val_source is not None:
            train, val = self.source, self.val_source
        elif self.split_by == "run":
            train, val = split_by_run(self.source, self.val_fraction, self.split_seed, self.run_keys, self.val_region)
        else:
            train, val = split_by_clip(self.source, self.val_fraction, self.split_seed)
        self.train_clips, self.val_clips = train, val
        self.train_set, self.val_set = self.wrap(train, True), self.wrap(val, False)

    def _sampler(self) -> BalancedSampler | None:
        if not self.balance:
            return None
        features = dict(self.balance["features"])
        weights = balancing_weights(source_features(self.train_clips, list(features)), features,
                                    self.balance["exponent"])
        return BalancedSampler(weights, seed=self.split_seed)

    def train_dataloader(self) -> DataLoader:
        return train_loader(self, self.train_set, self.batch_size, sampler=self._sampler(),
                            num_workers=self.num_workers, collate_fn=self.collate,
                            persistent_workers=self.num_workers > 0,
                            drop_last=len(self.train_set) >= self.batch_size)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.val_set, batch_size=self.batch_size, num_workers=self.num_workers,
                          collate_fn=self.collate, persistent_workers=self.num_workers > 0)


class FrameDataModule(ClipSourceDataModule):
    """Single frames for image tokenizers: batches {"image": (b·k·v, 3, H, W)}.

    frames_per_clip: k frames drawn from each clip per item (amortises decoding a clip).
    agent_boxes: also {"agent_box": (b·k·v, H, W) bool}, the clips' agent boxes in each image (for
        `model.weights.agents`); every clip needs agent boxes and camera specs.
    """

    def __init__(self, *args, frames_per_clip: int = 1, agent_boxes: bool = False, **kwargs):
        super().__init__(*args, **kwargs)
        self.frames_per_clip, self.agent_boxes = frames_per_clip, agent_boxes

    def wrap(self, source: ClipSource, train: bool) -> Dataset:
        return FramesDataset(source, self.height, self.width, self.frames_per_clip, self.resize_mode, self.agent_boxes)

    def collate(self, samples: list) -> Any:
        return collate_frames(samples)


class ClipDataModule(ClipSourceDataModule):
    """Video windows with every condition: batches from `collate_clips` ("video": (b, v, t, 3, H, W), …).

    clip_len: steps per window; fps: resampling rate by timestamps (GAIA-1 world model 6.25 Hz),
    None keeps the source rate; cameras: camera names to keep, in order (None keeps all).
    """

    def __init__(self, *args, clip_len: int = 8, fps: float | None = None, cameras: Sequence[str] | None = None,
                 **kwargs):
        super().__init__(*args, **kwargs)
        self.clip_len, self.fps, self.cameras = check_count(clip_len, "data.clip_len"), fps, cameras
        self.skipped_short = 0  # clips dropped at setup for being shorter than one window

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is None:  # clips too short for one window are skipped here, not at their first draw
            self.source = self.long_enough(self.source, "data.source")
            if self.val_source is not None:
                self.val_source = self.long_enough(self.val_source, "data.val_source")
        super().setup(stage)

    def long_enough(self, source: ClipSource, name: str) -> ClipSource:
        """`source` without the clips that have fewer than clip_len frames at `fps` (counted in a warning); sources
        that cannot tell a clip's length without reading it are kept whole."""
        steps_at = getattr(source, "steps_at", None)
        if steps_at is None:
            return source
        keep = [i for i in range(len(source)) if steps_at(i, self.fps) >= self.clip_len]
        if len(keep) == len(source):
            return source
        rate = f"{self.fps:g} Hz" if self.fps else "their own rate"
        if not keep:
            raise ClipError(f"{name}: none of its {len(source)} clips has data.clip_len={self.clip_len} frames at "
                            f"{rate}; lower data.clip_len or give longer clips")
        log.warning("%s: skipped %d of %d clips with fewer than data.clip_len=%d frames at %s", name,
                    len(source) - len(keep), len(source), self.clip_len, rate)
        self.skipped_short += len(source) - len(keep)
        return Subset(source, keep)

    def wrap(self, source: ClipSource, train: bool) -> Dataset:
        return ClipsDataset(source, self.height, self.width, self.clip_len, self.fps, self.cameras,
                            self.resize_mode, random_window=train)

    def collate(self, samples: list) -> Any:
        return collate_clips(samples)


class TokenCacheDataModule(L.LightningDataModule):
    """Windows of cached tokens for world models: batches {"tokens": (b, t, n), "actions"?: (b, t, 2),
    "text"?: b lists of t captions} (`collate_token_windows`).

    Args:
        path: a token `.npy` file or a folder of them (see token_cache.py).
        seq_len: steps per window (GAIA-1 T = 26). stride: steps between window starts.
        frame_stride: keep every k-th step (e.g. 4 for 25 → 6.25 Hz; 3 for commaVQ's 20 → 6.67 Hz).
        val_fraction: share of segments (or of the only segment's tail) held out.
        window_sampling, change_after: where training windows start ("uniform", or "action_change": ∝ how much the
            command changes after `change_after` steps; token_cache.TokenWindows). Validation windows stay uniform.
    """

    def __init__(self, path: str, seq_len: int = 16, stride: int = 1, frame_stride: int = 1, val_fraction: float = 0.1,
                 batch_size: int = 8, num_workers: int = 0, window_sampling: str = "uniform", change_after: int = 4):
        super().__init__()
        self.path, self.seq_len, self.stride, self.frame_stride = path, seq_len, stride, frame_stride
        self.window_sampling, self.change_after = window_sampling, change_after
        self.val_fraction = val_fraction
        self.batch_size = check_count(batch_size, "data.batch_size")
        self.num_workers = check_count(num_workers, "data.num_workers", minimum=0)
        self.train_set: TokenWindows | None = None

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        segments = [load_segment(p, self.frame_stride) for p in find_segments(self.path)]
        train, val = split_spans(segments, self.val_fraction, self.seq_len)
        self.vocab_size = int(max(s.tokens.max() for s in segments)) + 1
        self.train_set = TokenWindows(segments, train, self.seq_len, self.stride, self.window_sampling,
                                      self.change_after)
        self.val_set = TokenWindows(segments, val, self.seq_len, self.seq_len)

    def train_dataloader(self) -> DataLoader:
        return train_loader(self, self.train_set, self.batch_size, num_workers=self.num_workers,
                            drop_last=True, collate_fn=collate_token_windows)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.val_set, batch_size=self.batch_size, num_workers=self.num_workers,
                          collate_fn=collate_token_windows)
