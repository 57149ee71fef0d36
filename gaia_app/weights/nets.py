"""Inference nets straight from GAIA-1 and GAIA-2 training checkpoints, without building their LightningModules.

A training checkpoint holds the model config `train.py` stored and every tensor of the LightningModule. For
inference only the nets matter (the tokenizer without its discriminator, the world model with its text encoder,
the video decoder's EMA weights), so they are built from their own sub-configs and filled from the checkpoint's
tensors (read weights-only, gaia_app/weights/checkpoints.py), picked by the component and state-dict prefixes the
checkpoint records (`NETS_RECORD`, written by the training module). Every `_target_` of the whole config must name a
path in the allow-list (gaia_app/weights/targets.py), and those of the nets built here must resolve to nets and
encoders of gaia_app (as in shipped weights): the training objective's module is named, never imported. No
objective, optimiser or frozen loss network is built, and nothing of the checkpoint is executed.
`generate.py mode=export` writes the same nets as shipped weights.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch import nn

from gaia_app.utils.untrusted import check_finite
from gaia_app.weights.checkpoints import read_checkpoint
from gaia_app.weights.folders import build, load_exactly
from gaia_app.weights.targets import check_targets

# what a training checkpoint holds for inference, written by the LightningModule at training time
# (gaia_app/lit/base.py, `GaiaModule.on_save_checkpoint`): {"component": one of COMPONENTS,
# "prefixes": {net key of the model config: state-dict prefix}}
NETS_RECORD = "gaia_nets"
COMPONENTS = ("tokenizer", "world_model", "video_decoder", "video_tokenizer", "latent_world_model")
NET_KEYS = ("net", "text_encoder")
# Checkpoints written before the record existed (before 2026-11-28) carry none: the record their training module
# would have written, found by the module the stored config names. New checkpoints never read this table.
LEGACY_RECORDS = {
    "gaia_app.lit.gaia1_tokenizer.ImageTokenizerModule": ("tokenizer", {"net": "net."}),
    "gaia_app.lit.gaia1_world_model.WorldModelModule": ("world_model",
                                                        {"net": "net.", "text_encoder": "text_encoder."}),
    "gaia_app.lit.gaia1_video_decoder.VideoDecoderModule": ("video_decoder", {"net": "ema.module."}),
    "gaia_app.lit.gaia2_video_tokenizer.VideoTokenizerModule": ("video_tokenizer", {"net": "net."}),
    "gaia_app.lit.gaia2_world_model.LatentWorldModelModule": ("latent_world_model",
                                                            {"net": "net.", "text_encoder": "text_encoder."}),
}


class CheckpointNets(NamedTuple):
    """nets: {net key: module in eval mode}; config: the checked model config; component: what the checkpoint holds."""

    nets: dict[str, nn.Module]
    config: dict[str, Any]
    component: str


def nets_record(checkpoint: dict[str, Any], path: str | Path) -> tuple[str, dict[str, str]] | None:
    """(component, {net key: state-dict prefix}) that a checkpoint says it holds, or None (not a gaia_app net)."""
    record = checkpoint.get(NETS_RECORD)
    if record is None:
        config = (checkpoint.get("hyper_parameters") or {}).get("model_cfg") or {}
        return LEGACY_RECORDS.get(config.get("_target_")) if isinstance(config, dict) else None
    component = record.get("component") if isinstance(record, dict) else None
    prefixes = record.get("prefixes") if isinstance(record, dict) else None
    if (component not in COMPONENTS or not isinstance(prefixes, dict) or not prefixes
            or not all(key in NET_KEYS and isinstance(value, str) for key, value in prefixes.items())):
        raise ValueError(f"checkpoint '{path}': {NETS_RECORD}={record!r} is not a record of its nets; expected "
                         f"{{'component': one of {list(COMPONENTS)}, 'prefixes': {{net key in {list(NET_KEYS)}: "
                         "state-dict prefix}}")
    return component, dict(prefixes)


def checkpoint_component(checkpoint: dict[str, Any], path: str | Path) -> str | None:
    """The component a checkpoint dict holds (None: none of COMPONENTS)."""
    record = nets_record(checkpoint, path)
    return None if record is None else record[0]


def held_by(checkpoint: dict[str, Any], path: str | Path) -> str:
    """How an error names what a checkpoint holds: its component and the module that trained it."""
    config = (checkpoint.get("hyper_parameters") or {}).get("model_cfg") or {}
    module = str(config.get("_target_", "unknown")).rsplit(".", 1)[-1] if isinstance(config, dict) else "unknown"
    return f"{checkpoint_component(checkpoint, path) or 'unknown'} ({module})"


def checkpoint_nets(path: str | Path, component: str | tuple[str, ...], role: str,
                    device: str | torch.device = "cpu") -> CheckpointNets:
    """The inference nets of a `component` checkpoint (or of any of several), on `device`, in eval mode.

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
    record = nets_record(checkpoint, path)
    if record is None or record[0] not in wanted:
        raise TypeError(f"{role}={path} holds a {held_by(checkpoint, path)} checkpoint, expected a "
                        f"{' or '.join(wanted)} checkpoint")
    found, prefixes = record
    state = checkpoint["state_dict"]
    nets: dict[str, nn.Module] = {}
    for key, prefix in prefixes.items():
        if config.get(key) is None:  # e.g. a world model trained without a text encoder
            continue
        net = build(config[key], f"{where}.{key}")  # nets and encoders of gaia_app only
        part = {name[len(prefix):]: value for name, value in state.items() if name.startswith(prefix)}
        check_finite(part, f"{role}={path}: state_dict under '{prefix}'")
        load_exactly(net, part, f"{role}={path}: the tensors under '{prefix}' do not fit the stored model.{key} "
                                "config")
        nets[key] = net.to(device).eval()
    return CheckpointNets(nets, config, found)
