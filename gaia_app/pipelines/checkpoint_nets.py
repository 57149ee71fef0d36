"""Inference nets straight from GAIA-1 and GAIA-2 training checkpoints, without building their LightningModules.

A training checkpoint holds the model config `train.py` stored and every tensor of the LightningModule. For
inference only the nets matter (the tokenizer without its discriminator, the world model with its text encoder,
the video decoder's EMA weights), so they are built from their own sub-configs and filled from the checkpoint's
tensors (read weights-only, gaia_app/utils/checkpoint_io.py). Every `_target_` of the whole config must name a
path in the allow-list (gaia_app/utils/targets.py), and those of the nets built here must resolve to nets and
encoders of gaia_app (as in shipped weights): the training objective's module is named, never imported. No
objective, optimiser or frozen loss network is built, and nothing of the checkpoint is executed.
`generate.py mode=export` writes the same nets as shipped weights.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import nn

from gaia_app.utils.checkpoint_io import read_checkpoint
from gaia_app.utils.shipped import build
from gaia_app.utils.targets import check_targets
from gaia_app.utils.untrusted import check_finite

# component → (the LightningModule its checkpoint comes from, {net key of the model config: state-dict prefix})
COMPONENTS = {
    "tokenizer": ("gaia_app.lit.gaia1_tokenizer.ImageTokenizerModule", {"net": "net."}),
    "world_model": ("gaia_app.lit.gaia1_world_model.WorldModelModule",
                    {"net": "net.", "text_encoder": "text_encoder."}),
    # generation samples with the EMA weights (GAIA-1 §4.3); the EMA copy has the net's own names
    "video_decoder": ("gaia_app.lit.gaia1_video_decoder.VideoDecoderModule", {"net": "ema.module."}),
    # GAIA-2: the video tokenizer without its discriminator, the latent world model with its caption encoder
    "video_tokenizer": ("gaia_app.lit.gaia2_video_tokenizer.VideoTokenizerModule", {"net": "net."}),
    "latent_world_model": ("gaia_app.lit.gaia2_world_model.LatentWorldModelModule",
                           {"net": "net.", "text_encoder": "text_encoder."}),
}


def checkpoint_nets(path: str | Path, component: str | tuple[str, ...], role: str,
                    device: str | torch.device = "cpu") -> tuple[dict[str, nn.Module], dict[str, Any]]:
    """({net key: module in eval mode on `device`}, the checked model config) of a `component` checkpoint (or of
    any of several; `component_of(config)` says which).

    role: the setting that named the file (tokenizer_ckpt=…), for errors. A checkpoint of another component is a
    TypeError naming both; tensors that do not fit the stored config are a ValueError naming the file.
    """
    checkpoint = read_checkpoint(path, map_location="cpu")
    config = (checkpoint.get("hyper_parameters") or {}).get("model_cfg")
    if config is None:
        raise KeyError(f"checkpoint '{path}' has no hyper_parameters.model_cfg; was it written by gaia_app's train.py?")
    where = f"checkpoint '{path}': hyper_parameters.model_cfg"
    check_targets(config, where, resolve=False)
    wanted = (component,) if isinstance(component, str) else tuple(component)
    found = component_of(config)
    if found not in wanted:
        held = str(config.get("_target_", "unknown")).rsplit(".", 1)[-1]
        expected = " or ".join(COMPONENTS[c][0].rsplit(".", 1)[-1] for c in wanted)
        raise TypeError(f"{role}={path} holds a {held} checkpoint, expected a {expected}")
    _, prefixes = COMPONENTS[found]
    state = checkpoint["state_dict"]
    nets: dict[str, nn.Module] = {}
    for key, prefix in prefixes.items():
        if config.get(key) is None:  # e.g. a world model trained without a text encoder
            continue
        net = build(config[key], f"{where}.{key}")  # nets and encoders of gaia_app only
        part = {name[len(prefix):]: value for name, value in state.items() if name.startswith(prefix)}
        check_finite(part, f"{role}={path}: state_dict under '{prefix}'")
        try:
            net.load_state_dict(part, strict=True)
        except RuntimeError as error:
            raise ValueError(f"{role}={path}: the tensors under '{prefix}' do not fit the stored model.{key} "
                             f"config ({error})") from None
        nets[key] = net.to(device).eval()
    return nets, config


def component_of(config: dict[str, Any]) -> str | None:
    """The component of COMPONENTS whose training module a checkpoint's model config names (None: none of them)."""
    return next((name for name, (module, _) in COMPONENTS.items() if config.get("_target_") == module), None)
