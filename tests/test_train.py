"""End to end: train.py's task trains, checkpoints, resumes; generate.py reconstructs from the checkpoint."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from gaia_app.tasks.generate import generate
from gaia_app.tasks.train import train
from tests.conftest import ROOT, compose_config

TINY = ["experiment=gaia1/tokenizer_tiny", "trainer=tiny", "data=synthetic_frames_tiny", "extras.print_config=false"]


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("run")
    # 5 steps, checkpoints every 2: the final step is off the grid and must still reach last.ckpt
    cfg = compose_config("train", [*TINY, "trainer.max_steps=5", "callbacks.model_checkpoint.every_n_train_steps=2"],
                         run_dir)
    out = train(cfg)
    assert out["trainer"].global_step == 5
    return run_dir


def test_run_dir_holds_checkpoint_config_and_recording(trained_run: Path) -> None:
    assert (trained_run / "checkpoints" / "last.ckpt").is_file()
    assert (trained_run / "config_resolved.yaml").is_file()
    assert (trained_run / "run.rrd").stat().st_size > 0
    ckpt = torch.load(trained_run / "checkpoints" / "last.ckpt", weights_only=False)
    assert ckpt["hyper_parameters"]["model_cfg"]["_target_"].endswith("ImageTokenizerModule")
    assert ckpt["global_step"] == 5  # the final step, not the last multiple of every_n_train_steps (4)


def test_resume_continues_from_last_checkpoint(trained_run: Path) -> None:
    cfg = compose_config("train", [*TINY, "trainer.max_steps=6", "ckpt_path=last"], trained_run)
    out = train(cfg)
    # resumed at step 5, so only one new step ran
    assert out["trainer"].global_step == 6
    assert out["model"].trainer.fit_loop.epoch_loop._batches_that_stepped == 6


def test_a_resume_with_another_checkpoint_interval_keeps_writing_last_ckpt(tmp_path: Path) -> None:
    """Lightning keys ModelCheckpoint's saved state by its settings: a run resumed with another interval (e.g.
    val_check_interval 2 → 1) does not get its last_model_path back, and with Lightning's version counter it wrote
    last-v1.ckpt beside the stale last.ckpt, so the next ckpt_path=last went back to the older step."""
    run = [*TINY, "trainer.max_steps=2", "callbacks.model_checkpoint.every_n_train_steps=2"]
    train(compose_config("train", run, tmp_path))
    resumed = [*TINY, "trainer.max_steps=4", "callbacks.model_checkpoint.every_n_train_steps=1", "ckpt_path=last"]
    assert train(compose_config("train", resumed, tmp_path))["trainer"].global_step == 4
    assert sorted(p.name for p in (tmp_path / "checkpoints").glob("last*.ckpt")) == ["last.ckpt"]
    assert torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=False)["global_step"] == 4
    again = [*TINY, "trainer.max_steps=5", "callbacks.model_checkpoint.every_n_train_steps=1", "ckpt_path=last"]
    out = train(compose_config("train", again, tmp_path))
    assert out["model"].trainer.fit_loop.epoch_loop._batches_that_stepped == 5  # resumed at 4, not at 2


def test_ckpt_path_last_takes_a_newer_versioned_last_of_an_older_run_dir(tmp_path: Path) -> None:
    import os

    from gaia_app.tasks.train import newest_last

    assert newest_last(tmp_path) == tmp_path / "last.ckpt"  # nothing there: the fresh-start path
    for name, mtime in (("last.ckpt", 100), ("last-v1.ckpt", 300), ("last-v2.ckpt", 200)):
        (tmp_path / name).write_bytes(b"")
        os.utime(tmp_path / name, (mtime, mtime))
    assert newest_last(tmp_path) == tmp_path / "last-v1.ckpt"
    os.utime(tmp_path / "last.ckpt", (400, 400))
    assert newest_last(tmp_path) == tmp_path / "last.ckpt"


def test_resume_from_missing_path_is_an_error(tmp_path: Path) -> None:
    cfg = compose_config("train", [*TINY, "ckpt_path=/nonexistent/x.ckpt"], tmp_path)
    with pytest.raises(FileNotFoundError, match="nonexistent"):
        train(cfg)


def test_generate_reconstructs_from_checkpoint(trained_run: Path, tmp_path: Path) -> None:
    ckpt = trained_run / "checkpoints" / "last.ckpt"
    cfg = compose_config("generate", [f"ckpt={ckpt}", "data=synthetic_frames_tiny", "num_clips=1",
                                      "data.val_source.clip_len=3", "extras.print_config=false"], tmp_path)
    out = generate(cfg)
    results = json.loads((tmp_path / "results.json").read_text())
    assert results == out["results"] and len(results) == 1
    clip_id, scores = next(iter(results.items()))
    assert 0 < scores["psnr"] < 100 and -1 <= scores["ssim"] <= 1
    assert (tmp_path / f"{clip_id}_front.mp4").stat().st_size > 0
    tokens = __import__("numpy").load(tmp_path / f"{clip_id}_tokens.npy")
    assert tokens.shape == (1, 3, 16, 28)  # D = 4 on 64×112 (tiny preset)
    assert (tmp_path / "reconstruction.rrd").stat().st_size > 0


def test_lightning_module_overfits_a_batch(tmp_path: Path) -> None:
    """Through the full Lightning stack: the train loss on two repeated batches falls by ≥ 3× (at 32×48, where it
    falls 4.4× in 80 steps; 4.2× at the preset's 64×112 for 1.7× the time)."""
    cfg = compose_config("train", [*TINY, "data.height=32", "data.width=48", "debug=overfit", "trainer.max_steps=80",
                                   "trainer.val_check_interval=80",
                                   "logger=csv", "callbacks=none", "++trainer.enable_checkpointing=false",
                                   "trainer.log_every_n_steps=1", "model.sched.warmup_steps=5"], tmp_path)
    train(cfg)
    import csv

    rows = list(csv.DictReader(open(next(tmp_path.rglob("metrics.csv")))))
    losses = [float(r["train/loss"]) for r in rows if r.get("train/loss")]
    assert losses[-1] < losses[0] / 3, (losses[0], losses[-1])


@pytest.mark.slow
def test_cli_help_lists_groups_and_fast_dev_run(tmp_path: Path) -> None:
    help_text = subprocess.run([sys.executable, "train.py", "--help"], cwd=ROOT, capture_output=True, text=True,
                               check=True).stdout
    for group in ("data:", "model:", "trainer:", "debug:", "logger:", "experiment/gaia1:"):
        assert group in help_text
    subprocess.run([sys.executable, "train.py", "debug=fdr", "data=synthetic_frames_tiny", f"hydra.run.dir={tmp_path}"],
                   cwd=ROOT, check=True, capture_output=True, text=True, timeout=300)
    assert (tmp_path / "config_resolved.yaml").is_file()


def test_trains_on_a_user_clip_folder(tmp_path: Path) -> None:
    """data=video_folder_frames on exported clips: the user path, read through ClipFolderDataset."""
    from gaia_app.data.clip_writer import write_clip
    from gaia_app.data.synthetic import generate_clip

    root = tmp_path / "clips"
    for seed in range(3):
        write_clip(generate_clip(seed=seed, height=72, width=128, cameras=["front"], clip_len=6, fps=25.0), root)
    cfg = compose_config("train", [*TINY, "data=video_folder_frames", f"data.source.root={root}", "data.height=64",
                                   "data.width=112", "data.batch_size=2", "data.num_workers=0",
                                   "data.val_fraction=0.34", "trainer.max_steps=2", "logger=csv"], tmp_path / "run")
    out = train(cfg)
    assert out["trainer"].global_step == 2
    dm = out["datamodule"]
    assert len(dm.train_clips) == 2 and len(dm.val_clips) == 1
