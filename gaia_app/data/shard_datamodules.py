"""The shard DataModules (`data=video_folder_shards`, `data=token_cache_shards`, `data=latent_cache_shards`): which
decoder turns a shard sample into training items, and balanced acceptance from the split's feature table. The stream
itself (shard order, workers, resuming) is gaia_app/data/shards.py.
"""

from __future__ import annotations

import io
import json
import logging
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch

from gaia_app.data.clip import ClipError
from gaia_app.data.sampling import balancing_weights
from gaia_app.data.shard_format import INDEX
from gaia_app.data.shards import ShardLoader, ShardStream, Unpacked, shard_urls

log = logging.getLogger(__name__)


def acceptance(folder: str | None, split: str, balance: dict[str, Any] | None) -> np.ndarray | None:
    """Per-row acceptance weights of the split from its feature table (GAIA-1 §3), or None without balancing.
    folder: a local folder with the shards' shards.json and features-<split>.npz."""
    if not balance:
        return None
    if folder is None:
        raise ValueError("data.balance on remote shards needs their shards.json and features-<split>.npz locally: "
                         "set data.index_dir to a folder holding them")
    index = json.loads((Path(folder) / INDEX).read_text())
    table = np.load(Path(folder) / index["splits"][split]["features"])
    features = dict(balance["features"])
    missing = sorted(set(features) - set(table.files))
    if missing:
        raise ValueError(f"data.balance.features {missing}: not in the shards' feature table "
                         f"(has {sorted(table.files)})")
    return balancing_weights({name: table[name] for name in features}, features, balance["exponent"])


class ShardDataModule(L.LightningDataModule, ABC):
    """Common part of the shard DataModules.

    Args:
        path: the shard folder (or URL pattern(s) joined by `::`, train and val as `<pattern>` with {split} in it).
        batch_size, num_workers: loader settings. shuffle_buffer: items mixed per worker.
        balance: None or {"features": {name: bins}, "exponent": float}. seed: shard order, buffers and acceptance.
        epoch_batches: batches per epoch and rank (None: the whole stream).
        index_dir: a local folder with shards.json and the feature tables, for balancing remote shards (a local
            shard folder is its own).
        skip_bad_samples: count, log and skip samples that cannot be read (default: stop, naming shard and sample).
        allow_pipe: accept `pipe:` URLs in `path` (they run a shell command per shard; docs/safety.md).
    """

    def __init__(self, path: str, batch_size: int = 8, num_workers: int = 0, shuffle_buffer: int = 256,
                 balance: dict[str, Any] | None = None, seed: int = 0, epoch_batches: int | None = None,
                 index_dir: str | None = None, skip_bad_samples: bool = False, allow_pipe: bool = False):
        super().__init__()
        self.index_dir, self.skip_bad_samples, self.allow_pipe = index_dir, bool(skip_bad_samples), bool(allow_pipe)
        self.path, self.batch_size, self.num_workers = str(path), batch_size, num_workers
        self.shuffle_buffer, self.balance, self.seed, self.epoch_batches = shuffle_buffer, balance, seed, epoch_batches
        self.loaders: dict[str, ShardLoader] = {}

    @abstractmethod
    def decoder(self, train: bool) -> Callable[[str, dict[str, bytes]], list[Any]]:
        """A picklable (key, the sample's files {name: bytes}) → its training items (validation: `train` False)."""

    @abstractmethod
    def collate(self) -> Callable[[list], Any]:
        """A picklable function batching a list of items."""

    def urls(self, split: str) -> tuple[list[str], dict[str, Any] | None]:
        return shard_urls(self.path.replace("{split}", split), split, self.allow_pipe)

    def loader(self, split: str) -> ShardLoader:
        if split not in self.loaders:
            urls, index = self.urls(split)
            train = split == "train"
            weights = (acceptance(self.index_dir or (self.path if index else None), split, self.balance) if train
                       else None)
            stream = ShardStream(urls, self.decoder(train), self.collate(), self.batch_size, shuffle=train,
                                 shuffle_buffer=self.shuffle_buffer, weights=weights, seed=self.seed,
                                 skip_bad=self.skip_bad_samples)
            self.loaders[split] = ShardLoader(stream, self.num_workers, self.epoch_batches if train else None,
                                              self.finish())
        return self.loaders[split]

    def finish(self) -> Callable[[Any], Any] | None:
        """What the main process does to each batch from the workers (None: nothing)."""
        return None

    def on_before_batch_transfer(self, batch: Any, dataloader_idx: int) -> Any:
        """Called once per batch a step uses (after Lightning's one-batch prefetch): count it for the resume state."""
        trainer = getattr(self, "trainer", None)
        if trainer is not None and trainer.training and "train" in self.loaders:
            self.loaders["train"].mark_used()
        return batch

    def train_dataloader(self) -> ShardLoader:
        return self.loader("train")

    def val_dataloader(self) -> ShardLoader:
        return self.loader("val")




