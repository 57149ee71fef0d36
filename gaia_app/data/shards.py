"""Streaming readers for WebDataset shards written by `python -m gaia_app.data.shard` (docs/data.md, "Sharded
streaming"): `data=video_folder_shards`, `data=token_cache_shards`, `data=latent_cache_shards`.

Shards come from a local folder (its shards.json), `http(s)://` URLs or `pipe:` commands (e.g.
`pipe:aws s3 cp s3://bucket/train-000000.tar -`), opened by WebDataset (`webdataset.tarfile_to_samples`).

Epoch semantics (tested in tests/data/test_shards.py and tests/test_shards_ddp.py):
- Each epoch the shard list is shuffled with (seed, epoch), then split by rank (`shards[rank::world]`) and by loader
  worker (`[worker::workers]`): every shard, so every sample, is read exactly once per epoch across ranks and
  workers. Ranks may get different numbers of samples (up to one shard's worth); under DDP set `epoch_batches` so
  every rank stops after the same number of batches (what is left of that epoch is not seen).
- Inside a worker: samples are decoded by the folder readers' own code, filtered by balanced acceptance (a sample is
  kept with probability weight / max weight, the weights of gaia_app/data/sampling.py computed from the split's
  feature table; GAIA-1 §3), cut into training items and mixed by a shuffle buffer of `shuffle_buffer` items, all
  with generators seeded by (seed, epoch, rank, worker); batches are formed in the worker.
- Resuming: the loader's state (epoch and batches taken from each worker) is saved in Lightning checkpoints; a resumed
  run replays that epoch's stream and skips the batches already taken, so nothing is repeated or skipped (on rank 0
  exactly; another rank whose workers ended at other points is off by at most one shard).
"""

from __future__ import annotations

import collections
import io
import json
import logging
import shutil
import tempfile
import weakref
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from gaia_app.data.clip import ClipError
from gaia_app.data.sampling import balancing_weights
from gaia_app.data.shard_format import INDEX, decode_name

log = logging.getLogger(__name__)
REMOTE = ("http://", "https://", "pipe:", "s3://", "gs://")


def shard_urls(location: str, split: str, allow_pipe: bool = False) -> tuple[list[str], dict[str, Any] | None]:
    """The shards of `split` and the index that lists them: a local folder (its shards.json) or a brace pattern /
    list of URLs (e.g. `pipe:curl -s https://host/train-{000000..000031}.tar`), whose index is read from beside them
    when it is local and absent otherwise. A `pipe:` URL runs its text as a shell command, so it is refused unless
    `allow_pipe` (data.allow_pipe=true; docs/safety.md)."""
    from braceexpand import braceexpand

    if "pipe:" in location and not allow_pipe:
        raise ValueError(f"data.path={location[:120]!r}: a 'pipe:' URL runs its text as a shell command for every "
                         "shard; set data.allow_pipe=true if you wrote it yourself (docs/safety.md)")
    path = Path(location)
    if not location.startswith(REMOTE) and path.is_dir():
        index_path = path / INDEX
        if not index_path.is_file():
            raise FileNotFoundError(f"{path}: no {INDEX} (write shards with python -m gaia_app.data.shard)")
        index = json.loads(index_path.read_text())
        if split not in index["splits"]:
            raise ClipError(f"{index_path}: no '{split}' split (has {sorted(index['splits'])})")
        return [str(path / s["name"]) for s in index["splits"][split]["shards"]], index
    urls = [u for part in location.split("::") for u in braceexpand(part)]
    missing = [u for u in urls if not u.startswith(REMOTE) and not Path(u).is_file()]
    if missing:
        raise FileNotFoundError(f"data.{split}_shards: {missing[:3]} not found")
    return urls, None


def split_shards(urls: Sequence[str], epoch: int, seed: int, shuffle: bool, rank: int, world: int, worker: int,
                 workers: int) -> list[str]:
    """This rank's and worker's shards of the epoch (module docstring)."""
    order = np.random.default_rng([seed, epoch]).permutation(len(urls)) if shuffle else np.arange(len(urls))
    return [urls[i] for i in order[rank::world][worker::workers]]


def sample_files(sample: dict[str, Any]) -> tuple[str, dict[str, bytes], dict[str, Any]]:
    """A WebDataset sample → its key, its files {original relative name: bytes} and its features."""
    files = {decode_name(name): value for name, value in sample.items() if not name.startswith("__")}
    features = json.loads(files.pop("features.json", b"{}"))
    return decode_name(sample["__key__"]), files, features


