"""Train loaders of the folder datamodules resume mid-epoch (gaia_app/data/resumable.py): a run resumed from a
checkpoint taken inside an epoch trains on the very items, in the very order, of a run that never stopped."""

from __future__ import annotations

import json
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from torch.utils.data import Dataset

from gaia_app.data.datamodules import FrameDataModule, TokenCacheDataModule
from gaia_app.data.latent_windows import LatentCacheDataModule
from gaia_app.data.resumable import EpochShuffle, ResumableLoader, train_loader
from gaia_app.data.sampling import BalancedSampler
from gaia_app.lit.callbacks import FinalStepCheckpoint


class Indices(Dataset):
    def __init__(self, n: int):
        self.n = n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, index: int) -> int:
        return index


def items(batches) -> list[int]:
    return [int(i) for batch in batches for i in batch]


@pytest.mark.parametrize("workers", [0, 2])
def test_a_resumed_loader_goes_on_with_the_rest_of_its_epoch(workers: int) -> None:
    def loader() -> ResumableLoader:
        return ResumableLoader(Indices(23), EpochShuffle(23, seed=5), batch_size=4, drop_last=True,
                               num_workers=workers)

    full = items(loader())
    assert sorted(full) == sorted(set(full)) and len(full) == 20  # 5 batches of 4, the last 3 items dropped
    first = loader()
    taken = []
    for i, batch in enumerate(first):
        taken.append(batch)
        if i == 2:
            state = first.state_dict()
            break
    assert state == {"epoch": 0, "order": 0, "items": 12, "batch_size": 4, "length": 23, "seed": 5}
    resumed = loader()
    resumed.load_state_dict(json.loads(json.dumps(state)))  # what a checkpoint stores
    rest = list(resumed)
    assert items(taken) + items(rest) == full  # nothing repeated, nothing skipped, the same order
    assert resumed.state_dict()["epoch"] == 1 and resumed.state_dict()["items"] == 0  # that epoch is over
    second = items(resumed)  # outside a trainer a complete pass moves to the next epoch, as shuffle=True would
    assert len(second) == 20 and second != full  # the next epoch: whole, in a new order


def test_a_balanced_sampler_resumes_too() -> None:
    weights = np.linspace(0.2, 1.0, 30)

    def loader() -> ResumableLoader:
        return ResumableLoader(Indices(30), BalancedSampler(weights, seed=3), batch_size=5, drop_last=True)

    full = items(loader())
    first = loader()
    taken = [batch for _, batch in zip(range(2), first)]
    resumed = loader()
    resumed.load_state_dict(first.state_dict())
    assert items(taken) + items(resumed) == full


def test_a_state_from_another_split_starts_the_epoch_afresh_and_says_so(caplog) -> None:
    loader = ResumableLoader(Indices(12), EpochShuffle(12, seed=1), batch_size=3)
    loader.load_state_dict({"epoch": 2, "items": 6, "batch_size": 3, "length": 15, "seed": 1})
    assert "starts afresh" in caplog.text and "15" in caplog.text
    assert loader.order.epoch == 2 and len(items(loader)) == 12


def test_the_folder_datamodules_train_through_a_resumable_loader(tmp_path: Path) -> None:
    from tests.data.test_datamodules import ListSource, make_clip

    np.save(tmp_path / "a.npy", np.random.default_rng(0).integers(0, 50, (40, 6), dtype=np.int16))
    tokens = TokenCacheDataModule(str(tmp_path), seq_len=4, stride=2, val_fraction=0.25, batch_size=2)
    frames = FrameDataModule(ListSource([make_clip(i, t=2) for i in range(6)]), val_fraction=0.5, batch_size=2,
                             height=32, width=48)
    latents = LatentCacheDataModule(str(tmp_path / "latents"))
    latents.train_set = Indices(5)  # the loader's choice does not depend on what the windows hold
    for dm in (tokens, frames):
        dm.setup()
    for dm in (tokens, frames, latents):
        loader = dm.train_dataloader()
        assert isinstance(loader, ResumableLoader) and isinstance(loader.order.inner, EpochShuffle), type(dm)