@dataclass
class TokenDecoder:
    """A token segment → a reference (segment, start) per window of `seq_len` steps at `stride`; none when shorter.
    `collate_token_refs` cuts the windows of a batch at once."""

    seq_len: int
    stride: int
    frame_stride: int

    def __call__(self, key: str, files: dict[str, bytes]) -> list[Any]:
        from gaia_app.data.token_cache import read_segment

        sidecars = {name.removeprefix("tokens"): io.BytesIO(data)
                    for name, data in files.items() if name != "tokens.npy"}
        # tokens stay in their stored type (int16 for codebooks that fit) until the main process (`widen_tokens`):
        # a quarter of the bytes through the worker queues
        segment = read_segment(key, io.BytesIO(files["tokens.npy"]), sidecars, self.frame_stride,
                               f"shard sample {key}.npy", stored_dtype=True)
        starts = range(0, len(segment.tokens) - self.seq_len + 1, self.stride)
        return [(segment, start, self.seq_len) for start in starts]


def collate_token_refs(refs: list[tuple[Any, int, int]]) -> dict[str, Any]:
    """Window references (segment, start, length) → the batch `collate_token_windows` makes of the same windows
    (TokenWindows items), cut with one numpy stack per field instead of a tensor per window."""
    from gaia_app.data.token_cache import TokenSegment

    segments: list[TokenSegment] = [segment for segment, _, _ in refs]
    cut = lambda name: [getattr(seg, name)[start : start + n] for seg, start, n in refs]  # noqa: E731
    batch: dict[str, Any] = {"tokens": torch.from_numpy(np.stack(cut("tokens")))}
    for name in ("actions", "text", "timestamps"):
        have = [getattr(seg, name) is not None for seg in segments]
        if not any(have):
            continue
        if not all(have):
            raise ClipError(f"token batch mixes windows with and without '{name}' ({sum(have)} of {len(refs)} have it)")
        if name == "text":
            batch["text"] = [list(window) for window in cut("text")]
        elif name == "actions":
            batch["actions"] = torch.from_numpy(np.stack(cut("actions")))
        else:
            times = np.stack(cut("timestamps"))
            batch["timestamps"] = torch.from_numpy(times - times[:, :1]).float()
    return dict(sorted(batch.items()))


class TokenShardDataModule(ShardDataModule):
    """`data=token_cache_shards`: token windows as TokenCacheDataModule's (gaia_app/data/token_cache.py), every window
    of each segment (stride `stride` in training, `seq_len` in validation); segments shorter than a window give none.
    """

    def __init__(self, path: str, seq_len: int = 16, stride: int = 1, frame_stride: int = 1, **kwargs: Any):
        super().__init__(path, **kwargs)
        self.seq_len, self.stride, self.frame_stride = seq_len, stride, frame_stride

    def decoder(self, train: bool) -> TokenDecoder:
        return TokenDecoder(self.seq_len, self.stride if train else self.seq_len, self.frame_stride)

    def collate(self) -> Callable[[list], Any]:
        return collate_token_refs

    def finish(self) -> Callable[[Any], Any]:
        return widen_tokens


