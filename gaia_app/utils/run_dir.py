"""Run-directory helpers: one run per folder, atomic writes and the resolved config of a run."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from gaia_app.utils.locks import FolderInUseError, FolderLock

# set by launchers on the processes that share rank 0's run dir (Lightning's DDP children, torchrun, srun)
SECONDARY_RANK_VARIABLES = ("LOCAL_RANK", "RANK", "SLURM_PROCID", "NODE_RANK")


class RunDirLock(Callback):
    """Hydra callback (conf/hydra/default.yaml): the run takes its run dir's lock before Hydra writes `.hydra/` into
    it, and holds it until the process ends. A second run given the same `hydra.run.dir` while the first runs fails
    at once, naming the folder, instead of overwriting the first run's config and mixing their checkpoints; run
    again after it ends, the folder is reused as before (`ckpt_path=last` resumes there). The processes a launcher
    starts for one run (other ranks) share rank 0's folder and take no lock."""

    def __init__(self) -> None:
        self.lock: FolderLock | None = None

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        if any(os.environ.get(name, "0") not in ("", "0") for name in SECONDARY_RANK_VARIABLES):
            return
        try:
            self.lock = FolderLock(str(OmegaConf.select(config, "hydra.run.dir")), "hydra.run.dir").acquire()
        except FolderInUseError as error:
            # Hydra turns a callback's exceptions into warnings and carries on; SystemExit is not an Exception
            raise SystemExit(f"Error: {error}") from None

    def on_run_end(self, config: DictConfig, **kwargs: Any) -> None:
        if self.lock is not None:
            self.lock.release()


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temp path beside `path` to write to; on success it replaces `path`, on error it is removed.

    Readers never see half a file, and an interrupted write leaves the old file (or none). The temp
    name starts with '.' and ends in '.tmp', so globs for the final suffix skip it. The file gets the
    usual permissions (0666 minus the umask), not mkstemp's private 0600.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~current_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write `text` to `path` atomically (see `atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write `data` to `path` atomically (see `atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def save_resolved_config(cfg: DictConfig, run_dir: str | Path, name: str = "config_resolved.yaml") -> Path:
    """Write the fully resolved job config (without the hydra node) into the run dir."""
    job = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    path = Path(run_dir) / name
    atomic_write_text(path, OmegaConf.to_yaml(job, resolve=True))
    return path


def atomic_save_npy(path: str | Path, array: np.ndarray) -> None:
    """`np.save` to `path` atomically (see `atomic_path`); the temp name does not end in `.npy`."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, array)
