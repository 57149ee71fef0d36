"""Shipped reference weights: inference nets rebuilt from `.safetensors` + `.yaml` alone (DESIGN.md layout).

`gaia_app/weights/<family>/<component>.safetensors` holds the tensors of the nets inference needs (no optimiser,
no discriminator); `<component>.yaml` holds how to build them:

    format: 1
    component: world_model
    dtype: float16                 # storage type; nets are rebuilt in float32
    nets: {net: {_target_: gaia_app.models..., _partial_: true, ...}, text_encoder: {...}}
    info: {image_size: [64, 112], rate: 6.25, ...}

Tensors are named `<net>.<parameter>`. Nothing is unpickled, and a YAML may only build nets and encoders of gaia_app
(gaia_app/weights/targets.py), so a weights folder from elsewhere cannot run code on load. `export_component` writes
both files from a training checkpoint of this project; `load_nets` reads them back.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf
from torch import nn

from gaia_app.utils.run_dir import atomic_write_bytes, atomic_write_text
from gaia_app.utils.untrusted import check_finite, dump_plain_yaml, read_untrusted_yaml
from gaia_app.weights.targets import UnsafeTargetError, check_targets, instantiate_checked

WEIGHTS_ROOT = Path(__file__).resolve().parent
FORMAT = 1
STORAGE_TYPES = {"float16": torch.float16, "float32": torch.float32}
# shipped weights hold nets only: their YAML may build nets and text encoders, nothing else
SHIPPED_TARGETS = ("gaia_app.models.", "gaia_app.nn.", "gaia_app.encoders.")


def shipped_folder(name: str | Path) -> Path:
    """A weights folder: an existing path, else `gaia_app/weights/<name>` (e.g. "gaia1")."""
    path = Path(name)
    if path.is_dir():
        return path
    if (WEIGHTS_ROOT / str(name)).is_dir():
        return WEIGHTS_ROOT / str(name)
    shipped = sorted(p.name for p in WEIGHTS_ROOT.iterdir() if p.is_dir()) if WEIGHTS_ROOT.is_dir() else []
    raise FileNotFoundError(f"weights={name}: no such folder, and gaia_app/weights has {shipped or 'no weights'}; "
                            "restore it with `git checkout -- gaia_app/weights` or rebuild it with `make reproduce`")


def weight_files(folder: str | Path, component: str) -> tuple[Path, Path]:
    """(`<component>.safetensors`, `<component>.yaml`) in `folder`."""
    folder = Path(folder)
    return folder / f"{component}.safetensors", folder / f"{component}.yaml"


def restore_hint(path: Path) -> str:
    inside = WEIGHTS_ROOT in path.resolve().parents
    return ("restore it with `git checkout -- gaia_app/weights` (or reinstall gaia_app), or rebuild the weights "
            "with `make reproduce`") if inside else "export it again with `python generate.py mode=export`"


def export_component(checkpoint: Mapping[str, Any], folder: str | Path, component: str, nets: Sequence[str],
                     info: Mapping[str, Any], dtype: str = "float16",
                     prefixes: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Write `<component>.safetensors` + `.yaml` from a training checkpoint dict (`state_dict`, `hyper_parameters`).

    nets: keys of the module config (`model_cfg.<key>`) whose nets inference needs; their tensors are the state
    dict entries under `<key>.`, or under `prefixes[key]` (e.g. the video decoder's EMA copy, "ema.module."), stored
    as `<key>.`. Returns {"parameters": count, "bytes": size of the safetensors file}.
    """
    from safetensors.torch import save as save_tensors

    if dtype not in STORAGE_TYPES:
        raise ValueError(f"dtype: expected one of {sorted(STORAGE_TYPES)}, got {dtype!r}")
    model_cfg = checkpoint.get("hyper_parameters", {}).get("model_cfg")
    if model_cfg is None:
        raise KeyError("checkpoint has no hyper_parameters.model_cfg; was it written by gaia_app's train.py?")
    model_cfg = OmegaConf.create(model_cfg)
    state: dict[str, torch.Tensor] = {}
    configs: dict[str, Any] = {}
    for key in nets:
        if model_cfg.get(key) is None:
            raise KeyError(f"checkpoint's model_cfg has no '{key}' net to export")
        configs[key] = OmegaConf.to_container(model_cfg[key], resolve=True)
        prefix = (prefixes or {}).get(key, f"{key}.")
        part = {f"{key}.{name[len(prefix):]}": value for name, value in checkpoint["state_dict"].items()
                if name.startswith(prefix)}
        if not part and build(configs[key], f"model_cfg.{key}").state_dict():
            # a net with no tensors of its own (a frozen text encoder that loads its weights from its package)
            # is exported as its config alone; any other net must have its tensors in the checkpoint
            raise KeyError(f"checkpoint's state_dict has no tensors under '{prefix}'")
        state.update({name: stored(value, STORAGE_TYPES[dtype]) for name, value in part.items()})
    data = save_tensors(state)
    weights, config = weight_files(folder, component)
    atomic_write_bytes(weights, data)
    atomic_write_text(config, dump_plain_yaml({"format": FORMAT, "component": component, "dtype": dtype,
                                               "nets": configs, "info": dict(info)}))
    return {"parameters": sum(v.numel() for v in state.values()), "bytes": len(data)}


