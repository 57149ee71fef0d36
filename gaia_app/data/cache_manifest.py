"""Cache manifests: what a token or latent cache folder holds, checked before more is written into it.

`generate.py mode=tokenize` / `mode=encode` skip clips already in their output folder, so a folder can be
filled over several runs. Rerun with another tokenizer, frame rate or frame size, the skipped clips would keep
the old tokens and the new ones would mix in: a stale or mixed cache that trains without complaint. Each cache
folder therefore holds `cache.json`:

    {"format": 2, "kind": "gaia1_tokens", "tokenizer_sha256": "…", "fps": 6.25, "image_size": [64, 112], …}

and a run refuses a folder whose manifest differs from its own (or that holds cache files but no manifest,
written before manifests existed), naming each differing field, unless `overwrite=true` empties it first.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from gaia_app.data.clip import ClipError
from gaia_app.utils.locks import content
from gaia_app.utils.run_dir import atomic_write_text

MANIFEST = "cache.json"
FORMAT = 2  # 1: flat `<clip>_<camera>.npy` token files without a manifest; 2: `<clip>/<camera>.npy` + cache.json


def weights_sha256(net: nn.Module) -> str:
    """SHA-256 of a net's state dict (names, dtypes, shapes and values): which tokenizer made a cache."""
    digest = hashlib.sha256()
    for name, value in sorted(net.state_dict().items()):
        tensor = value.detach().cpu().contiguous()
        digest.update(f"{name}:{tensor.dtype}:{tuple(tensor.shape)}".encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
    return digest.hexdigest()


def cache_manifest(kind: str, **fields: Any) -> dict[str, Any]:
    """The manifest of a cache made by `kind` with `fields` (JSON values: hashes, rates, sizes)."""
    return json.loads(json.dumps({"format": FORMAT, "kind": kind, **fields}))


def prepare_cache(folder: str | Path, manifest: Mapping[str, Any], overwrite: bool = False) -> None:
    """Make `folder` ready to receive the cache described by `manifest`: a new or empty folder gets the manifest;
    a folder with the same manifest is kept (the run resumes it); any other content is refused (ClipError naming
    the folder and each differing field) unless `overwrite`, which empties the folder first. The caller holds the
    folder's lock (`gaia_app.utils.locks.folder_lock`) from here until its last file is written, so two runs cannot
    both accept one folder."""
    folder = Path(folder)
    found = read_manifest(folder)
    if found == dict(manifest):
        return
    if content(folder):
        if not overwrite:
            raise ClipError(f"{folder}: {describe_mismatch(found, manifest)}; write to another out_dir, or pass "
                            "overwrite=true to empty this one and start again")
        for entry in content(folder):  # the lock file stays: the caller holds it
            shutil.rmtree(entry) if entry.is_dir() and not entry.is_symlink() else entry.unlink()
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(folder / MANIFEST, json.dumps(dict(manifest), indent=2))


def read_manifest(folder: Path) -> dict[str, Any] | None:
    path = folder / MANIFEST
    if not path.is_file():
        return None
    try:
        found = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ClipError(f"{path}: not readable JSON ({error}); pass overwrite=true to rebuild the cache") from None
    if not isinstance(found, dict):
        raise ClipError(f"{path}: expected a JSON object; pass overwrite=true to rebuild the cache")
    return found


def describe_mismatch(found: Mapping[str, Any] | None, wanted: Mapping[str, Any]) -> str:
    if found is None:
        return (f"holds files but no {MANIFEST} (a cache written before manifests, or other files), so what "
                "made them is unknown")
    fields = sorted(set(found) | set(wanted))
    changed = [f"{key}: cache has {found.get(key)!r}, this run makes {wanted.get(key)!r}"
               for key in fields if found.get(key) != wanted.get(key)]
    return "holds a cache made differently (" + "; ".join(changed) + ")"
