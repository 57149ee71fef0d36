"""Train loaders over map-style datasets that resume mid-epoch: a crashed or paused run (`ckpt_path=last`) goes on
with the rest of its epoch's order instead of drawing a new one, so no item is seen twice or skipped in that epoch.

Lightning saves a loader's `state_dict` in the checkpoint and hands it back through `load_state_dict` before the
first batch of a resumed run, for loaders that have both (lightning.fabric's `_Stateful`). The order of an epoch is a
function of (seed, epoch) (`EpochShuffle`, or a `BalancedSampler`), so the state is small: the epoch, the items the
training steps finished, the batch size, the seed and the split's size. What each item does with randomness of its
own (a random window inside a clip) is drawn again.

"Finished" is Lightning's own count (the fit loop's processed batches): a checkpoint taken inside a step (on an
exception) leaves that step's batch to the resumed run, as Lightning's restart does. Where Lightning resumes an
epoch under the next epoch's number (a last.ckpt written at train end inside an epoch), the loader follows it and keeps
serving the orders 0, 1, 2, … (`ResumableLoader.line_up`). Lightning rebuilds the train
loader under a parallel strategy (with a DistributedSampler, even on one process) and for `trainer.overfit_batches`
(a sequential sampler); there `train_loader` gives a `PlainTrainLoader`, which shuffles as DataLoader does, cannot
resume mid-epoch and says so when a resumed run lands inside an epoch. A multi-process run that must resume
mid-epoch streams shards (docs/data.md, "Sharded streaming").
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
    resumed epoch's batches against.

    `offset`: Lightning's epoch number minus the epoch whose order it gets. It grows by one when Lightning resumes an
    epoch it had closed early under the next number (`ResumableLoader.line_up`), so the orders still run 0, 1, 2, …
    """

    def __init__(self, inner: Sampler[int]):
        self.inner, self.epoch, self.offset = inner, 0, 0
        self.resume = (-1, 0)  # (epoch, items to skip in it)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch
        if hasattr(self.inner, "set_epoch"):
            self.inner.set_epoch(epoch - self.offset)

    def resume_at(self, epoch: int, skip: int, offset: int = 0) -> None:
        self.resume, self.offset = (epoch, skip), offset
        self.set_epoch(epoch)

    def skipped(self) -> int:
        """Items left out of the current epoch (0 unless it is the resumed one)."""
        return self.resume[1] if self.resume[0] == self.epoch else 0

    def __len__(self) -> int:
        return len(self.inner)  # type: ignore[arg-type]

    def __iter__(self) -> Iterator[int]:
        return itertools.islice(iter(self.inner), self.skipped(), None)


def finished_batches(trainer: Any) -> int | None:
    """Batches of the current epoch whose training step finished, by the fit loop's count (None outside a fit)."""
    loop = getattr(trainer, "fit_loop", None)
    return None if loop is None else int(loop.epoch_loop.batch_progress.current.processed)


def warn_if_resumed_inside_an_epoch(trainer: Any, restored: bool) -> None:
    """Lightning warns of a mid-epoch resume only for loaders without a state; these loaders have one, so they say
    it themselves when they could not restore their place."""
    finished = finished_batches(trainer)
    if not restored and trainer is not None and trainer.global_step > 0 and finished:
        log.warning("resumed after %d batches of epoch %d from a checkpoint without this loader's place in it "
                    "(written before the loaders were resumable, under a parallel strategy or with overfit_batches): "
                    "the rest of the epoch is drawn afresh, so some items can come twice and others not at all",
                    finished, trainer.current_epoch)


