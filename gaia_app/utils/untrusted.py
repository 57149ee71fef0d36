"""Data read from files other people wrote (weights YAMLs, checkpoint hyper-parameters): plain data, bounded.

A config from a file is handed to Hydra's `instantiate`, which resolves OmegaConf interpolations before it builds
anything. An interpolation is code: `${oc.create:{_target_: ...}}` makes a new node with a `_target_` *after* the
`_target_` allow-list (gaia_app/weights/targets.py) read the text, and `${oc.env:...}` copies environment variables
(tokens, paths) into net arguments. gaia_app writes every config it stores fully resolved (`tasks.train` saves
`OmegaConf.to_container(cfg.model, resolve=True)`, exports write plain YAML), so a stored config never needs one:
any string holding `${` is refused, in keys and values, at every depth.

Size is bounded too, before anything is built: a YAML file of at most MAX_YAML_BYTES, no anchors or aliases
(a sub-kilobyte alias bomb expands to millions of nodes), nesting at most MAX_DEPTH deep and at most MAX_NODES
nodes (a 50k-deep list would otherwise end in a bare RecursionError).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
import yaml

MAX_YAML_BYTES = 1 << 20
MAX_DEPTH = 48
MAX_NODES = 200_000
# the plain types a stored config may hold (checkpoints are unpickled weights-only, so nothing else arrives there)
SCALARS = (str, int, float, bool, type(None), bytes)


class UntrustedDataError(ValueError):
    """A config or checkpoint from a file holds an interpolation, an alias, or exceeds the size bounds."""


def read_untrusted_yaml(path: Path, max_bytes: int = MAX_YAML_BYTES) -> Any:
    """`yaml.safe_load` of `path` after checking its size, anchors/aliases and nesting on the event stream (the
    parser keeps an explicit stack, so a deep file cannot exhaust Python's); the result is checked by `check_plain`."""
    size = path.stat().st_size
    if size > max_bytes:
        raise UntrustedDataError(f"{path}: {size} bytes, more than the {max_bytes} a config file may have")
    text = path.read_text()
    depth = nodes = 0
    try:
        for event in yaml.parse(text, Loader=yaml.SafeLoader):
            if isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None) is not None:
                raise UntrustedDataError(f"{path}: line {event.start_mark.line + 1}: YAML anchors and aliases are "
                                         "refused in a config file (an alias bomb expands to millions of nodes)")
            if isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
                depth += 1
                if depth > MAX_DEPTH:
                    raise UntrustedDataError(f"{path}: line {event.start_mark.line + 1}: nested more than "
                                             f"{MAX_DEPTH} levels deep")
            elif isinstance(event, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
                depth -= 1
            nodes += isinstance(event, (yaml.ScalarEvent, yaml.MappingStartEvent, yaml.SequenceStartEvent))
            if nodes > MAX_NODES:
                raise UntrustedDataError(f"{path}: more than {MAX_NODES} values")
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise ValueError(f"{path}: not readable YAML ({error})") from error
    check_plain(data, str(path))
    return data


class NoAliasDumper(yaml.SafeDumper):
    """Writes a shared object out in full each time: files gaia_app writes pass `read_untrusted_yaml`."""

    def ignore_aliases(self, data: Any) -> bool:
        return True


def dump_plain_yaml(data: Any) -> str:
    """YAML text of plain `data`, in key order, without anchors or aliases."""
    return yaml.dump(data, Dumper=NoAliasDumper, sort_keys=False)


def check_plain(node: Any, where: str, max_depth: int = MAX_DEPTH, max_nodes: int = MAX_NODES) -> None:
    """Raise UntrustedDataError naming `where` and the key path if `node` holds an OmegaConf interpolation (`${`
    in any key or string), a type other than containers, scalars and tensors, more than `max_depth` levels or
    `max_nodes` values. Walks with an explicit stack: no recursion, whatever the input."""
    stack: list[tuple[Any, str, int]] = [(node, where, 0)]
    seen = 0
    while stack:
        value, path, depth = stack.pop()
        seen += 1
        if seen > max_nodes:
            raise UntrustedDataError(f"{where}: more than {max_nodes} values")
        if depth > max_depth:
            raise UntrustedDataError(f"{path}: nested more than {max_depth} levels deep")
        if isinstance(value, Mapping):
            for key, item in value.items():
                check_scalar(key, f"{path}: key {key!r}")
                stack.append((item, f"{path}.{key}", depth + 1))
        elif isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
            stack.extend((item, f"{path}[{i}]", depth + 1) for i, item in enumerate(value))
        elif not isinstance(value, torch.Tensor):
            check_scalar(value, path)


def check_scalar(value: Any, where: str) -> None:
    if not isinstance(value, SCALARS):
        raise UntrustedDataError(f"{where}: a {type(value).__name__} where a stored config holds plain data only")
    if isinstance(value, str) and "${" in value:
        raise UntrustedDataError(
            f"{where}: {value[:80]!r} is an OmegaConf interpolation; a config read from a file is refused when it "
            "holds one, since resolving it can build objects or read the environment (gaia_app stores configs "
            "resolved, so a genuine file has none)")


def check_finite(tensors: Mapping[str, torch.Tensor], where: str) -> None:
    """Raise UntrustedDataError naming `where` and the first tensors holding NaN or ±inf: weights like that give a
    black video or a NaN-probability traceback far from the file that caused it."""
    bad = [name for name, value in tensors.items()
           if isinstance(value, torch.Tensor) and value.is_floating_point() and not bool(torch.isfinite(value).all())]
    if bad:
        raise UntrustedDataError(f"{where}: tensor {bad[0]!r} holds NaN or infinite values"
                                 + (f" (and {len(bad) - 1} more: {bad[1:4]})" if len(bad) > 1 else "")
                                 + "; the weights are damaged: use another checkpoint or export them again")
