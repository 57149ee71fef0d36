"""Sharded streaming under DDP (issue: data at cluster scale): 2 gloo processes × 2 loader workers read every sample
of an epoch exactly once, and train.py trains and resumes from shards on 2 ranks with the loader state checkpointed."""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from gaia_app.data.shard import write_shards
from gaia_app.data.shard_datamodules import TokenShardDataModule
from tests.data.test_shards import SEQ, STRIDE, token_cache, window_ids
from tests.test_distributed import run_train, world_model_args

pytestmark = pytest.mark.slow  # two processes each: `make test-slow`


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def read_epoch(rank: int, world: int, port: int, shards: str, out: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    torch.set_num_threads(1)
    dist.init_process_group("gloo", rank=rank, world_size=world)
    module = TokenShardDataModule(shards, seq_len=SEQ, stride=STRIDE, batch_size=3, num_workers=2, shuffle_buffer=8)
    mine = window_ids(module.train_dataloader())
    gathered: list = [None] * world
    dist.all_gather_object(gathered, mine)
    if rank == 0:
        Path(out).write_text(json.dumps(gathered))
    dist.destroy_process_group()


@pytest.fixture(scope="module")
def shards(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ddp_tokens")
    write_shards("tokens", token_cache(root / "cache", clips=16), root / "shards", shard_size=3000, progress=False)
    return root / "shards"


def test_two_ranks_with_two_workers_each_read_every_sample_once(shards: Path, tmp_path: Path) -> None:
    out = tmp_path / "keys.json"
    mp.spawn(read_epoch, args=(2, free_port(), str(shards), str(out)), nprocs=2, join=True)
    per_rank = [[tuple(k) for k in keys] for keys in json.loads(out.read_text())]
    every = [k for keys in per_rank for k in keys]
    assert all(per_rank) and len(every) == len(set(every)) == 16 * 2 * 4  # clips × cameras × windows
    alone = window_ids(TokenShardDataModule(str(shards), seq_len=SEQ, stride=STRIDE, batch_size=3).train_dataloader())
    assert set(every) == set(alone)


def test_train_py_trains_on_shards_with_ddp_and_resumes_the_stream(tmp_path: Path) -> None:
    """One drifting segment cut into 6 segment files, 4 of them for training, one per shard: each of 2 ranks reads 2
    shards, 3 batches of 2 windows. The first run stops mid-epoch at step 2, the resumed one finishes the epoch with
    the one batch it had not taken."""
    cache = tmp_path / "cache"
    tokens = (np.random.default_rng(0).integers(0, 16, size=12)[None] + np.arange(60)[:, None]) % 16
    actions = np.random.default_rng(1).normal(size=(60, 2)).astype(np.float32)
    cache.mkdir()
    for i in range(6):
        np.save(cache / f"seg{i}.npy", tokens[i * 10 : i * 10 + 10].reshape(10, 3, 4).astype(np.int16))
        np.save(cache / f"seg{i}.actions.npy", actions[i * 10 : i * 10 + 10])
    write_shards("tokens", cache, tmp_path / "shards", shard_size=400, val_fraction=0.34, progress=False)
    run_dir = tmp_path / "run"
    args = [*world_model_args(tmp_path / "shards", tmp_path / "logs"), "trainer=ddp", "trainer.precision=32-true",
            "data=token_cache_shards", "data.seq_len=8",
            "data.num_workers=1", "data.shuffle_buffer=4", "data.epoch_batches=3", "trainer.val_check_interval=2",
            f"hydra.run.dir={run_dir}"]
    run_train([*args, "trainer.max_steps=2"])
    checkpoint = torch.load(run_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    state = checkpoint["loops"]["fit_loop"]["state_dict"]["combined_loader"]
    assert state == [{"epoch": 0, "taken": [2]}]  # stopped mid-epoch: 2 of its 3 batches taken
    run_train([*args, "trainer.max_steps=3", "ckpt_path=last"])
    resumed = torch.load(run_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert resumed["global_step"] == 3
    # the resumed loader skipped the 2 batches already taken: the epoch ended at step 3 (a loader restarted from the
    # epoch's start would stand at 1 of 3 batches of epoch 0)
    assert resumed["loops"]["fit_loop"]["state_dict"]["combined_loader"] == [{"epoch": 1, "taken": [0]}]