class ResumableLoader(DataLoader):
    """A DataLoader over `dataset` in the order of `sampler`, whose state Lightning checkpoints and restores.

    trainer: the trainer whose fit loop counts the finished batches (None: every batch handed out counts, and each
    complete pass moves to the next epoch, as a shuffling DataLoader gives a new order per pass).
    State: {"epoch" (Lightning's number), "order" (the epoch whose order it serves), "items" (finished in that
    epoch), "batch_size", "length" (of an epoch), "seed" (of an EpochShuffle, else None)}. A state from a split of
    another size starts its epoch afresh with a warning; one cut in batches of another size is refused (Lightning
    would count the resumed epoch's batches wrongly)."""

    def __init__(self, dataset: Dataset, sampler: Sampler[int], batch_size: int, trainer: Any = None,
                 **kwargs: Any):
        self.order = ResumableSampler(sampler)
        super().__init__(dataset, batch_size=batch_size, sampler=self.order, **kwargs)
        self.trainer, self.restored, self.checked = trainer, False, False
        self.handed = (0, 0)  # (epoch, batches handed out in it)

    def __iter__(self) -> Iterator[Any]:
        if not self.checked:
            self.checked = True
            self.line_up()
        epoch = self.order.epoch
        self.handed = (epoch, self.order.skipped() // self.batch_size)
        for batch in super().__iter__():
            self.handed = (epoch, self.handed[1] + 1)
            yield batch
        if self.trainer is None:
            self.order.set_epoch(epoch + 1)

    def line_up(self) -> None:
        """On the first pass under a trainer (after Lightning has set the epoch and restored its batch count), line
        the restored place up with where Lightning resumes, or warn that the epoch is drawn afresh."""
        trainer = self.trainer
        if trainer is None or not self.restored:
            warn_if_resumed_inside_an_epoch(trainer, self.restored)
            return
        (saved, items), offset = self.order.resume, self.order.offset
        finished, now = finished_batches(trainer), self.order.epoch
        if finished == items // self.batch_size and now == saved:
            return
        if finished == items // self.batch_size and now == saved + 1:
            # Lightning resumes this epoch under the next number: a last.ckpt written when the run stopped inside an
            # epoch (FinalStepCheckpoint at max_steps or max_time), or one written at an epoch's end in a max_steps
            # run (Lightning's epoch count runs one ahead there); the orders stay 0, 1, 2, … all the same
            self.order.resume_at(now, items, offset + 1)
            return
        if items or finished:
            log.warning("the checkpoint's train loader stopped after %d items of epoch %d, but Lightning resumes after "
                        "%s batches of epoch %d: the rest of that epoch is drawn afresh, so some items can come twice "
                        "and others not at all", items, saved, finished, now)
        self.order.resume = (-1, 0)
        self.order.set_epoch(now)

    def batches_per_epoch(self) -> int:
        """The batches of a whole epoch, or as many as the trainer takes of it (`limit_train_batches`)."""
        whole = len(self.batch_sampler)  # type: ignore[arg-type]
        taken = getattr(self.trainer, "num_training_batches", whole)
        return whole if not isinstance(taken, int) else min(whole, taken)

    def state_dict(self) -> dict[str, Any]:
        epoch, batches = self.handed
        finished = finished_batches(self.trainer)
        batches = batches if finished is None else finished
        if batches >= self.batches_per_epoch():  # that epoch is over: the next starts afresh
            epoch, batches = epoch + 1, 0
        inner = self.order.inner
        return {"epoch": epoch, "order": epoch - self.order.offset, "items": batches * self.batch_size,
                "batch_size": self.batch_size, "length": len(self.order),
                "seed": inner.seed if isinstance(inner, EpochShuffle) else None}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if "items" not in state:  # saved by a PlainTrainLoader: it kept no place
            return
        epoch, items = int(state["epoch"]), int(state["items"])
        if items and int(state["batch_size"]) != self.batch_size:
            raise ValueError(f"resuming inside epoch {epoch}, cut in batches of {state['batch_size']}, with "
                             f"data.batch_size={self.batch_size}: keep data.batch_size={state['batch_size']} until "
                             "that epoch ends, or resume from a checkpoint taken at an epoch's end")
        if int(state["length"]) != len(self.order):
            log.warning("resuming a train loader saved over %d items per epoch with %d now (another data split?): "
                        "epoch %d starts afresh, so items the run already used in it can come again",
                        state["length"], len(self.order), epoch)
            items = 0
        else:
            self.restored = True
        if isinstance(self.order.inner, EpochShuffle) and state.get("seed") is not None:
            self.order.inner.seed = int(state["seed"])
        self.order.resume_at(epoch, items, epoch - int(state.get("order", epoch)))
        self.handed = (epoch, items // self.batch_size)


class PlainTrainLoader(DataLoader):
    """A shuffling DataLoader for where Lightning rebuilds the train loader with a sampler of its own: it keeps no
    place in an epoch, accepts a ResumableLoader's state (a single-device run resumed under DDP) and warns when a
    resumed run lands inside an epoch. `trainer` is a constructor argument so that Lightning's rebuild keeps it."""

    def __init__(self, dataset: Dataset, trainer: Any = None, **kwargs: Any):
        super().__init__(dataset, **kwargs)
        self.trainer, self.checked = trainer, False

    def __iter__(self) -> Iterator[Any]:
        if not self.checked:
            self.checked = True
            warn_if_resumed_inside_an_epoch(self.trainer, restored=False)
        yield from super().__iter__()

    def state_dict(self) -> dict[str, Any]:
        return {"resumable": False}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        return None


def train_loader(module: Any, dataset: Sized, batch_size: int, sampler: Sampler[int] | None = None,
                 **kwargs: Any) -> DataLoader:
    """The train loader of a datamodule `module`: a ResumableLoader in `sampler`'s order (default: EpochShuffle
    seeded from torch's initial seed, which `seed_everything` sets), or a PlainTrainLoader where Lightning rebuilds
    the loader (`lightning_rebuilds`)."""
    trainer = getattr(module, "trainer", None)
    if lightning_rebuilds(trainer):
        return PlainTrainLoader(dataset, trainer=trainer, batch_size=batch_size,  # type: ignore[arg-type]
                                shuffle=sampler is None, sampler=sampler, **kwargs)
    order = sampler if sampler is not None else EpochShuffle(len(dataset), torch.initial_seed() % 2**31)
    return ResumableLoader(dataset, order, batch_size, trainer=trainer, **kwargs)  # type: ignore[arg-type]


def lightning_rebuilds(trainer: Any) -> bool:
    """Whether Lightning re-creates the train loader from its constructor's arguments: under any parallel strategy
    (DDP, FSDP, DeepSpeed: a DistributedSampler, even for one process) and for `overfit_batches` (a sequential
    sampler). It cannot re-create a ResumableLoader (its sampler argument is wrapped) and would refuse to."""
    return trainer is not None and (not isinstance(trainer.strategy, SingleDeviceStrategy)
                                    or trainer.overfit_batches > 0)
