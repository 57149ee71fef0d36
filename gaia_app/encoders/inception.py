"""Frozen Inception-v3 pool3 features for FID, from a local checkpoint (DESIGN.md §6: nothing is downloaded).

Accepts torchvision's `inception_v3` state dict or the FID reference weights pytorch-fid distributes
(`pt_inception-2015-12-05-*.pth`); their classifier (`fc.*`) and auxiliary head (`AuxLogits.*`) are dropped.
"""

from __future__ import annotations

from pathlib import Path

from gaia_app.encoders.checkpoints import StateDict, freeze, load_exact, read_state_dict
from gaia_app.nn.inception import InceptionV3Features


def inception_trunk_state_dict(state: StateDict) -> StateDict:
    """Drop the classifier and the auxiliary head, which FID does not use."""
    return {k: v for k, v in state.items() if not k.startswith(("fc.", "AuxLogits."))}


def load_inception(checkpoint: str | Path, config_key: str = "eval.fid",
                   fid_variant: bool = True) -> InceptionV3Features:
    """The Inception-v3 trunk with weights from `checkpoint`; frozen, eval mode. fid_variant: the reference FID
    network's pooling (gaia_app/nn/inception.py); False for plain torchvision ImageNet weights.
    Raises FileNotFoundError naming `config_key` and the path, or StateDictMismatchError listing bad keys."""
    trunk = InceptionV3Features(fid_variant=fid_variant)
    state = inception_trunk_state_dict(read_state_dict(checkpoint, config_key))
    load_exact(trunk, state, f"{config_key} '{checkpoint}'")
    return freeze(trunk)
