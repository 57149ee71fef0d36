"""benchmarks/gpu_checks.py (issue 51, item 5): the dry run writes its JSON and Markdown on a CPU, and without CUDA
the real run refuses in one line. The GPU numbers themselves come from a GPU machine (docs/gpu_speed.md)."""

from __future__ import annotations

import importlib.util
import json
import signal
import sys

import pytest
import torch

from tests.conftest import ROOT


@pytest.fixture
def gpu_checks(monkeypatch):
    spec = importlib.util.spec_from_file_location("gpu_checks", ROOT / "benchmarks" / "gpu_checks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    handler, threads = signal.getsignal(signal.SIGALRM), torch.get_num_threads()
    torch.set_num_threads(1)  # tiny sizes: a second OpenMP thread on a busy core only stalls
    yield module
    signal.signal(signal.SIGALRM, handler)
    torch.set_num_threads(threads)


@pytest.mark.rehearsal
def test_dry_run_writes_every_check(gpu_checks, monkeypatch, tmp_path) -> None:
    monkeypatch.setattr(sys, "argv", ["gpu_checks.py", "--out", str(tmp_path), "--dry-run", "--tokens-per-call", "3"])
    gpu_checks.main()
    data = json.loads((tmp_path / "gpu_checks.json").read_text())
    assert data["meta"]["dry_run"] and data["meta"]["torch"] == torch.__version__ and data["meta"]["date"]
    checks = data["checks"]
    expected = {"bandwidth", "generation_100M", "generation_300M", "futures_16", "training_mfu", "gaia2_rollout",
                "strategies"}
    assert expected <= set(checks)
    assert all(checks[name]["status"] == "ok" for name in checks), checks
    rows = checks["futures_16"]["rows"]
    assert checks["futures_16"]["batch"] == 16 and rows["eager"]["tokens_per_s"] > 0
    assert 0 < rows["compiled"]["roofline_fraction"] and checks["training_mfu"]["mfu"] > 0
    assert rows["compiled"]["tokens_per_call"] == 3 and rows["eager"]["tokens_per_call"] == 1
    assert "| generation_300M | compiled |" in (tmp_path / "gpu_checks.md").read_text()
    assert checks["gaia2_rollout"]["rows"]["50 Euler steps"]["frames_per_s"] > 0
    assert checks["strategies"]["rows"]["fsdp2"]["steps"] == "4 → 6"  # trained, then resumed from its checkpoint
    assert "| strategies | fsdp2 |" in (tmp_path / "gpu_checks.md").read_text()


def test_a_check_past_its_budget_is_marked_and_the_rest_still_written(gpu_checks, tmp_path) -> None:
    report = gpu_checks.Report(tmp_path, {"date": "now", "device": "cpu", "torch": "x", "cuda": None, "dry_run": True})
    signal.signal(signal.SIGALRM, gpu_checks.on_timeout)

    def slow(save):
        save({"rows": {"eager": {"frames_per_s": 1.0}}})
        while True:
            pass

    gpu_checks.run_check(report, "slow", slow, budget=1.0)
    result = json.loads((tmp_path / "gpu_checks.json").read_text())["checks"]["slow"]
    assert result["status"] == "timeout" and result["rows"]["eager"]["frames_per_s"] == 1.0


def test_without_cuda_it_refuses_in_one_line(gpu_checks, monkeypatch, capsys, tmp_path) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(sys, "argv", ["gpu_checks.py", "--out", str(tmp_path / "gpu")])
    with pytest.raises(SystemExit) as exit_:
        gpu_checks.main()
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.strip().count("\n") == 0 and "no CUDA device" in err
    assert not (tmp_path / "gpu").exists()