class IndexData(L.LightningDataModule):
    def __init__(self, n: int, batch_size: int):
        super().__init__()
        self.n, self.batch_size = n, batch_size

    def train_dataloader(self):
        return train_loader(self, Indices(self.n), self.batch_size, drop_last=True)


class Recorder(L.LightningModule):
    """Trains one weight and records the items of every step; `crash_at` stops the run inside that step, as a
    kill or a preemption does."""

    def __init__(self, crash_at: int | None = None):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(()))
        self.seen: list[int] = []
        self.crash_at = crash_at

    def training_step(self, batch, batch_idx):
        if self.global_step == self.crash_at:
            raise KeyboardInterrupt
        self.seen.extend(int(i) for i in batch)
        return (self.weight - batch.float().mean()) ** 2

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.01)


def fit(root: Path, max_steps: int, resume: bool, batch_size: int = 3, crash_at: int | None = None, every: int = 1,
        **trainer_args) -> list[int]:
    L.seed_everything(7)
    model = Recorder(crash_at)
    # the project's checkpoint callback: last.ckpt also holds a final step off the `every` grid (written at train end)
    checkpoints = FinalStepCheckpoint(dirpath=root, every_n_train_steps=every, save_last=True)
    # written inside the interrupted step, over the last step's last.ckpt (and removed by a run that ends well)
    on_crash = [L.pytorch.callbacks.OnExceptionCheckpoint(root, "last")] if crash_at is not None else []
    trainer = L.Trainer(max_steps=max_steps, accelerator="cpu", logger=False, enable_progress_bar=False,
                        enable_model_summary=False, callbacks=[checkpoints, *on_crash], num_sanity_val_steps=0,
                        **trainer_args)
    try:
        trainer.fit(model, IndexData(n=10, batch_size=batch_size),
                    ckpt_path=str(root / "last.ckpt") if resume else None)
    except SystemExit:  # Lightning's answer to the interrupt, after OnExceptionCheckpoint wrote last.ckpt
        assert crash_at is not None
    return model.seen


@pytest.fixture(scope="module")
def whole(tmp_path_factory) -> list[int]:
    """A run that never stopped: 3 batches of 3 an epoch, epochs 0 and 1 and one step of epoch 2."""
    items = fit(tmp_path_factory.mktemp("whole"), max_steps=7, resume=False)
    assert len(items) == 21 and sorted(items[:9]) == sorted(set(items[:9]))
    return items


def test_a_run_resumed_mid_epoch_trains_on_the_items_of_one_that_never_stopped(whole, tmp_path: Path) -> None:
    first = fit(tmp_path, max_steps=4, resume=False)  # stops after one step of epoch 1
    assert first + fit(tmp_path, max_steps=7, resume=True) == whole


@pytest.mark.parametrize("stop", [3, 6])
def test_a_run_stopped_at_an_epochs_end_resumes_with_the_next_epochs_order(whole, tmp_path: Path, stop: int) -> None:
    first = fit(tmp_path, max_steps=stop, resume=False)
    assert first + fit(tmp_path, max_steps=7, resume=True) == whole


def test_an_epoch_cut_short_by_limit_train_batches_counts_as_over(tmp_path: Path) -> None:
    limited = {"limit_train_batches": 2}  # 2 of the 3 batches an epoch
    whole = fit(tmp_path / "whole", max_steps=5, resume=False, **limited)
    first = fit(tmp_path / "stopped", max_steps=2, resume=False, **limited)
    state = torch.load(tmp_path / "stopped" / "last.ckpt", weights_only=False)["loops"]["fit_loop"]["state_dict"]
    assert state["combined_loader"][0]["epoch"] == 1 and state["combined_loader"][0]["items"] == 0
    assert first + fit(tmp_path / "stopped", max_steps=5, resume=True, **limited) == whole


