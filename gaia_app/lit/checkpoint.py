"""Rebuild a trained LightningModule from its checkpoint alone (no run dir, no Hydra needed).

A checkpoint is either Lightning's single file or, from a sharded run (trainer=fsdp2 / fsdp with
`save_distributed_checkpoint` / `state_dict_type: sharded`), a folder of per-rank `.distcp` shards plus Lightning's
`meta.pt`; both load on one CPU process.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import torch
from hydra.utils import instantiate

from gaia_app.lit.base import GaiaModule

SHARDED_META = "meta.pt"  # what Lightning writes beside the shards: hyper-parameters, loop state


def read_checkpoint(ckpt_path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The checkpoint dict (`state_dict`, `hyper_parameters`, ...) of a file or of a sharded checkpoint folder."""
    path = Path(ckpt_path)
    if path.is_dir():
        return read_sharded_checkpoint(path, map_location)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint '{path}' does not exist")
    return torch.load(path, map_location=map_location, weights_only=False)


def read_sharded_checkpoint(folder: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Gather a torch.distributed.checkpoint folder into one full state dict, without a process group."""
    from torch.distributed.checkpoint.format_utils import dcp_to_torch_save

    meta = folder / SHARDED_META
    if not meta.is_file() or not any(folder.glob("*.distcp")):
        raise FileNotFoundError(f"checkpoint folder '{folder}' is not a sharded checkpoint: expected *.distcp shards "
                                f"and {SHARDED_META}")
    with tempfile.TemporaryDirectory() as tmp:
        gathered = Path(tmp) / "gathered.pt"
        dcp_to_torch_save(folder, gathered)
        shards = torch.load(gathered, map_location=map_location, weights_only=False)
    checkpoint = torch.load(meta, map_location=map_location, weights_only=False)
    checkpoint["state_dict"] = shards["state_dict"]
    return checkpoint


def load_module(ckpt_path: str | Path, map_location: str | torch.device = "cpu") -> GaiaModule:
    """Instantiate the module from the `model_cfg` stored by `tasks.train` and load its weights (strict)."""
    ckpt = read_checkpoint(ckpt_path, map_location)
    model_cfg = ckpt.get("hyper_parameters", {}).get("model_cfg")
    if model_cfg is None:
        raise KeyError(f"checkpoint '{ckpt_path}' has no hyper_parameters.model_cfg; was it written by gaia_app's "
                       "train.py?")
    module: GaiaModule = instantiate(model_cfg)
    module.configure_model()
    module.load_state_dict(ckpt["state_dict"], strict=True)
    return module.eval()
