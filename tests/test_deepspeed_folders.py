"""DeepSpeed checkpoint folders (trainer=deepspeed_zero2): `ckpt_path=last` checks them before Lightning resumes,
`read_checkpoint` reads a ZeRO-2 folder's weights, and nothing in one runs code
(gaia_app/weights/deepspeed_folders.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from gaia_app.tasks.train import resume_path
from gaia_app.weights.checkpoints import UnsafeCheckpointError, check_checkpoint_file, read_checkpoint
from tests.conftest import DEEPSPEED_ONE_PROCESS, ROOT, Payload

deepspeed = pytest.importorskip("deepspeed")
from deepspeed.runtime.fp16.loss_scaler import LossScaler  # noqa: E402
from deepspeed.runtime.zero.config import ZeroStageEnum  # noqa: E402
from deepspeed.utils.tensor_fragment import fragment_address  # noqa: E402

HYPER = {"model_cfg": {"_target_": "gaia_app.lit.world_model.WorldModelModule"}}


def lay_out(folder: Path, stage: int = 2, optimizer_extra: object = None, tag: str = "checkpoint") -> Path:
    """A folder laid out as Lightning's DeepSpeedStrategy saves one: `latest`, the model states (Lightning's
    entries beside the engine's) and one rank's optimizer states holding
    DeepSpeed's loss scaler, stage enum and fragment addresses."""
    (folder / tag).mkdir(parents=True)
    model_states = "zero_pp_rank_0_mp_rank_00_model_states.pt" if stage == 3 else "mp_rank_00_model_states.pt"
    (folder / "latest").write_text(tag)
    torch.save({"module": {"net.weight": torch.ones(3)}, "ds_config": {"zero_optimization":
                {"stage": stage}}, "ds_version": "0.19", "global_step": 20, "hyper_parameters": HYPER,
                "loops": {"fit_loop": {}}},
               folder / tag / model_states)
    optimizer = {"loss_scaler": LossScaler(1.0), "zero_stage": ZeroStageEnum(stage),
                 "param_slice_mappings": [{"net.weight": fragment_address(numel=3, start=0)}], "extra": optimizer_extra}
    torch.save({"optimizer_state_dict": optimizer, "ds_version": "0.19"},
               folder / tag / "zero_pp_rank_0_mp_rank_00_optim_states.pt")
    return folder


def test_a_deepspeed_folder_passes_the_resume_check_and_reads_its_weights(tmp_path: Path) -> None:
    folder = lay_out(tmp_path / "checkpoints" / "last.ckpt")
    assert resume_path("last", tmp_path) == str(folder)  # checked, not refused for lacking a DCP index
    checkpoint = read_checkpoint(folder)
    assert list(checkpoint["state_dict"]) == ["net.weight"]
    assert checkpoint["global_step"] == 20 and checkpoint["hyper_parameters"] == HYPER
    assert "ds_config" not in checkpoint and "module" not in checkpoint


def test_a_pickled_object_in_the_optimizer_states_is_refused_and_runs_nothing(tmp_path: Path) -> None:
    marker = tmp_path / "ran"
    folder = lay_out(tmp_path / "last.ckpt", optimizer_extra=Payload(marker))
    with pytest.raises(UnsafeCheckpointError, match="optim_states.pt"):
        check_checkpoint_file(folder)
    assert not marker.exists()


def test_a_tag_outside_the_folder_is_refused(tmp_path: Path) -> None:
    folder = lay_out(tmp_path / "last.ckpt")
    (folder / "latest").write_text("../elsewhere")
    with pytest.raises(ValueError, match="expected one folder name"):
        check_checkpoint_file(folder)


def test_a_zero3_folder_resumes_and_reading_it_names_the_converter(tmp_path: Path) -> None:
    folder = lay_out(tmp_path / "last.ckpt", stage=3)  # ZeRO-3 names its model states per rank
    check_checkpoint_file(folder)
    with pytest.raises(ValueError, match="convert_zero_checkpoint_to_fp32_state_dict"):
        read_checkpoint(folder)


ENGINE_SCRIPT = """
import sys, deepspeed, torch
from gaia_app.models.gaia1.world_model import WorldModel
torch.manual_seed(0)
deepspeed.init_distributed(dist_backend="gloo")
net = WorldModel(16, 32, 2, 2, kv_heads=1, frames=4, image_tokens=12)
config = {"train_micro_batch_size_per_gpu": 2, "zero_optimization": {"stage": 2}}
engine, _, _, _ = deepspeed.initialize(model=net, optimizer=torch.optim.AdamW(net.parameters(), lr=1e-3), config=config)
engine.save_checkpoint(sys.argv[1], client_state={"global_step": 3, "hyper_parameters": {"lr": 1e-3}}, tag="checkpoint")
torch.save(net.state_dict(), sys.argv[2])
"""


@pytest.mark.slow
def test_a_folder_written_by_deepspeed_itself_is_checked_and_read(tmp_path: Path) -> None:
    script = tmp_path / "save.py"
    script.write_text(DEEPSPEED_ONE_PROCESS + ENGINE_SCRIPT)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT), "MASTER_ADDR": "127.0.0.1",
           "MASTER_PORT": "29563", "RANK": "0", "LOCAL_RANK": "0", "WORLD_SIZE": "1", "DS_ACCELERATOR": "cpu"}
    folder, weights = tmp_path / "last.ckpt", tmp_path / "weights.pt"
    done = subprocess.run([sys.executable, str(script), str(folder), str(weights)], capture_output=True, text=True,
                          env=env, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    check_checkpoint_file(folder)
    checkpoint = read_checkpoint(folder)
    expected = torch.load(weights, weights_only=True)
    assert checkpoint["global_step"] == 3 and set(checkpoint["state_dict"]) == set(expected)
    assert all(torch.equal(checkpoint["state_dict"][k], expected[k]) for k in expected)
