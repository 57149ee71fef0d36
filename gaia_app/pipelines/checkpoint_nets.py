"""Inference nets straight from GAIA-1 training checkpoints, without building their LightningModules.

A training checkpoint holds the model config `train.py` stored and every tensor of the LightningModule. For
inference only the nets matter (the tokenizer without its discriminator, the world model with its text encoder,
the video decoder's EMA weights), so they are built from their own sub-configs, after every `_target_` of the
whole config passed the allow-list (gaia_app/utils/targets.py), and filled from the checkpoint's tensors
(read weights-only, gaia_app/lit/checkpoint.py). No objective, optimiser or frozen loss network is built, and
nothing of the checkpoint is executed. `generate.py mode=export` writes the same nets as shipped weights.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import nn

from gaia_app.lit.checkpoint import model_config, read_checkpoint
from gaia_app.utils.shipped import build

# component → (the LightningModule its checkpoint comes from, {net key of the model config: state-dict prefix})
COMPONENTS = {
    "tokenizer": ("gaia_app.lit.gaia1_tokenizer.ImageTokenizerModule", {"net": "net."}),
    "world_model": ("gaia_app.lit.gaia1_world_model.WorldModelModule", {"net": "net.", "text_encoder": "text_encoder."}),
    # generation samples with the EMA weights (GAIA-1 §4.3); the EMA copy has the net's own names
    "video_decoder": ("gaia_app.lit.gaia1_video_decoder.VideoDecoderModule", {"net": "ema.module."}),
}


def checkpoint_nets(path: str | Path, component: str, role: str,
                    device: str | torch.device = "cpu") -> tuple[dict[str, nn.Module], dict[str, Any]]:
    """({net key: module in eval mode on `device`}, the checked model config) of a `component` checkpoint.

    role: the setting that named the file (tokenizer_ckpt=…), for errors. A checkpoint of another component is a
    TypeError naming both; tensors that do not fit the stored config are a ValueError naming the file.
    """
    checkpoint = read_checkpoint(path, map_location="cpu")
    config = model_config(checkpoint, path)
    module, prefixes = COMPONENTS[component]
    if config.get("_target_") != module:
        held = str(config.get("_target_", "unknown")).rsplit(".", 1)[-1]
        raise TypeError(f"{role}={path} holds a {held} checkpoint, expected a {module.rsplit('.', 1)[-1]}")
    state = checkpoint["state_dict"]
    nets: dict[str, nn.Module] = {}
    for key, prefix in prefixes.items():
        if config.get(key) is None:  # e.g. a world model trained without a text encoder
            continue
        net = build(config[key])
        part = {name[len(prefix):]: value for name, value in state.items() if name.startswith(prefix)}
        try:
            net.load_state_dict(part, strict=True)
        except RuntimeError as error:
            raise ValueError(f"{role}={path}: the tensors under '{prefix}' do not fit the stored model.{key} "
                             f"config ({error})") from None
        nets[key] = net.to(device).eval()
    return nets, config