class Unpacked:
    """A scratch folder holding one sample's files at a time, for readers that take a folder (clip folders, latent
    clips); in memory under /dev/shm when the machine has it. Created per process on first use."""

    def __init__(self) -> None:
        self.folder: Path | None = None

    def __call__(self, files: dict[str, bytes]) -> Path:
        if self.folder is None:
            shm = Path("/dev/shm")
            self.folder = Path(tempfile.mkdtemp(prefix="gaia-shard-", dir=shm if shm.is_dir() else None))
            weakref.finalize(self, shutil.rmtree, self.folder, True)
        for child in self.folder.iterdir():
            shutil.rmtree(child) if child.is_dir() else child.unlink()
        for name, data in files.items():
            target = self.folder / name
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
        return self.folder

    def __getstate__(self) -> dict[str, Any]:  # each worker process makes its own folder
        return {"folder": None}


class ShardStream(IterableDataset):
    """Batches from shards (module docstring).

    Args:
        urls: the split's shards. decode: (key, files {name: bytes}) → training items (a list, possibly empty).
        collate: list of items → batch. batch_size: items per batch (the last of a worker may be smaller).
        shuffle: shuffle shards and items (training). shuffle_buffer: items in the shuffle buffer.
        weights: per-row acceptance weights (balanced sampling) or None. seed: base seed.
        skip_bad: a sample that cannot be read is logged (shard, index in the shard, key, error), counted and
            skipped; otherwise (default) it stops the run with that message.
    """

    def __init__(self, urls: Sequence[str], decode: Callable[[str, dict[str, bytes]], list[Any]],
                 collate: Callable[[list], Any], batch_size: int, shuffle: bool = True, shuffle_buffer: int = 256,
                 weights: np.ndarray | None = None, seed: int = 0, skip_bad: bool = False):
        self.urls, self.decode, self.collate = list(urls), decode, collate
        self.batch_size, self.shuffle, self.shuffle_buffer = batch_size, shuffle, shuffle_buffer
        self.weights, self.seed, self.skip_bad = weights, seed, skip_bad
        self.epoch, self.rank, self.world = 0, 0, 1
        self.skip: list[int] = []  # batches to skip per worker (resuming)

    def items(self, worker: int, workers: int) -> Iterator[Any]:
        """This worker's decoded, accepted training items, in stream order."""
        import webdataset as wds

        rng = np.random.default_rng([self.seed, self.epoch, self.rank, worker, 1])
        mine = split_shards(self.urls, self.epoch, self.seed, self.shuffle, self.rank, self.world, worker, workers)
        if not mine:
            log.warning("shards: rank %d worker %d has none of the %d shards (%d ranks × %d workers read them): write "
                        "smaller shards (--shard-size) or use fewer workers", self.rank, worker, len(self.urls),
                        self.world, workers)
        position: collections.Counter[str] = collections.Counter()  # samples seen per shard
        skipped = 0
        for sample in wds.tarfile_to_samples()(iter([{"url": u} for u in mine])):
            url = str(sample.get("__url__", "?"))
            position[url] += 1
            try:
                key, files, features = sample_files(sample)
                accepted = self.weights is None or rng.random() < self.weights[int(features["row"])]
                items = self.decode(key, files) if accepted else []
            except Exception as error:  # noqa: BLE001 (any reader error of one sample: named, then raised or skipped)
                where = f"{url}: sample {position[url] - 1} ('{decode_name(str(sample.get('__key__')))}')"
                if not self.skip_bad:
                    raise ClipError(f"{where} cannot be read ({type(error).__name__}: {error}); set "
                                    "data.skip_bad_samples=true to count and skip such samples") from error
                skipped += 1
                log.warning("shards: skipped %s (%s: %s); %d skipped so far by this worker", where,
                            type(error).__name__, error, skipped)
                continue
            yield from items

    def shuffled(self, items: Iterator[Any], worker: int) -> Iterator[Any]:
        """Items mixed by a buffer of `shuffle_buffer` (each new item swaps with a random buffered one)."""
        if not self.shuffle or self.shuffle_buffer <= 1:
            yield from items
            return
        rng = np.random.default_rng([self.seed, self.epoch, self.rank, worker, 2])
        buffer: list[Any] = []
        size = self.shuffle_buffer
        picks = iter(())  # uniform positions in the full buffer, drawn a thousand at a time
        for item in items:
            if len(buffer) < size:
                buffer.append(item)
                continue
            j = next(picks, None)
            if j is None:
                picks = iter(rng.integers(size, size=1000).tolist())
                j = next(picks)
            yield buffer[j]
            buffer[j] = item
        rng.shuffle(buffer)
        yield from buffer

    def __iter__(self) -> Iterator[tuple[int, Any]]:
        info = get_worker_info()
        worker, workers = (info.id, info.num_workers) if info else (0, 1)
        torch.manual_seed(int(np.random.default_rng([self.seed, self.epoch, self.rank, worker, 3]).integers(2**62)))
        skip = self.skip[worker] if worker < len(self.skip) else 0
        batch: list[Any] = []
        taken = 0
        for item in self.shuffled(self.items(worker, workers), worker):
            batch.append(item)
            if len(batch) == self.batch_size:
                taken += 1
                if taken > skip:
                    yield worker, self.collate(batch)
                batch = []
        if batch and taken >= skip:
            yield worker, self.collate(batch)


