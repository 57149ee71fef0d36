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
    assert state == {"epoch": 0, "items": 12, "length": 23, "seed": 5}
    resumed = loader()
    resumed.load_state_dict(json.loads(json.dumps(state)))  # what a checkpoint stores
    rest = list(resumed)
    assert items(taken) + items(rest) == full  # nothing repeated, nothing skipped, the same order
    assert resumed.state_dict()["epoch"] == 1 and resumed.state_dict()["items"] == 0  # that epoch is over
    resumed.order.set_epoch(1)
    second = items(resumed)
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
    loader.load_state_dict({"epoch": 2, "items": 6, "length": 15, "seed": 1})
    assert "starts afresh" in caplog.text and "15" in caplog.text
    assert len(items(loader)) == 12 and loader.order.epoch == 2


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
    """Trains one weight and records the items of every step."""

    def __init__(self):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(()))
        self.seen: list[int] = []

    def training_step(self, batch, batch_idx):
        self.seen.extend(int(i) for i in batch)
        return (self.weight - batch.float().mean()) ** 2

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.01)


def fit(root: Path, max_steps: int, resume: bool) -> list[int]:
    L.seed_everything(7)
    model = Recorder()
    checkpoints = L.pytorch.callbacks.ModelCheckpoint(dirpath=root, every_n_train_steps=1, save_last=True)
    trainer = L.Trainer(max_steps=max_steps, accelerator="cpu", logger=False, enable_progress_bar=False,
                        enable_model_summary=False, callbacks=[checkpoints], num_sanity_val_steps=0)
    trainer.fit(model, IndexData(n=10, batch_size=3), ckpt_path=str(root / "last.ckpt") if resume else None)
    return model.seen


def test_a_run_resumed_mid_epoch_trains_on_the_items_of_one_that_never_stopped(tmp_path: Path) -> None:
    whole = fit(tmp_path / "whole", max_steps=7, resume=False)  # 3 batches an epoch: epochs 0, 1 and one step of 2
    first = fit(tmp_path / "stopped", max_steps=4, resume=False)  # stops after one step of epoch 1
    rest = fit(tmp_path / "stopped", max_steps=7, resume=True)
    assert first + rest == whole
    assert len(whole) == 21 and sorted(whole[:9]) == sorted(set(whole[:9]))


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
