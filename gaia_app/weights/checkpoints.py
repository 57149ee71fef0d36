"""Read training checkpoints safely, without Lightning: what inference and export need of a checkpoint.

A checkpoint is either Lightning's single file or, from a sharded run (trainer=fsdp2 / fsdp with
`save_distributed_checkpoint` / `state_dict_type: sharded`), a folder of per-rank `.distcp` shards plus Lightning's
`meta.pt`, or a DeepSpeed folder (trainer=deepspeed_zero2; `deepspeed_folders.py`); all load on one CPU process.

Checkpoints travel between users, so loading one must never run code: every file is unpickled with
`weights_only=True` (tensors and plain containers only), the shards' `.metadata` pickle by an unpickler that
builds only torch.distributed.checkpoint's metadata types, and the stored model config is returned only after
every `_target_` in it passed `gaia_app.weights.targets.check_targets`. Rebuilding a LightningModule from it
(training resume, reports) is `gaia_app.lit.checkpoint.load_module`.
"""

from __future__ import annotations

import pickle
import re
from pathlib import Path
from typing import Any

import torch

from gaia_app.utils.untrusted import check_plain
from gaia_app.weights.targets import check_targets

SHARDED_META = "meta.pt"  # what Lightning writes beside the shards: hyper-parameters, loop state
DCP_METADATA = ".metadata"  # torch.distributed.checkpoint's index of the shards, a pickle


class UnsafeCheckpointError(ValueError):
    """A checkpoint file holds something other than tensors and plain data."""


def safe_torch_load(path: Path, map_location: str | torch.device = "cpu", mmap: bool = False) -> Any:
    """torch.load with weights_only=True; errors name the file: refused content, truncated or foreign files."""
    try:
        return torch.load(path, map_location=map_location, weights_only=True, mmap=mmap)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, ValueError) as error:
        found = re.search(r"Unsupported global: GLOBAL (\S+)", str(error))
        if found:
            raise UnsafeCheckpointError(
                f"checkpoint '{path}' was refused: it holds objects other than tensors and plain data, which could "
                f"run code when loaded (unsupported global {found.group(1)}); only load checkpoints written by "
                "gaia_app's train.py, from a source you trust") from None
        first_line = str(error).strip().splitlines()[0][:200] if str(error).strip() else ""
        raise ValueError(f"checkpoint '{path}' is empty, truncated or not a PyTorch checkpoint "
                         f"({type(error).__name__}: {first_line}); use another checkpoint of the run, e.g. its "
                         "checkpoints/last.ckpt, or train again") from None


