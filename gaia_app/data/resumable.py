"""Train loaders over map-style datasets that resume mid-epoch: a crashed or paused run (`ckpt_path=last`) goes on
with the rest of its epoch's order instead of drawing a new one, so no item is seen twice or skipped in that epoch.

Lightning saves a loader's `state_dict` in the checkpoint and hands it back through `load_state_dict` before the
first batch of a resumed run, for loaders that have both (lightning.fabric's `_Stateful`). The order of an epoch is a
function of (seed, epoch) (`EpochShuffle`, or a `BalancedSampler`), so the state is small: the epoch, the items the
training steps used, the seed and the split's size. What each item does with randomness of its own (a random window
inside a clip) is drawn again.

Lightning fetches no batch ahead from a loader with a length (its `_PrefetchDataFetcher`), so the batches handed out
are the batches the steps used, and a checkpoint taken after step k says k. Lightning rebuilds the loader under a
parallel strategy (to give it a DistributedSampler, even on one process) and for `trainer.overfit_batches`; those
keep a plain DataLoader (`train_loader`), and a multi-process run that must resume mid-epoch streams shards
(docs/data.md, "Sharded streaming").
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Iterator, Sized
from typing import Any

import torch
from lightning.pytorch.strategies import SingleDeviceStrategy
from torch.utils.data import DataLoader, Dataset, Sampler

log = logging.getLogger(__name__)


class EpochShuffle(Sampler[int]):
    """Indices 0..n-1 in an order drawn from (seed, epoch): the same epoch gives the same order in every process."""

    def __init__(self, n: int, seed: int):
        self.n, self.seed, self.epoch = n, seed, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return self.n

    def __iter__(self) -> Iterator[int]:
        generator = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
        return iter(torch.randperm(self.n, generator=generator).tolist())


class ResumableSampler(Sampler[int]):
    """`inner` (an order fixed by its epoch, through `set_epoch`) with the first `skip` items of one epoch left out:
    those a resumed run's steps had already used. Its length stays the whole epoch's, the number Lightning counts a
    resumed epoch's batches against."""

    def __init__(self, inner: Sampler[int]):
        self.inner, self.epoch = inner, 0
        self.resume = (-1, 0)  # (epoch, items to skip in it)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch
        if hasattr(self.inner, "set_epoch"):
            self.inner.set_epoch(epoch)

    def resume_at(self, epoch: int, skip: int) -> None:
        self.set_epoch(epoch)
        self.resume = (epoch, skip)

    def skipped(self) -> int:
        """Items left out of the current epoch (0 unless it is the resumed one)."""
        return self.resume[1] if self.resume[0] == self.epoch else 0

    def __len__(self) -> int:
        return len(self.inner)  # type: ignore[arg-type]

    def __iter__(self) -> Iterator[int]:
        return itertools.islice(iter(self.inner), self.skipped(), None)


class ResumableLoader(DataLoader):
    """A DataLoader over `dataset` in the order of `sampler`, whose state Lightning checkpoints and restores.

    State: {"epoch", "items" (handed out in that epoch), "seed" (of an EpochShuffle, else None), "length" (of the
    sampler's epoch)}. A state whose length differs from this loader's (another split) starts its epoch afresh with a
    warning that says so."""

    def __init__(self, dataset: Dataset, sampler: Sampler[int], batch_size: int, **kwargs: Any):
        self.order = ResumableSampler(sampler)
        super().__init__(dataset, batch_size=batch_size, sampler=self.order, **kwargs)
        self.handed = (0, 0)  # (epoch, batches handed out in it)

    def __iter__(self) -> Iterator[Any]:
        epoch = self.order.epoch
        self.handed = (epoch, self.order.skipped() // self.batch_size)
        for batch in super().__iter__():
            self.handed = (epoch, self.handed[1] + 1)
            yield batch

    def state_dict(self) -> dict[str, Any]:
        epoch, batches = self.handed
        if batches >= len(self.batch_sampler):  # type: ignore[arg-type]  # that epoch is over: the next starts afresh
            epoch, batches = epoch + 1, 0
        inner = self.order.inner
        return {"epoch": epoch, "items": batches * self.batch_size, "length": len(self.order),
                "seed": inner.seed if isinstance(inner, EpochShuffle) else None}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        epoch, items = int(state["epoch"]), int(state["items"])
        if int(state["length"]) != len(self.order):
            log.warning("resuming a train loader saved over %d items per epoch with %d now (another data split?): "
                        "epoch %d starts afresh, so items the run already used in it can come again",
                        state["length"], len(self.order), epoch)
            items = 0
        if isinstance(self.order.inner, EpochShuffle) and state.get("seed") is not None:
            self.order.inner.seed = int(state["seed"])
        self.order.resume_at(epoch, items)
        self.handed = (epoch, items // self.batch_size)


def train_loader(module: Any, dataset: Sized, batch_size: int, sampler: Sampler[int] | None = None,
                 **kwargs: Any) -> DataLoader:
    """The train loader of a datamodule `module`: a ResumableLoader in `sampler`'s order (default: EpochShuffle
    seeded from torch's initial seed, which `seed_everything` sets), or a plain shuffling DataLoader where Lightning
    would rebuild the loader (`lightning_rebuilds`)."""
    if lightning_rebuilds(getattr(module, "trainer", None)):
        return DataLoader(dataset, batch_size=batch_size, shuffle=sampler is None, sampler=sampler,  # type: ignore[arg-type]
                          **kwargs)
    order = sampler if sampler is not None else EpochShuffle(len(dataset), torch.initial_seed() % 2**31)
    return ResumableLoader(dataset, order, batch_size, **kwargs)  # type: ignore[arg-type]



def lightning_rebuilds(trainer: Any) -> bool:
    """Whether Lightning re-creates the train loader from its constructor's arguments: under any parallel strategy
    (DDP, FSDP, DeepSpeed: a DistributedSampler, even for one process) and for `overfit_batches` (a sequential
    sampler). A ResumableLoader rebuilt there would lose its shuffle (Lightning reads it off a RandomSampler)."""
    return trainer is not None and (not isinstance(trainer.strategy, SingleDeviceStrategy)
                                    or trainer.overfit_batches > 0)