def widen_tokens(batch: dict[str, Any]) -> dict[str, Any]:
    """Token ids as int64 (the batch contract), in the main process after the compact trip through the queues."""
    batch["tokens"] = batch["tokens"].long()
    return batch


@dataclass
class LatentDecoder:
    """A latent clip → one window of `steps` latent steps (LatentCacheDataModule's item)."""

    steps: int
    metadata_fields: list[str]
    random_window: bool
    unpacked: Unpacked = field(default_factory=Unpacked)

    def __call__(self, key: str, files: dict[str, bytes]) -> list[Any]:
        from gaia_app.data.latent_cache import read_latent_clip
        from gaia_app.data.latent_windows import random_latent_window
        from gaia_app.data.metadata import MetadataEncoder

        clip = read_latent_clip(self.unpacked(files))
        clip.clip_id = key
        return [random_latent_window(clip, self.steps, MetadataEncoder(self.metadata_fields), self.random_window)]


class LatentShardDataModule(ShardDataModule):
    """`data=latent_cache_shards`: latent windows as LatentCacheDataModule's (gaia_app/data/latent_windows.py), one
    per clip and epoch (a random start in training, the first steps in validation)."""

    def __init__(self, path: str, steps: int = 4, metadata_fields: Sequence[str] = (), **kwargs: Any):
        super().__init__(path, **kwargs)
        self.steps, self.metadata_fields = steps, list(metadata_fields)

    def decoder(self, train: bool) -> LatentDecoder:
        return LatentDecoder(self.steps, self.metadata_fields, train)

    def collate(self) -> Callable[[list], Any]:
        from gaia_app.data.latent_windows import collate_latent_windows

        return collate_latent_windows


@dataclass
class ClipDecoder:
    """A clip folder → one window of `clip_len` steps at `fps` (ClipDataModule's item); none when too short (logged)."""

    clip_len: int
    fps: float | None
    cameras: list[str] | None
    height: int
    width: int
    resize_mode: str
    random_window: bool
    unpacked: Unpacked = field(default_factory=Unpacked)

    def __call__(self, key: str, files: dict[str, bytes]) -> list[Any]:
        from gaia_app.data.clip_folder import read_clip
        from gaia_app.data.datasets import ClipsDataset

        clip = read_clip(self.unpacked(files), self.cameras)
        clip.clip_id = key
        windows = ClipsDataset([clip], self.height, self.width, self.clip_len, self.fps, self.cameras,
                               self.resize_mode, random_window=self.random_window)
        try:
            return [windows[0]]
        except ClipError as error:  # too short for one window
            log.warning("shards: %s", error)
            return []


class ClipShardDataModule(ShardDataModule):
    """`data=video_folder_shards`: video windows as ClipDataModule's (gaia_app/data/datasets.ClipsDataset), one per
    clip and epoch. A clip with fewer than clip_len frames at `fps` gives none and is logged."""

    def __init__(self, path: str, clip_len: int = 8, fps: float | None = None, cameras: Sequence[str] | None = None,
                 height: int = 64, width: int = 112, resize_mode: str = "crop", **kwargs: Any):
        super().__init__(path, **kwargs)
        self.clip_len, self.fps, self.cameras = clip_len, fps, None if cameras is None else list(cameras)
        self.height, self.width, self.resize_mode = height, width, resize_mode

    def decoder(self, train: bool) -> ClipDecoder:
        return ClipDecoder(self.clip_len, self.fps, self.cameras, self.height, self.width, self.resize_mode, train)

    def collate(self) -> Callable[[list], Any]:
        from gaia_app.data.collate import collate_clips

        return collate_clips
