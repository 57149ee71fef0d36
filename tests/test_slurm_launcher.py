"""hydra/launcher=slurm (issue 24, item 6): a sweep composes with the submitit SLURM launcher, and each job it would
submit asks for the run's rig (nodes = trainer.num_nodes, one task and one GPU per device). No cluster is needed:
a stand-in `srun` on PATH lets submitit build its executor, and the sbatch header it would submit is checked."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from tests.conftest import compose_config

pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="pip install -e .[slurm]")


def sbatch_header(launcher_cfg, folder: Path, monkeypatch) -> str:
    """The sbatch script submitit would submit for one job of this launcher config, as the plugin builds it."""
    import submitit
    from hydra_plugins.hydra_submitit_launcher.config import BaseQueueConf

    bin_dir = folder / "bin"
    bin_dir.mkdir(parents=True)
    for tool in ("srun", "sbatch"):  # submitit checks that it runs on a SLURM node
        (bin_dir / tool).write_text("#!/bin/sh\nexit 0\n")
        (bin_dir / tool).chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    params = {k: v for k, v in launcher_cfg.items() if k != "_target_"}
    init = {"folder": str(folder / "submitit"), "slurm_max_num_timeout": params.pop("max_num_timeout")}
    params.pop("submitit_folder")
    executor = submitit.AutoExecutor(cluster="slurm", **init)
    base = set(OmegaConf.structured(BaseQueueConf).keys())
    executor.update_parameters(**{k if k in base else f"slurm_{k}": v for k, v in params.items()})
    return executor._executor._make_submission_file_text("python -u -m submitit.core._submit x", "job")


def test_a_paper_sweep_submits_one_task_per_gpu_on_the_runs_nodes(tmp_path: Path, monkeypatch) -> None:
    cfg = compose_config("train", ["hydra/launcher=slurm", "experiment=gaia1/world_model_paper",
                                   "hydra.launcher.partition=gpu"], tmp_path)
    launcher = OmegaConf.to_container(cfg.hydra.launcher, resolve=True)
    assert launcher["_target_"].endswith("submitit_launcher.SlurmLauncher")
    assert (launcher["nodes"], launcher["tasks_per_node"], launcher["gpus_per_node"]) == (8, 8, 8)  # 64 GPUs, §4.2
    header = sbatch_header(launcher, tmp_path, monkeypatch)
    for line in ("#SBATCH --nodes=8", "#SBATCH --ntasks-per-node=8", "#SBATCH --gpus-per-node=8",
                 "#SBATCH --cpus-per-task=12", "#SBATCH --time=2880", "#SBATCH --partition=gpu"):
        assert line in header, f"{line} missing from\n{header}"
    # the launcher class itself builds from the composed config (what `train.py -m` would use)
    assert type(instantiate(cfg.hydra.launcher)).__name__ == "SlurmLauncher"


def test_the_rig_follows_the_trainer_overrides(tmp_path: Path) -> None:
    cfg = compose_config("train", ["hydra/launcher=slurm", "experiment=gaia1/video_decoder_paper",
                                   "trainer.num_nodes=2", "trainer.devices=4"], tmp_path)
    launcher = cfg.hydra.launcher
    assert (launcher.nodes, launcher.tasks_per_node, launcher.gpus_per_node) == (2, 4, 4)