def read_checkpoint(ckpt_path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The checkpoint dict (`state_dict`, `hyper_parameters`, ...) of a file, of a sharded checkpoint folder or of
    a DeepSpeed ZeRO-1/2 folder."""
    from gaia_app.weights import deepspeed_folders  # it imports this module

    path = Path(ckpt_path)
    if deepspeed_folders.is_deepspeed_folder(path):
        checkpoint = deepspeed_folders.read_deepspeed_checkpoint(path)
        checkpoint["state_dict"] = {name: value.to(map_location) for name, value in checkpoint["state_dict"].items()}
        return checkpoint
    if path.is_dir():
        return read_sharded_checkpoint(path, map_location)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint '{path}' does not exist")
    return checked_dict(safe_torch_load(path, map_location), path)


def check_checkpoint_file(ckpt_path: str | Path) -> None:
    """Before Lightning resumes from `ckpt_path`: a file that loads safely (memory-mapped, nothing copied); a sharded
    folder whose index is safe; a DeepSpeed folder whose files load weights-only. Raises the errors of
    `read_checkpoint`."""
    from gaia_app.weights import deepspeed_folders  # it imports this module

    path = Path(ckpt_path)
    if deepspeed_folders.is_deepspeed_folder(path):
        deepspeed_folders.check_deepspeed_folder(path)
    elif path.is_dir():
        check_dcp_metadata(path)
        checked_dict(safe_torch_load(path / SHARDED_META), path / SHARDED_META)
    else:
        checked_dict(safe_torch_load(path, mmap=True), path)


def checked_dict(checkpoint: Any, path: Path) -> dict[str, Any]:
    """The checkpoint dict, its hyper-parameters (the module's and the data module's, at every depth) plain data
    without interpolations (utils/untrusted.py): they are what `instantiate` builds from."""
    if not isinstance(checkpoint, dict):
        raise ValueError(f"checkpoint '{path}' holds a {type(checkpoint).__name__}, expected Lightning's checkpoint "
                         "dict (state_dict, hyper_parameters, ...)")
    for key, value in checkpoint.items():
        if isinstance(key, str) and key.endswith("hyper_parameters"):
            check_plain(value, f"checkpoint '{path}': {key}")
    return checkpoint


class DcpMetadataUnpickler(pickle.Unpickler):
    """Builds only the dataclasses of torch.distributed.checkpoint's index (and torch.Size / dtypes / containers)."""

    SAFE = {("torch", "Size"), ("collections", "OrderedDict"), ("builtins", "set"), ("builtins", "frozenset"),
            ("builtins", "slice"), ("torch.serialization", "_get_layout"),
            # the checkpoint id of StorageMeta: a path, built as data
            ("pathlib", "PosixPath"), ("pathlib", "PurePosixPath"), ("pathlib", "WindowsPath"),
            ("pathlib", "PureWindowsPath")}

    def find_class(self, module: str, name: str) -> Any:
        dtype = module == "torch" and isinstance(getattr(torch, name, None), (torch.dtype, torch.layout,
                                                                            torch.memory_format))
        if module.startswith("torch.distributed.checkpoint.") or (module, name) in self.SAFE or dtype:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"Unsupported global: {module}.{name}")


def load_dcp_metadata(folder: Path) -> Any:
    """torch.distributed.checkpoint's index of a shard folder, unpickled by `DcpMetadataUnpickler`, with every file
    it names checked to lie inside the folder (an index is free to name `../../etc/passwd`)."""
    index = folder / DCP_METADATA
    if not index.is_file():
        raise FileNotFoundError(f"checkpoint folder '{folder}' has no {DCP_METADATA} index of its shards")
    try:
        with index.open("rb") as f:
            metadata = DcpMetadataUnpickler(f).load()
    except pickle.UnpicklingError as error:
        raise UnsafeCheckpointError(f"checkpoint index '{index}' was refused: it holds objects other than "
                                    f"torch.distributed.checkpoint metadata ({error})") from None
    except (EOFError, ValueError, TypeError, AttributeError) as error:
        raise ValueError(f"checkpoint index '{index}' is truncated or damaged "
                         f"({type(error).__name__}: {error})") from None
    if not isinstance(getattr(metadata, "state_dict_metadata", None), dict) or \
            not isinstance(getattr(metadata, "storage_data", None), dict):
        raise ValueError(f"checkpoint index '{index}' is not a torch.distributed.checkpoint index")
    root = folder.resolve()
    for item in metadata.storage_data.values():
        file = (folder / str(getattr(item, "relative_path", ""))).resolve()
        if root not in file.parents or not file.is_file():
            raise UnsafeCheckpointError(f"checkpoint index '{index}' was refused: it names "
                                        f"{getattr(item, 'relative_path', item)!r}, which is not a file inside "
                                        f"'{folder}'")
    return metadata


def check_dcp_metadata(folder: Path) -> Any:
    """Before torch.distributed.checkpoint (Lightning's resume) reads a shard folder: its index is safe, every file
    it names lies inside the folder, and every non-tensor entry of the shards is plain data (torch's own reader
    unpickles those entries without the weights-only restriction, so they are read here weights-only first)."""
    metadata = load_dcp_metadata(folder)
    entries = [fqn for fqn, meta in metadata.state_dict_metadata.items() if not hasattr(meta, "chunks")]
    if entries:
        read_dcp_entries(folder, entries, keep=False)
    return metadata


