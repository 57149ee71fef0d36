"""Nothing lost, nothing mixed (issue: nothing runs, nothing lost): one run per run folder, one writer per cache,
damaged weights refused at load with the file and tensor named. (Shards: tests/data/test_shards.py.)"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from gaia_app.tasks.generate import generate
from gaia_app.utils.locks import FolderInUseError, FolderLock, folder_lock
from gaia_app.utils.run_dir import RunDirLock
from gaia_app.utils.untrusted import UntrustedDataError
from gaia_app.weights.folders import WEIGHTS_ROOT, load_nets
from gaia_app.weights.nets import checkpoint_nets
from tests.conftest import ROOT, compose_config, tampered

pytestmark = pytest.mark.usefixtures("one_thread")


def test_a_second_run_in_a_busy_run_folder_fails_before_writing_anything(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    with folder_lock(run_dir, "hydra.run.dir"):  # as if another run were writing there
        done = subprocess.run([sys.executable, "generate.py", "mode=reconstruct", f"hydra.run.dir={run_dir}"],
                              cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode != 0
    assert f"hydra.run.dir={run_dir} is in use by another running process (pid {os.getpid()})" in done.stderr
    assert sorted(p.name for p in run_dir.iterdir()) == [".lock"]  # no .hydra/, no log: the other run's files stay


def test_the_lock_is_dropped_with_its_process_and_shared_ranks_take_none(tmp_path: Path, monkeypatch) -> None:
    folder = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from gaia_app.utils.locks import FolderLock; "
                               f"lock = FolderLock({str(folder)!r}, 'x').acquire(); "
                               "print('held', flush=True); time.sleep(60)"],
                              stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert holder.stdout.readline().strip() == "held"
    with pytest.raises(FolderInUseError, match=f"pid {holder.pid}"):
        FolderLock(folder, "x").acquire()
    holder.kill()  # kill -9: no clean-up ran, yet the kernel dropped the lock
    holder.wait()
    FolderLock(folder, "x").acquire().release()
    config = OmegaConf.create({"hydra": {"run": {"dir": str(folder)}}})
    with folder_lock(folder, "x"):
        monkeypatch.setenv("LOCAL_RANK", "1")  # a DDP child of the run that holds the folder
        RunDirLock().on_run_start(config)
        monkeypatch.delenv("LOCAL_RANK")
        with pytest.raises(SystemExit, match="in use by another running process"):
            RunDirLock().on_run_start(config)


def test_default_run_folders_of_two_processes_differ() -> None:
    stamp = OmegaConf.create({"d": "${pid:}"}).d
    assert stamp == str(os.getpid())
    hydra_defaults = (ROOT / "conf" / "hydra" / "default.yaml").read_text()
    assert "${now:%Y-%m-%d_%H-%M-%S}_${pid:}" in hydra_defaults and "RunDirLock" in hydra_defaults


def test_two_caches_cannot_fill_one_folder_at_once(genuine: Path, tmp_path: Path) -> None:
    out = tmp_path / "cache"
    base = ["mode=tokenize", f"ckpt={genuine}", "data=synthetic_tiny", "splits=[train]", "max_clips=1",
            f"out_dir={out}", "extras.print_config=false"]
    with folder_lock(out / "train", "out_dir"):  # another tokenize run, still writing
        with pytest.raises(FolderInUseError, match=rf"out_dir={out / 'train'} is in use"):
            generate(compose_config("generate", base, tmp_path / "g1"))
    assert not (out / "train" / "cache.json").exists()
    results = generate(compose_config("generate", base, tmp_path / "g2"))["results"]
    assert results["train"]["written"] == 1  # the lock file alone does not make the folder "a cache made differently"


def test_non_finite_shipped_weights_are_refused_naming_file_and_tensor(tmp_path: Path) -> None:
    from safetensors.torch import load_file, save_file

    folder = tmp_path / "weights"
    shutil.copytree(WEIGHTS_ROOT / "gaia1", folder)
    path = folder / "tokenizer.safetensors"
    tensors = load_file(str(path))
    name = sorted(k for k, v in tensors.items() if v.is_floating_point())[3]
    tensors[name] = tensors[name].clone()
    tensors[name].view(-1)[0] = float("nan")
    save_file(tensors, str(path))
    with pytest.raises(ValueError, match=rf"{path}: tensor '{name}' holds NaN or infinite values"):
        load_nets(folder, "tokenizer")


def test_non_finite_checkpoint_weights_are_refused_naming_file_and_tensor(genuine: Path, tmp_path: Path) -> None:
    def poison(checkpoint: dict) -> None:
        weight = next(k for k in checkpoint["state_dict"] if k.startswith("net.") and k.endswith("weight"))
        checkpoint["state_dict"][weight] = torch.full_like(checkpoint["state_dict"][weight], float("inf"))

    path = tampered(genuine, tmp_path, poison)
    with pytest.raises(UntrustedDataError,
                       match=rf"ckpt={path}: state_dict under 'net\.': tensor '.*weight' holds NaN"):
        checkpoint_nets(path, "tokenizer", role="ckpt")


def test_shipped_names_resolve_in_load_nets() -> None:
    nets, info = load_nets("gaia1", "tokenizer")
    assert set(nets) == {"net"} and info["image_size"] == [64, 112]
