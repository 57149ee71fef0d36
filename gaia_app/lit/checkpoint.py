"""Rebuild a trained LightningModule from its checkpoint alone (no run dir, no Hydra needed)."""

from __future__ import annotations

from pathlib import Path

import torch
from hydra.utils import instantiate

from gaia_app.lit.base import GaiaModule


def load_module(ckpt_path: str | Path, map_location: str | torch.device = "cpu") -> GaiaModule:
    """Instantiate the module from the `model_cfg` stored by `tasks.train` and load its weights (strict)."""
    path = Path(ckpt_path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint '{path}' does not exist")
    ckpt = torch.load(path, map_location=map_location, weights_only=False)
    model_cfg = ckpt.get("hyper_parameters", {}).get("model_cfg")
    if model_cfg is None:
        raise KeyError(f"checkpoint '{path}' has no hyper_parameters.model_cfg; was it written by gaia_app's train.py?")
    module: GaiaModule = instantiate(model_cfg)
    module.configure_model()
    module.load_state_dict(ckpt["state_dict"], strict=True)
    return module.eval()
