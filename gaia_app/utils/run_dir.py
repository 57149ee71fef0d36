"""Run-directory helpers: atomic writes and the resolved config of a run."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write `text` to `path` through a temp file in the same folder, so readers never see half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def save_resolved_config(cfg: DictConfig, run_dir: str | Path, name: str = "config_resolved.yaml") -> Path:
    """Write the fully resolved job config (without the hydra node) into the run dir."""
    job = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    path = Path(run_dir) / name
    atomic_write_text(path, OmegaConf.to_yaml(job, resolve=True))
    return path


def atomic_save_npy(path: str | Path, array: np.ndarray) -> None:
    """`np.save` through a temp file in the same folder and `os.replace`: an interrupted write leaves
    the old file (or none), never a truncated one. The temp name does not end in `.npy`, so globs skip it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.save(f, array)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
