"""Reading local checkpoints of frozen networks: clear errors for missing files and mismatched keys.

No download ever happens here (DESIGN.md §6): a checkpoint is a local file or an error that says
which config key points at it and how to switch the loss off.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import torch
from torch import nn

StateDict = dict[str, torch.Tensor]


class StateDictMismatchError(RuntimeError):
    """A checkpoint's keys or shapes do not match the architecture it is loaded into."""


def read_state_dict(checkpoint: str | Path, config_key: str) -> StateDict:
    """Load a tensor-only state dict from `checkpoint` (torch.save format, weights_only).

    Raises FileNotFoundError naming `config_key`, the path, and how to switch the loss off.
    """
    path = Path(checkpoint).expanduser()
    if not path.is_file():
        raise FileNotFoundError(
            f"{config_key}: checkpoint '{path}' does not exist. Put the weights there (see docs/tokenizer.md, "
            f"'Local checkpoints'), point {config_key}.checkpoint at them, or switch the loss off with "
            f"{config_key}=none."
        )
    # weights_only: a checkpoint is data, never code to unpickle
    loaded = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(loaded, Mapping):
        raise ValueError(f"{config_key}: '{path}' holds a {type(loaded).__name__}, not a state dict")
    return dict(loaded)


def load_exact(module: nn.Module, state_dict: Mapping[str, torch.Tensor], source: str) -> None:
    """Strict load that lists every missing and unexpected key (and shape mismatch) in one error."""
    expected = module.state_dict()
    missing = sorted(set(expected) - set(state_dict))
    unexpected = sorted(set(state_dict) - set(expected))
    wrong_shape = sorted(
        f"{k}: checkpoint {tuple(state_dict[k].shape)} vs model {tuple(v.shape)}"
        for k, v in expected.items()
        if k in state_dict and tuple(state_dict[k].shape) != tuple(v.shape)
    )
    if missing or unexpected or wrong_shape:
        raise StateDictMismatchError(
            f"{source} does not match {type(module).__name__}:\n"
            f"  missing keys ({len(missing)}): {missing}\n"
            f"  unexpected keys ({len(unexpected)}): {unexpected}\n"
            f"  shape mismatches ({len(wrong_shape)}): {wrong_shape}"
        )
    module.load_state_dict(state_dict, strict=True)


def freeze(module: nn.Module) -> nn.Module:
    """No gradients, eval mode; returns the module."""
    module.requires_grad_(False)
    return module.eval()
