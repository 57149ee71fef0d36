"""The tiny checkpoints the suite trains, each once per test run (issue 52 item 6).

Every builder trains real components through train.py / generate.py for a step or two, so the weights are noise but
every file is what a trained run writes. `built_once` keeps one copy for the whole run: under pytest-xdist the
workers share the run's base temporary folder and a file lock, so the first worker to ask builds and the others
wait for it and reuse the folder. Tests read these folders and never write into them (each test writes to its own
tmp_path).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import torch
from filelock import FileLock

from tests.conftest import TINY_TOKENIZER, compose_config

QUIET = ["extras.print_config=false", "logger=none", "callbacks=model_checkpoint"]
# 32×48 images → 8×12 = 96 tokens per frame at D = 4: a quarter of the tiny preset's sampling work
GAIA1_SIZE = ["data.height=32", "data.width=48"]
GAIA1_WORLD_MODEL_NET = ["model.net.dim=32", "model.net.depth=1", "model.net.heads=2", "model.net.kv_heads=1"]
GAIA1_DECODER_NET = ["model.net.channels=8", "model.net.channel_mults=[1,2]", "model.net.attention_levels=[1]",
                     "model.net.token_dim=8", "model.net.heads=2", "model.net.vocab_size=512",
                     "model.net.token_grid=[8,12]", "model.net.image_size=[32,48]"]
GAIA2_RIG = ["data=synthetic_rig_tiny", "extras.print_config=false"]


def built_once(base: Path, name: str, build: Callable[[Path], None]) -> Path:
    """`base/name`, filled by `build(folder)` the first time any worker of this run asks for it.

    A folder left half-built by a failed build has no `.built` marker and is built again from scratch."""
    folder = base / name
    with FileLock(str(folder) + ".lock"):
        if not (folder / ".built").exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            threads = torch.get_num_threads()
            torch.set_num_threads(1)  # tiny nets: a second thread only waits on the other worker's core
            try:
                build(folder)
            finally:
                torch.set_num_threads(threads)
            (folder / ".built").touch()
    return folder


def run_base(tmp_path_factory) -> Path:
    """The folder every worker of this test run sees: the run's base temp folder (its parent under xdist)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def _train(overrides: list[str], run_dir: Path) -> None:
    from gaia_app.tasks.train import train

    train(compose_config("train", overrides, run_dir))


def _generate(overrides: list[str], run_dir: Path) -> None:
    from gaia_app.tasks.generate import generate

    generate(compose_config("generate", overrides, run_dir))


def build_tokenizer(folder: Path) -> None:
    """A 2-step GAIA-1 tokenizer run at the tiny preset's 64×112, exactly as train.py writes it."""
    _train([*TINY_TOKENIZER, "trainer.max_steps=2"], folder / "run")


def tokenizer_checkpoint(folder: Path) -> Path:
    return folder / "run" / "checkpoints" / "last.ckpt"


def build_gaia1(folder: Path) -> None:
    """GAIA-1 Fig. 1 at 32×48: tokenizer (1 step) → token cache → world model (2 steps) → video decoder (1 step)."""
    _train(["experiment=gaia1/tokenizer_tiny", "trainer=tiny", "trainer.max_steps=1", "data=synthetic_frames_tiny",
            *GAIA1_SIZE, *QUIET], folder / "tokenizer")
    tokenizer = folder / "tokenizer" / "checkpoints" / "last.ckpt"
    _generate(["mode=tokenize", "data=synthetic_tiny", f"ckpt={tokenizer}", f"out_dir={folder / 'tokens'}",
               "extras.print_config=false", *GAIA1_SIZE], folder / "tokenize")
    _train(["experiment=gaia1/world_model_tiny", "trainer=tiny", "trainer.max_steps=2", "trainer.limit_val_batches=0",
            f"data.path={folder / 'tokens' / 'train'}", "data.frame_stride=1", "model.net.image_tokens=96",
            *GAIA1_WORLD_MODEL_NET, *QUIET], folder / "world_model")
    _train(["experiment=gaia1/video_decoder_tiny", "trainer=tiny", "trainer.max_steps=1", "trainer.limit_val_batches=0",
            f"model.tokenizer_ckpt={tokenizer}", "data.source.num_clips=2", "data.val_source.num_clips=1",
            *GAIA1_SIZE, *GAIA1_DECODER_NET, *QUIET], folder / "decoder")


def gaia1_checkpoints(folder: Path) -> dict[str, Path]:
    """generate.py's checkpoint settings for the chain of `build_gaia1`."""
    return {"tokenizer_ckpt": folder / "tokenizer" / "checkpoints" / "last.ckpt",
            "world_model_ckpt": folder / "world_model" / "checkpoints" / "last.ckpt",
            "decoder_ckpt": folder / "decoder" / "checkpoints" / "last.ckpt"}


def build_gaia2(folder: Path) -> None:
    """A tiny 3-camera video tokenizer (2 steps), its latent cache of 16-frame clips (4 latent steps) and a tiny
    latent world model (2 steps) on it."""
    _train(["experiment=gaia2/video_tokenizer_tiny", "trainer=tiny", *GAIA2_RIG, "trainer.max_steps=2", "logger=csv"],
           folder / "tok")
    _generate(["mode=encode", *GAIA2_RIG, f"ckpt={folder / 'tok' / 'checkpoints' / 'last.ckpt'}",
               f"out_dir={folder / 'latents'}", "data.source.clip_len=16", "data.source.num_clips=4"], folder / "enc")
    _train(["experiment=gaia2/world_model_tiny", "trainer=tiny", "trainer.max_steps=2",
            f"data.path={folder / 'latents'}", "data.batch_size=2", "logger=csv", "extras.print_config=false"],
           folder / "wm")


def gaia2_checkpoints(folder: Path) -> dict[str, Path]:
    """The tokenizer and world-model checkpoints and the latent cache of `build_gaia2`."""
    return {"tokenizer": folder / "tok" / "checkpoints" / "last.ckpt",
            "world_model": folder / "wm" / "checkpoints" / "last.ckpt", "latents": folder / "latents"}