def test_a_run_that_stopped_off_its_checkpoint_grid_resumes_from_its_final_step(whole, tmp_path: Path) -> None:
    """max_steps 4 with checkpoints every 3 steps: last.ckpt is written at train end, after Lightning has closed the
    unfinished epoch 1; the resumed run serves the rest of epoch 1's order under Lightning's epoch 2."""
    first = fit(tmp_path, max_steps=4, resume=False, every=3)
    assert torch.load(tmp_path / "last.ckpt", weights_only=False)["global_step"] == 4
    second = fit(tmp_path, max_steps=5, resume=True, every=3)  # and once more off the grid, inside the carried epoch
    assert first + second + fit(tmp_path, max_steps=7, resume=True, every=3) == whole


def test_a_run_killed_inside_a_step_trains_that_steps_batch_again(whole, tmp_path: Path) -> None:
    first = fit(tmp_path, max_steps=7, resume=False, crash_at=4)  # killed inside step 5, the second of epoch 1
    assert torch.load(tmp_path / "last.ckpt", weights_only=False)["global_step"] == 4
    assert first + fit(tmp_path, max_steps=7, resume=True) == whole


def test_resuming_inside_an_epoch_with_another_batch_size_is_refused(tmp_path: Path) -> None:
    fit(tmp_path, max_steps=4, resume=False)
    with pytest.raises(ValueError, match="cut in batches of 3, with data.batch_size=2"):
        fit(tmp_path, max_steps=6, resume=True, batch_size=2)


def test_a_single_device_checkpoint_resumes_under_ddp_and_says_the_epoch_is_drawn_afresh(tmp_path: Path, caplog,
                                                                                         monkeypatch) -> None:
    for name in ("MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "LOCAL_RANK"):  # Lightning's DDP sets them
        monkeypatch.delenv(name, raising=False)
    fit(tmp_path, max_steps=4, resume=False)
    try:
        rest = fit(tmp_path, max_steps=6, resume=True, strategy="ddp", devices=1)  # Lightning rebuilds a plain loader
    finally:  # Lightning leaves its one-process group behind; later tests in this worker must not see it
        if torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()
    assert len(rest) == 6 and "drawn afresh" in caplog.text


def test_a_checkpoint_without_a_loader_state_resumed_mid_epoch_says_so(tmp_path: Path, caplog) -> None:
    fit(tmp_path, max_steps=4, resume=False)
    checkpoint = torch.load(tmp_path / "last.ckpt", weights_only=False)
    del checkpoint["loops"]["fit_loop"]["state_dict"]["combined_loader"]  # as written before the loaders kept one
    torch.save(checkpoint, tmp_path / "last.ckpt")
    fit(tmp_path, max_steps=6, resume=True)
    assert "resumed after 1 batches of epoch 1" in caplog.text


@pytest.mark.parametrize("strategy, overfit", [("ddp", 0), ("fsdp", 0), ("single", 2)])
def test_loaders_lightning_rebuilds_stay_plain_dataloaders(strategy: str, overfit: int) -> None:
    """Lightning re-creates the train loader under a parallel strategy (with a DistributedSampler, even on one
    process) and for overfit_batches (with a sequential sampler), reading the shuffle off a RandomSampler: those get
    the plain shuffling DataLoader."""
    from types import SimpleNamespace

    from lightning.pytorch.strategies import DDPStrategy, FSDPStrategy, SingleDeviceStrategy

    strategies = {"ddp": DDPStrategy, "fsdp": FSDPStrategy, "single": lambda: SingleDeviceStrategy("cpu")}
    module = SimpleNamespace(trainer=SimpleNamespace(strategy=strategies[strategy](), overfit_batches=overfit))
    loader = train_loader(module, Indices(8), 2)
    assert not isinstance(loader, ResumableLoader) and isinstance(loader.sampler, torch.utils.data.RandomSampler)
    alone = SimpleNamespace(trainer=SimpleNamespace(strategy=SingleDeviceStrategy("cpu"), overfit_batches=0))
    assert isinstance(train_loader(alone, Indices(8), 2), ResumableLoader)
