"""Streaming readers for WebDataset shards written by `python -m gaia_app.data.shard` (docs/data.md, "Sharded
streaming"): the stream and its loader. The DataModules of `data=video_folder_shards`, `data=token_cache_shards` and
`data=latent_cache_shards`, and the decoders that turn a sample into training items, are in
gaia_app/data/shard_datamodules.py.

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
import json
import logging
import shutil
import tempfile
import weakref
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from gaia_app.data.clip import ClipError
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
        if "taken" not in state:  # a folder loader's state (gaia_app/data/resumable.py): no place in this stream
            if state.get("items"):
                log.warning("resuming a sharded loader from a checkpoint of a folder loader taken inside epoch %s: "
                            "that epoch of the stream starts from its beginning", state.get("epoch"))
            self.epoch = int(state.get("epoch", 0))
            return
        if len(state["taken"]) != self.workers:
            raise ValueError(f"resuming a sharded loader saved with {len(state['taken'])} workers with "
                             f"data.num_workers={self.workers}: keep the worker count to resume mid-epoch")
        self.epoch, self.resume = int(state["epoch"]), list(state["taken"])
        self.used, self.handed = (self.epoch, list(self.resume)), collections.deque()
