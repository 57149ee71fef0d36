"""Rebuild a trained LightningModule from its checkpoint alone (no run dir, no Hydra config needed), safely.

The file is read weights-only and its model config checked against the `_target_` allow-list
(gaia_app/weights/checkpoints.py) before anything is instantiated. Inference does not come here: it builds
the bare nets (gaia_app/weights/nets.py, or shipped weights in gaia_app/weights/folders.py).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import torch

from gaia_app.lit.base import GaiaModule
from gaia_app.weights.checkpoints import (  # noqa: F401
    UnsafeCheckpointError,
    check_checkpoint_file,
    model_config,
    read_checkpoint,
    safe_torch_load,
)
from gaia_app.weights.folders import (
    read_config,
    read_tensors,
    shipped_folder,
    weight_files,
)
from gaia_app.weights.targets import instantiate_checked


def load_module(ckpt_path: str | Path, map_location: str | torch.device = "cpu") -> GaiaModule:
    """Instantiate the module from the `model_cfg` stored by `tasks.train` and load its weights (strict)."""
    ckpt = read_checkpoint(ckpt_path, map_location)
    where = f"checkpoint '{ckpt_path}': hyper_parameters.model_cfg"
    module: GaiaModule = instantiate_checked(model_config(ckpt, ckpt_path), where)
    module.configure_model()
    module.load_state_dict(ckpt["state_dict"], strict=True)
    return module.eval()


def load_net_weights(net: torch.nn.Module, path: str | Path, what: str, prefix: str = "net.",
                     component: str | None = None, fresh: Sequence[str] = (),
                     transform: Callable[[dict[str, torch.Tensor]], dict[str, torch.Tensor]] | None = None) -> None:
    """Copy the `{prefix}*` weights of a training checkpoint into `net`, in place (strict: same architecture).
    what: the checkpoint that `model.init_from` should name, for errors (e.g. "a stage-1 tokenizer checkpoint").
    component: also accept a weights folder (a path, or a shipped name such as "gaia2") holding
    `<component>.safetensors`, whose tensors are named `<net key>.<parameter>` like a checkpoint's (weights/folders.py):
    fine-tuning starts from shipped weights without a training checkpoint.
    fresh: dotted names of `net`'s modules that start as an identity (e.g. a zero-initialised residual refiner): the
    weights may lack them, and then they keep their initialisation; any other missing key is an error.
    transform: maps the weights read to those `net` loads (e.g. widening a tokenizer's latent channels)."""
    weights = initial_weights(path, what, prefix, component)
    if transform is not None:
        weights = transform(weights)
    try:
        missing, unexpected = net.load_state_dict(weights, strict=False)
    except RuntimeError as error:  # tensors of other shapes
        first = str(error).strip().splitlines()[1:2]
        raise ValueError(f"model.init_from='{path}' does not fit model.net: {' '.join(first).strip()} (same preset "
                         "as the run it comes from?)") from None
    missing = [key for key in missing if not any(key.startswith(f"{name}.") for name in fresh)]
    if missing or unexpected:
        raise ValueError(f"model.init_from='{path}' does not fit model.net: missing {missing[:5]}, "
                         f"unexpected {unexpected[:5]} (same preset as the run it comes from?)")


def initial_weights(path: str | Path, what: str, prefix: str, component: str | None) -> dict[str, torch.Tensor]:
    """{parameter: tensor} under `prefix` of a checkpoint file, or of a weights folder's `<component>` tensors."""
    path = Path(path)
    if path.is_file():
        state = read_checkpoint(path).get("state_dict", {})
    elif component is not None:
        state = shipped_tensors(path, component, what)
    else:
        raise FileNotFoundError(f"model.init_from='{path}' does not exist: give {what}")
    weights = {k.removeprefix(prefix): v for k, v in state.items() if k.startswith(prefix)}
    if not weights:
        raise KeyError(f"model.init_from='{path}' holds no '{prefix}*' weights: is it {what}?")
    return weights


def shipped_tensors(path: Path, component: str, what: str) -> dict[str, torch.Tensor]:
    """The tensors of `<component>.safetensors` in the weights folder `path` (a folder, or a name under
    gaia_app/weights), checked against its YAML's component."""
    try:
        folder = shipped_folder(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"model.init_from='{path}' is neither a file nor a weights folder: give {what}, or "
                                f"a weights folder with {component}.safetensors "
                                "(e.g. gaia_app/weights/gaia2)") from None
    weights, config = weight_files(folder, component)
    if read_config(config).get("component") != component:
        raise ValueError(f"model.init_from='{path}': {config.name} is not a {component} component")
    return read_tensors(weights)
