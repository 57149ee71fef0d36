"""DeepSpeed checkpoint folders (trainer=deepspeed_zero2 / deepspeed_zero3_offload), checked and read without
running code.

Lightning's DeepSpeedStrategy saves `checkpoints/last.ckpt/` as DeepSpeed lays it out: a `latest` file naming a tag
folder, `<tag>/mp_rank_00_model_states.pt` (ZeRO-3: `zero_pp_rank_<r>_mp_rank_00_model_states.pt` per rank; the
module's weights, plus Lightning's own entries: hyper-parameters, loops, callbacks) and one `*_optim_states.pt` per
rank. The optimizer files pickle a few small DeepSpeed classes (its static or dynamic loss scaler, the ZeRO stage enum
and a (start, numel) fragment address), and DeepSpeed's own loader unpickles them without torch's weights-only
restriction. Here every file is first unpickled weights-only with only those classes allowed, so a folder that holds
anything else is refused before Lightning hands it to DeepSpeed.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch

from gaia_app.weights.checkpoints import checked_dict, safe_torch_load

log = logging.getLogger(__name__)

LATEST = "latest"  # DeepSpeed's pointer to the newest tag folder
MODEL_STATES = "mp_rank_00_model_states.pt"
ZERO3_MODEL_STATES = "zero_pp_rank_0_mp_rank_00_model_states.pt"  # ZeRO-3: rank 0's file
# DeepSpeed's own entries of the model-states file; the rest is Lightning's checkpoint dict
ENGINE_KEYS = {"module", "buffer_names", "optimizer", "param_shapes", "frozen_param_shapes", "shared_params",
               "frozen_param_fragments", "lr_scheduler", "data_sampler", "random_ltd", "sparse_tensor_module_names",
               "skipped_steps", "global_steps", "global_samples", "dp_world_size", "mp_world_size",
               "checkpoint_parallel_dimensions", "ds_config", "ds_version"}


def is_deepspeed_folder(folder: Path) -> bool:
    return folder.is_dir() and (folder / LATEST).is_file()


def deepspeed_data_classes(folder: Path) -> list[type]:
    """The DeepSpeed classes its optimizer files may hold (nothing callable beyond building them)."""
    try:
        from deepspeed.runtime.fp16.loss_scaler import DynamicLossScaler, LossScaler
        from deepspeed.runtime.zero.config import ZeroStageEnum
        from deepspeed.utils.tensor_fragment import fragment_address
    except ImportError as error:
        raise ValueError(f"checkpoint folder '{folder}' is a DeepSpeed checkpoint; reading it needs deepspeed "
                         f"(pip install -e '.[deepspeed]'): {error}") from None
    return [LossScaler, DynamicLossScaler, ZeroStageEnum, fragment_address]


def tag_folder(folder: Path) -> Path:
    """The folder `latest` names, inside `folder` and holding the model states; errors name the file."""
    tag = (folder / LATEST).read_text().strip()
    if tag in ("", ".", "..") or "/" in tag or "\\" in tag:
        raise ValueError(f"'{folder / LATEST}' names the tag {tag!r}: expected one folder name inside '{folder}'")
    tagged = folder / tag
    if not any((tagged / name).is_file() for name in (MODEL_STATES, ZERO3_MODEL_STATES)):
        raise FileNotFoundError(f"DeepSpeed checkpoint folder '{folder}': '{tagged}' has no {MODEL_STATES} "
                                f"(ZeRO-3: {ZERO3_MODEL_STATES})")
    return tagged


def checkpoint_files(folder: Path) -> list[Path]:
    """The tag folder's `.pt` files; one that resolves outside the checkpoint folder (a link) is refused."""
    root = folder.resolve()
    files = sorted(tag_folder(folder).glob("*.pt"))
    for file in files:
        if not file.resolve().is_relative_to(root):
            raise ValueError(f"DeepSpeed checkpoint file '{file}' points outside its folder '{folder}'")
    return files


def load_deepspeed_file(path: Path, folder: Path, mmap: bool = False) -> dict[str, Any]:
    with torch.serialization.safe_globals(deepspeed_data_classes(folder)):
        return checked_dict(safe_torch_load(path, mmap=mmap), path)


def check_deepspeed_folder(folder: Path) -> None:
    """Before Lightning resumes from a DeepSpeed folder: every file loads weights-only (DeepSpeed's data classes
    alone allowed) and its hyper-parameters are plain data. Memory-mapped: every rank reads every rank's files."""
    for file in checkpoint_files(folder):
        load_deepspeed_file(file, folder, mmap=True)


def read_deepspeed_checkpoint(folder: Path) -> dict[str, Any]:
    """Lightning's checkpoint dict of a ZeRO-1/2 folder, `state_dict` from the module's weights (the LightningModule
    is DeepSpeed's module, so the names are Lightning's; as trained: bf16 under bf16-mixed, with a warning, the fp32
    master copies staying in the optimizer files). ZeRO-3 partitions the weights themselves across ranks: its folder
    is refused, naming Lightning's converter."""
    names = {file.name: file for file in checkpoint_files(folder)}
    if MODEL_STATES not in names:
        raise ValueError(f"DeepSpeed checkpoint folder '{folder}' is ZeRO stage 3 ({ZERO3_MODEL_STATES}), whose "
                         "weights are partitioned across ranks: consolidate it first with lightning.pytorch.utilities."
                         "deepspeed.convert_zero_checkpoint_to_fp32_state_dict(folder, 'model.ckpt')")
    states = load_deepspeed_file(names[MODEL_STATES], folder)
    stage = int((states.get("ds_config") or {}).get("zero_optimization", {}).get("stage", 0))
    if stage >= 3:
        raise ValueError(f"DeepSpeed checkpoint folder '{folder}' is ZeRO stage {stage}, whose weights are "
                         "partitioned across ranks: consolidate it first with lightning.pytorch.utilities."
                         "deepspeed.convert_zero_checkpoint_to_fp32_state_dict(folder, 'model.ckpt')")
    state_dict = states.get("module")
    if not isinstance(state_dict, dict) or not state_dict:
        raise ValueError(f"DeepSpeed checkpoint '{folder}': {MODEL_STATES} holds no module weights")
    low = sorted({str(v.dtype) for v in state_dict.values() if v.dtype in (torch.bfloat16, torch.float16)})
    if low:
        log.warning("DeepSpeed checkpoint '%s': its module weights are %s as trained (the fp32 master copies stay in "
                    "the optimizer files; lightning.pytorch.utilities.deepspeed.convert_zero_checkpoint_to_fp32_"
                    "state_dict writes them out)", folder, "/".join(low))
    return {key: value for key, value in states.items() if key not in ENGINE_KEYS} | {"state_dict": state_dict}