def stored(value: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Floating tensors in the storage type, others (integer buffers) as they are; contiguous, detached, and a copy
    of their own: tied weights (a token embedding shared with the head) would otherwise share memory, which
    safetensors refuses to write (float16 storage made the copy by itself, float32 did not)."""
    value = value.detach().cpu()
    return (value.to(dtype) if value.is_floating_point() else value).contiguous().clone()


def read_config(path: Path) -> dict[str, Any]:
    """The component YAML, checked: bounded plain data without interpolations (utils/untrusted.py), format, nets
    that build gaia_app classes only."""
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: {restore_hint(path)}")
    try:
        config = read_untrusted_yaml(path)
    except ValueError as error:  # unreadable, too large, an alias or an interpolation
        raise ValueError(f"{error}; {restore_hint(path)}") from None
    if not isinstance(config, dict) or config.get("format") != FORMAT or not isinstance(config.get("nets"), dict):
        raise ValueError(f"{path}: expected a weights config of format {FORMAT} with a 'nets' mapping; "
                         f"{restore_hint(path)}")
    for name, net in config["nets"].items():
        try:
            check_targets(net, f"{path}: nets.{name}", SHIPPED_TARGETS)
        except UnsafeTargetError as error:
            raise ValueError(f"{error}; {restore_hint(path)}") from None
    return config


def read_tensors(path: Path) -> dict[str, torch.Tensor]:
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: {restore_hint(path)}")
    try:
        tensors = load_file(str(path))
    except (SafetensorError, OSError) as error:
        raise ValueError(f"{path}: not a readable safetensors file ({error}); {restore_hint(path)}") from error
    check_finite(tensors, str(path))
    return tensors


def build(config: Any, where: str = "net config") -> nn.Module:
    """A net from its Hydra config (a `_partial_` factory, as the training configs write them, or the class), checked
    first: plain data, nets and encoders of gaia_app only (`instantiate_checked`)."""
    made = instantiate_checked(config, where, SHIPPED_TARGETS)
    if isinstance(made, functools.partial):
        check_arguments(made, where)
    return made() if callable(made) and not isinstance(made, nn.Module) else made


def check_arguments(factory: functools.partial, where: str) -> None:
    """Every key of a net's config must be an argument of its class: a YAML that asks for a conditioning path the net
    does not have (e.g. `agent_raster` on a GAIA-1 world model) is refused by that key, not by a TypeError."""
    parameters = inspect.signature(factory.func).parameters
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        return
    unknown = sorted(set(factory.keywords) - set(parameters))
    if unknown:
        raise ValueError(f"{where}.{unknown[0]}: {factory.func.__name__} has no argument '{unknown[0]}' (a "
                         f"conditioning path or setting this net does not have); it takes {sorted(parameters)}")


def load_exactly(net: nn.Module, tensors: Mapping[str, torch.Tensor], where: str, hint: str = "") -> None:
    """Fill `net` with `tensors`, every parameter and buffer and nothing else (strict); a mismatch is a ValueError
    `<where> (<what does not fit>)<hint>`. Both loaders (weights folders, training checkpoints) fill nets this way."""
    try:
        net.load_state_dict(dict(tensors), strict=True)
    except RuntimeError as error:
        raise ValueError(f"{where} ({error}){hint}") from None


def load_nets(folder: str | Path, component: str,
              device: str | torch.device = "cpu") -> tuple[dict[str, nn.Module], dict]:
    """({net key: float32 module in eval mode}, info) of a component written by `export_component`, from a folder
    or a shipped name (e.g. "gaia1", `shipped_folder`)."""
    weights, config_path = weight_files(shipped_folder(folder), component)
    config = read_config(config_path)
    state = read_tensors(weights)
    nets: dict[str, nn.Module] = {}
    for key, net_config in config["nets"].items():
        net = build(net_config, f"{config_path}: nets.{key}")
        part = {name[len(key) + 1:]: value for name, value in state.items() if name.startswith(f"{key}.")}
        load_exactly(net, part, f"{weights}: the tensors of '{key}' do not fit the net of {config_path.name}",
                     f"; {restore_hint(weights)}")
        nets[key] = net.float().to(device).eval()
    return nets, dict(config.get("info") or {})
