"""Which Hydra `_target_`s a config read from a file (checkpoint, weights YAML) may build.

A training checkpoint stores its model config, and loading it calls `hydra.utils.instantiate` on that config:
whatever a `_target_` names is called. Checkpoints travel between users, so a config from a file may only name
classes and functions of the packages that define models, objectives and optimisers. Two checks per target:
1. the dotted path starts with an allowed package (nothing else is imported, so no foreign module's code runs);
2. the object it resolves to is defined inside an allowed package: `gaia_app.models.gaia1.world_model.torch.load`
   starts like an allowed path but resolves to `torch.load`, defined in `torch.serialization`, and is refused.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

# packages whose classes and functions a model config from a file may build: nets, objectives, encoders, samplers,
# optimisers and schedules. Not gaia_app.tasks / pipelines / utils / data / viz, which write files.
MODEL_TARGETS = ("gaia_app.lit.", "gaia_app.models.", "gaia_app.nn.", "gaia_app.encoders.", "gaia_app.diffusion.",
                 "torch.optim.")
# what a stored video decoder's sampler and noise schedule may build
DIFFUSION_TARGETS = ("gaia_app.diffusion.",)


def instantiate_checked(node: Any, where: str, allowed: Sequence[str] = MODEL_TARGETS) -> Any:
    """`hydra.utils.instantiate(node)` of a config read from a file, after checking that it is bounded plain data
    without interpolations (utils/untrusted.py) and that every `_target_` resolves inside `allowed`: the one way a
    stored config is built."""
    from hydra.utils import instantiate

    from gaia_app.utils.untrusted import check_plain

    check_plain(node, where)
    check_targets(node, where, allowed)
    return instantiate(node)


class UnsafeTargetError(ValueError):
    """A config from a file names a `_target_` outside the allowed packages."""


def check_targets(node: Any, where: str, allowed: Sequence[str] = MODEL_TARGETS, resolve: bool = True) -> None:
    """Raise UnsafeTargetError (naming `where` and the key path) if any `_target_` at any depth of `node` (plain
    dicts and lists, or OmegaConf containers) is not a class or function defined inside an `allowed` package.
    resolve=False checks the dotted paths only and imports nothing (for parts of a config that will not be built)."""
    if isinstance(node, Mapping):
        if "_target_" in node:
            check_target(node["_target_"], f"{where}._target_", allowed, resolve)
        for key, value in node.items():
            check_targets(value, f"{where}.{key}", allowed, resolve)
    elif isinstance(node, Sequence) and not isinstance(node, (str, bytes)):
        for i, value in enumerate(node):
            check_targets(value, f"{where}[{i}]", allowed, resolve)


def check_target(target: Any, where: str, allowed: Sequence[str] = MODEL_TARGETS, resolve: bool = True) -> None:
    """One `_target_` value: a dotted path into an allowed package, resolving to a class or function defined there
    (resolve=False: the path alone)."""
    from hydra._internal.utils import _locate

    prefixes = tuple(allowed)
    refused = f"{where}: _target_ {target!r} is refused: a config read from a file may only build classes and " \
              f"functions of {', '.join(p.rstrip('.') for p in prefixes)}"
    if not isinstance(target, str) or not target.startswith(prefixes):
        raise UnsafeTargetError(refused)
    if not resolve:
        return
    try:
        obj = _locate(target)
    except ImportError as error:
        raise UnsafeTargetError(f"{where}: _target_ {target!r} does not exist ({error})") from None
    defined_in = getattr(obj, "__module__", None)
    if not callable(obj) or not isinstance(defined_in, str) or not f"{defined_in}.".startswith(prefixes):
        raise UnsafeTargetError(f"{refused} (it resolves to {defined_in}.{getattr(obj, '__qualname__', obj)!s})")