def as_batched(item: tuple[int, Any]) -> tuple[int, Any]:
    """The workers batch already: no default_convert pass over every batch."""
    return item


class ShardLoader(DataLoader):
    """A DataLoader over a ShardStream whose state (epoch, batches taken per worker) Lightning saves in checkpoints
    and restores on resume; `epoch_batches` caps the batches of an epoch (equal lengths across DDP ranks).

    Lightning fetches one batch ahead of the step that uses it, so under a trainer the state counts the batches
    the training loop used (`mark_used`, called by ShardDataModule.on_before_batch_transfer), not those fetched: a
    fetched batch that no step used is handed out again after a resume. Outside a trainer every batch handed out
    counts.
    """

    def __init__(self, stream: ShardStream, num_workers: int = 0, epoch_batches: int | None = None,
                 finish: Callable[[Any], Any] | None = None):
        super().__init__(stream, batch_size=None, num_workers=num_workers, persistent_workers=False,
                         collate_fn=as_batched)
        self.stream, self.epoch_batches, self.finish = stream, epoch_batches, finish
        self.workers = max(1, num_workers)
        self.epoch, self.resume = 0, None
        self.handed: collections.deque[tuple[int, int]] = collections.deque()  # (epoch, worker) not yet used
        self.sizes: dict[int, int] = {}  # batches in each finished epoch
        self.tracking, self.used = False, (0, [0] * self.workers)  # the consumer's (epoch, taken per worker)
        self.produced = (0, [0] * self.workers)  # the producer's

    def __iter__(self) -> Iterator[Any]:
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            self.stream.rank, self.stream.world = torch.distributed.get_rank(), torch.distributed.get_world_size()
        epoch, start = self.epoch, list(self.resume) if self.resume else [0] * self.workers
        self.stream.epoch, self.stream.skip, self.resume = epoch, list(start), None
        self.produced = (epoch, list(start))
        if self.used[0] < epoch or not self.handed:
            self.used = (epoch, list(start))
        for worker, batch in super().__iter__():
            if self.epoch_batches is not None and sum(self.produced[1]) >= self.epoch_batches:
                break
            self.produced[1][worker] += 1
            self.handed.append((epoch, worker))
            yield batch if self.finish is None else self.finish(batch)
        self.sizes[epoch] = sum(self.produced[1])
        self.epoch = epoch + 1

    def mark_used(self) -> None:
        """The training loop used the oldest batch handed out."""
        self.tracking = True
        if not self.handed:
            return
        epoch, worker = self.handed.popleft()
        if epoch != self.used[0]:
            self.used = (epoch, [0] * self.workers)
        self.used[1][worker] += 1

    def state_dict(self) -> dict[str, Any]:
        epoch, taken = self.used if self.tracking else self.produced
        if self.sizes.get(epoch) == sum(taken):  # that epoch is over and fully used: the next one starts afresh
            return {"epoch": epoch + 1, "taken": [0] * self.workers}
        return {"epoch": epoch, "taken": list(taken)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if len(state["taken"]) != self.workers:
            raise ValueError(f"resuming a sharded loader saved with {len(state['taken'])} workers with "
                             f"data.num_workers={self.workers}: keep the worker count to resume mid-epoch")
        self.epoch, self.resume = int(state["epoch"]), list(state["taken"])
        self.used, self.handed = (self.epoch, list(self.resume)), collections.deque()


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