def read_dcp_entries(folder: Path, fqns: list[str], keep: bool = True) -> dict[str, Any]:
    """The shard entries named by `fqns` (flattened names), nested as they were saved ({"model": {name: tensor}});
    tensors as they are, other entries unpickled weights-only (plain data; anything else is refused naming the
    entry). keep=False reads and checks without keeping."""
    from torch.distributed.checkpoint._traverse import set_element
    from torch.distributed.checkpoint.default_planner import _EmptyStateDictLoadPlanner
    from torch.distributed.checkpoint.filesystem import FileSystemReader
    from torch.distributed.checkpoint.state_dict_loader import _load_state_dict

    class SafeReader(FileSystemReader):
        def read_metadata(self, *args: Any, **kwargs: Any) -> Any:
            return load_dcp_metadata(folder)

    refused: list[str] = []

    class SafePlanner(_EmptyStateDictLoadPlanner):
        def load_bytes(self, read_item: Any, value: Any) -> None:
            fqn = read_item.dest_index.fqn
            try:
                loaded = torch.load(value, weights_only=True)
            except pickle.UnpicklingError as error:  # kept, raised after torch's loop (which wraps what it raises)
                found = re.search(r"GLOBAL (\S+)", str(error))
                refused.append(f"'{fqn}' (unsupported global {found.group(1) if found else error})")
                return
            if keep:
                set_element(self.original_state_dict, self.mappings[fqn], loaded)

    state: dict[str, Any] = {}
    _load_state_dict(state, storage_reader=SafeReader(folder), planner=SafePlanner(keys=set(fqns)),
                     no_dist=True)
    if refused:
        raise UnsafeCheckpointError(f"checkpoint folder '{folder}' was refused: shard entries holding objects other "
                                    f"than tensors and plain data, which could run code when loaded: "
                                    f"{', '.join(refused)}")
    return state


def read_sharded_checkpoint(folder: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Gather a torch.distributed.checkpoint folder into one full state dict, without a process group: its tensors
    only, through the safe index (`load_dcp_metadata`)."""
    meta = folder / SHARDED_META
    if not meta.is_file() or not any(folder.glob("*.distcp")):
        raise FileNotFoundError(f"checkpoint folder '{folder}' is not a sharded checkpoint: expected *.distcp shards "
                                f"and {SHARDED_META}")
    metadata = check_dcp_metadata(folder)
    checkpoint = checked_dict(safe_torch_load(meta, map_location), meta)
    # Lightning's ModelParallelStrategy (fsdp2) saves the weights under "state_dict", its FSDPStrategy under "model"
    found = sorted({fqn.split(".", 1)[0] for fqn in metadata.state_dict_metadata})
    weights_key = next((key for key in ("state_dict", "model") if key in found), None)
    if weights_key is None:
        raise KeyError(f"checkpoint folder '{folder}' holds no weights: expected a 'state_dict' (fsdp2) or 'model' "
                       f"(fsdp) entry in its shards, found {found}")
    tensors = [fqn for fqn, item in metadata.state_dict_metadata.items()
               if fqn.startswith(f"{weights_key}.") and hasattr(item, "chunks")]
    weights = read_dcp_entries(folder, tensors)[weights_key]
    checkpoint["state_dict"] = {name: value.to(map_location) for name, value in weights.items()}
    return checkpoint


def model_config(checkpoint: dict[str, Any], ckpt_path: str | Path) -> dict[str, Any]:
    """The `model_cfg` that `tasks.train` stored in the checkpoint, with every `_target_` checked (none built yet)."""
    model_cfg = (checkpoint.get("hyper_parameters") or {}).get("model_cfg")
    if model_cfg is None:
        raise KeyError(f"checkpoint '{ckpt_path}' has no hyper_parameters.model_cfg; was it written by gaia_app's "
                       "train.py?")
    check_targets(model_cfg, f"checkpoint '{ckpt_path}': hyper_parameters.model_cfg")
    return model_cfg
