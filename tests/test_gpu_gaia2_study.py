"""benchmarks/gpu_gaia2_study.py (issue 50): the GAIA-2 study's GPU budgets. On a CPU: the commands it builds, what it
brings back, its refusal without CUDA, and (slow tier) the whole dry run: encode, every arm at two budgets, slim
checkpoints that load as world models with each arm's conditioning paths."""

from __future__ import annotations

import tarfile
from pathlib import Path

import pytest
import torch

from tests.conftest import compose_config, load_benchmark


@pytest.fixture(scope="module")
def study():
    return load_benchmark("gpu_gaia2_study")


def test_each_arm_gets_its_experiment_budget_and_options(study, tmp_path: Path) -> None:
    latents = tmp_path / "latents"
    paper = study.train_command("paper", 250, latents, tmp_path / "run", 300, dry=False)
    assert {"experiment=gaia2/road_users/world_model_s4_paper_gpu", "trainer.max_steps=250",
            f"data.path={latents}", "+trainer.max_time=00:00:04:15"} <= set(paper)
    keyed = study.train_command("paper_posqk", 2000, latents, tmp_path / "run", 300, dry=False)
    assert {"model.net.agent_position_keys=true", "model.net.agent_position_queries=true",
            "trainer.val_check_interval=1000"} <= set(keyed)
    weighted = study.train_command("paper_boxattn_agentloss", 250, latents, tmp_path / "run", 300, dry=False)
    assert {"model.net.agent_box_attention=true", "model.agent_loss_weight=9.0"} <= set(weighted)
    onsets = study.train_command("paper_onsets", 250, latents, tmp_path / "run", 300, dry=False)
    assert {"experiment=gaia2/road_users/world_model_s4_paper_gpu", "data.window_sampling=action_change",
            "data.train_meta={open_loop:true}"} <= set(onsets)
    assert "paper_onsets" in study.parse_args(["--out", str(tmp_path)]).arms
    experiment, extra = study.ARMS["paper_onsets"]
    composed = compose_config("train", [f"experiment={experiment}", *extra], tmp_path / "onsets")
    assert dict(composed.data.train_meta) == {"open_loop": True}
    experiment, extra = study.ARMS["paper_onsets_p1"]
    fine = compose_config("train", [f"experiment={experiment}", *extra], tmp_path / "onsets_p1")
    assert fine.model.net.patch_size == 1 and composed.model.net.patch_size == 2
    assert fine.data.window_sampling == "action_change" and not fine.model.net.action_raster
    experiment, extra = study.ARMS["paper_onsets_w6"]
    long = compose_config("train", [f"experiment={experiment}", *extra], tmp_path / "onsets_w6")
    assert long.data.steps == 6 and composed.data.steps == 4 and long.data.change_after == 2
    assert "paper_onsets_w6" not in study.parse_args(["--out", str(tmp_path)]).arms  # opt-in
    shortcut = study.train_command("shortcut", 1200, latents, tmp_path / "run", 300, dry=False)
    assert "experiment=gaia2/road_users/world_model_s4_gpu" in shortcut
    assert not any(a.startswith("model.net.agent_position") for a in shortcut)
    encode = study.encode_command(latents, dry=False)
    assert {"mode=encode", "weights=gaia2_road_users", "data.source.num_clips=960", "device=cuda"} <= set(encode)


def test_the_gpu_presets_grow_the_cpu_recipe_and_keep_the_paper_paths(tmp_path: Path) -> None:
    shortcut, paper, cpu = (compose_config("train", [f"experiment=gaia2/road_users/{name}"], tmp_path / name)
                            for name in ("world_model_s4_gpu", "world_model_s4_paper_gpu", "world_model_s4"))
    assert (shortcut.model.net.dim, shortcut.model.net.depth) == (2 * cpu.model.net.dim, 2 * cpu.model.net.depth)
    assert shortcut.data.batch_size == 4 * cpu.data.batch_size and shortcut.trainer.accelerator == "gpu"
    assert shortcut.model.latent_scale == cpu.model.latent_scale
    assert shortcut.model.net.agent_raster and not paper.model.net.agent_raster and not paper.model.net.action_raster


def test_what_comes_back_is_the_report_and_one_archive(study, tmp_path: Path) -> None:
    back, out = tmp_path / "back", tmp_path / "out"
    back.mkdir()
    (back / "paper_250.ckpt").write_bytes(b"w")
    (back / "paper_250.log").write_text("log")
    (back / "encode.log").write_text("e")
    study.pack(out, back, ["paper_250", "shortcut_250"])
    with tarfile.open(out / "gaia2_study.tar") as archive:
        assert sorted(archive.getnames()) == ["encode.log", "paper_250.ckpt", "paper_250.log"]


def test_no_cuda_and_bad_steps_are_refused(study, tmp_path: Path, monkeypatch) -> None:
    with pytest.raises(SystemExit):
        study.parse_args(["--out", str(tmp_path), "--steps", "0"])
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SystemExit, match="needs CUDA"):
        study.main(["--out", str(tmp_path)])


@pytest.mark.rehearsal
def test_dry_run_encodes_trains_every_arm_and_brings_back_loadable_checkpoints(study, tmp_path: Path) -> None:
    from gaia_app.weights.nets import checkpoint_nets

    data = study.main(["--out", str(tmp_path / "out"), "--work", str(tmp_path / "work"), "--dry-run",
                       "--steps", "2", "1"])
    stages = data["stages"]
    runs = [f"{arm}_{steps}" for steps in (2, 1) for arm in ("shortcut", "paper", "paper_boxattn", "paper_onsets")]
    assert all(stages[name]["status"] == "ok" for name in ["encode", *runs]), stages
    with tarfile.open(tmp_path / "out/gaia2_study.tar") as archive:
        archive.extractall(tmp_path / "back", filter="data")
    nets = {arm: checkpoint_nets(tmp_path / f"back/{arm}_2.ckpt", "latent_world_model", "world_model_ckpt")[0]["net"]
            for arm in ("shortcut", "paper", "paper_boxattn", "paper_onsets")}
    assert nets["shortcut"].conditioner.agent_raster is not None
    assert nets["paper"].conditioner.agent_raster is None and not nets["paper"].agent_box_attention
    assert nets["paper_boxattn"].agent_box_attention and nets["paper_boxattn"].conditioner.agent_raster is None
    assert nets["paper_onsets"].conditioner.agent_raster is None and not nets["paper_onsets"].agent_box_attention
    assert len(list((tmp_path / "out").iterdir())) <= 8
