"""benchmarks/gpu_road_users.py (issue 49): the GPU run that trains the GAIA-1 world model on the D = 4 tokenizer's
448 tokens per frame. On a CPU: its pieces, its refusal without CUDA, and (slow tier) the whole dry run, whose
checkpoints load as inference nets."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from gaia_app.weights.nets import NETS_RECORD, checkpoint_nets
from tests.conftest import ROOT, load_benchmark


@pytest.fixture(scope="module")
def road_users():
    return load_benchmark("gpu_road_users")


def test_training_stages_stop_inside_their_budget(road_users) -> None:
    assert road_users.max_time(300) == "+trainer.max_time=00:00:04:15"
    assert road_users.max_time(3_700) == "+trainer.max_time=00:01:00:55"
    assert road_users.max_time(10) == "+trainer.max_time=00:00:00:30"  # never below half a minute


def test_both_clip_mixes_go_into_one_cache(road_users, tmp_path: Path) -> None:
    commands = road_users.tokenize_commands(tmp_path / "tok.ckpt", tmp_path / "cache", dry=False)
    assert len(commands) == 2
    for argv in commands:
        assert {f"out_dir={tmp_path / 'cache'}", "device=cuda", "data.source.num_clips=1024"} <= set(argv)
    assert "data.source.driven_share=0.5" in commands[0] and "data.val_source.num_clips=128" in commands[0]
    assert {"data.source.driven_share=1.0", "seed=5", "splits=[train]"} <= set(commands[1])
    dry = road_users.tokenize_commands(tmp_path / "tok.ckpt", tmp_path / "cache", dry=True)
    assert all("data.source.num_clips=2" in argv and "data.source.num_clips=1024" not in argv for argv in dry)


def test_a_tokenizer_weights_folder_is_read_as_weights_and_a_checkpoint_as_ckpt(road_users, tmp_path: Path) -> None:
    folder = tmp_path / "gaia1_road_users"
    folder.mkdir()
    assert road_users.tokenize_commands(folder, tmp_path / "cache", dry=False)[0][2] == f"weights={folder}"
    assert road_users.tokenize_commands(tmp_path / "t.ckpt", tmp_path / "cache", dry=False)[0][2] == \
        f"ckpt={tmp_path / 't.ckpt'}"
    assert load_benchmark("gpu_paper_faithful").export_command(folder, tmp_path / "w.ckpt", tmp_path / "o")[2] == \
        f"weights={folder}"


def test_slim_checkpoint_keeps_what_inference_reads_in_float16(road_users, tmp_path: Path) -> None:
    state = {"net.weight": torch.randn(4, 4), "net.steps": torch.tensor(3)}
    full = {"state_dict": state, "hyper_parameters": {"model_cfg": {"a": 1}}, NETS_RECORD: {"component": "tokenizer"},
            "global_step": 7, "optimizer_states": [{"big": torch.randn(100)}], "loops": {}}
    torch.save(full, tmp_path / "last.ckpt")
    info = road_users.slim_checkpoint(tmp_path / "last.ckpt", tmp_path / "slim.ckpt")
    slim = torch.load(tmp_path / "slim.ckpt", weights_only=True)
    assert set(slim) == {"state_dict", "hyper_parameters", NETS_RECORD, "global_step"}
    assert slim["state_dict"]["net.weight"].dtype == torch.float16
    assert slim["state_dict"]["net.steps"].dtype == torch.int64  # counters stay integers
    torch.testing.assert_close(slim["state_dict"]["net.weight"].float(), state["net.weight"], atol=1e-3, rtol=1e-3)
    assert info == {"file": "slim.ckpt", "megabytes": info["megabytes"], "global_step": 7}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt", "slim.ckpt"]  # no temporary file left


def test_without_cuda_the_real_run_refuses_in_one_line(road_users, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SystemExit, match="needs CUDA"):
        road_users.main(["--out", str(tmp_path)])
    assert not (tmp_path / "road_users.json").exists()


def test_a_failed_stage_is_recorded_and_stops_the_run(road_users, tmp_path: Path) -> None:
    report = road_users.Report(tmp_path, {"dry_run": True})
    ok = road_users.run_stage(report, tmp_path, "broken", [["-c", "print('x' * 10); raise SystemExit(3)"],
                                                           ["-c", "print('never')"]], budget=60)
    stage = json.loads((tmp_path / "road_users.json").read_text())["stages"]["broken"]
    assert not ok and stage["status"] == "exit 3" and len(stage["commands"]) == 2
    log = (tmp_path / "broken.log").read_text()
    assert "xxxxxxxxxx" in log and "never" not in log


@pytest.mark.rehearsal
def test_dry_run_trains_every_stage_and_brings_back_loadable_checkpoints(road_users, tmp_path: Path) -> None:
    from gaia_app.encoders.text import minilm_package_path

    data = road_users.main(["--out", str(tmp_path / "out"), "--work", str(tmp_path / "work"), "--dry-run",
                            "--minilm", str(minilm_package_path())])
    stages = data["stages"]
    assert all(stages[name]["status"] == "ok" for name in ("tokenizer", "tokenize", "world_model", "paper_d4")), stages
    paper = checkpoint_nets(tmp_path / "out/paper_d4.ckpt", "world_model", "world_model_ckpt")
    assert not paper.nets["net"].action_shortcut and paper.config["text_encoder"]["path"] is None
    world_model = checkpoint_nets(tmp_path / "out/world_model_d4.ckpt", "world_model", "world_model_ckpt")
    tokenizer = checkpoint_nets(tmp_path / "out/tokenizer_d4.ckpt", "tokenizer", "tokenizer_ckpt")
    assert world_model.nets["net"].n == 448  # image tokens per frame
    grid = tokenizer.nets["net"].encode(torch.zeros(1, 3, 64, 112)).shape[-2:]
    assert grid[0] * grid[1] == 448
    assert len(list((tmp_path / "out").iterdir())) <= 8  # what a GPU machine brings back


def test_world_models_side_by_side_each_get_their_log_and_status(road_users, tmp_path: Path) -> None:
    report = road_users.Report(tmp_path, {"dry_run": True})
    done = road_users.run_side_by_side(report, tmp_path, {"a": ["-c", "print('arm a')"],
                                                          "b": ["-c", "import time; time.sleep(30)"]}, budget=5)
    assert done == {"a": True, "b": False}
    stages = json.loads((tmp_path / "road_users.json").read_text())["stages"]
    assert stages["a"]["status"] == "ok" and stages["b"]["status"] == "timeout"
    assert "arm a" in (tmp_path / "a.log").read_text()


def test_the_paper_arm_trains_beside_only_with_minilm(road_users, tmp_path: Path) -> None:
    alone = road_users.world_model_arms(tmp_path / "cache", tmp_path, 300, dry=False, minilm=None)
    both = road_users.world_model_arms(tmp_path / "cache", tmp_path, 300, dry=False, minilm=tmp_path / "minilm")
    assert list(alone) == ["world_model"] and list(both) == ["world_model", "paper_d4"]
    assert "experiment=gaia1/paper_faithful/world_model_d4_gpu" in both["paper_d4"]
    assert f"model.text_encoder.path={tmp_path / 'minilm'}" in both["paper_d4"]
    assert both["world_model"] == alone["world_model"]  # the same wall clock and cache for both arms
    assert both["paper_d4"][-4:-2] == [road_users.max_time(300), f"model.text_encoder.path={tmp_path / 'minilm'}"]


def test_slim_paper_checkpoint_reads_minilm_from_its_package_again(road_users, tmp_path: Path) -> None:
    cfg = {"text_encoder": {"_target_": "gaia_app.encoders.text.MiniLMTextEncoder", "path": "/tmp/road_users/minilm"}}
    torch.save({"state_dict": {"net.w": torch.ones(2)}, "hyper_parameters": {"model_cfg": cfg}}, tmp_path / "l.ckpt")
    road_users.slim_checkpoint(tmp_path / "l.ckpt", tmp_path / "slim.ckpt")
    slim = torch.load(tmp_path / "slim.ckpt", weights_only=True)
    assert slim["hyper_parameters"]["model_cfg"]["text_encoder"]["path"] is None


@pytest.mark.rehearsal
def test_gpu_stubs_stand_in_for_rerun_and_pyav_on_a_lease_machine(tmp_path: Path) -> None:
    """The GPU machine has neither rerun-sdk nor PyAV: with benchmarks/gpu_stubs first on PYTHONPATH the token-cache
    and training entry points still import, and a no-op call returns without logging."""
    import os
    import subprocess
    import sys

    code = ("import rerun as rr, av; from gaia_app.tasks.modes import mode_run; import gaia_app.tasks.train; "
            "assert 'gpu_stubs' in rr.__file__ and 'gpu_stubs' in av.__file__; rr.RecordingStream('x').log('y')")
    env = {**os.environ, "PYTHONPATH": f"{ROOT / 'benchmarks' / 'gpu_stubs'}{os.pathsep}{ROOT}"}
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
