"""Checkpoints that every rank writes into one folder, made atomic: written beside the old one, then swapped in.

Lightning's sharded strategies (FSDP's sharded state dict, FSDP2's distributed checkpoint, DeepSpeed) write
`last.ckpt/` in place, each rank its files, and FSDP2's distributed checkpoint says so ("overwriting"). A run that
crashes in the middle of such a save leaves a folder holding parts of two steps, and `ckpt_path=last` cannot resume
from it. `StagedSave` writes the new checkpoint to `<name>.partial`; when every rank has written its part, rank 0
moves the old checkpoint to `<name>.old`, the new one to `<name>`, and deletes the old. A crash while writing leaves
the previous checkpoint untouched; a crash between the two renames leaves it whole as `<name>.old`, which
`recover_checkpoint` (called by `ckpt_path=last`) renames back.
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

STAGED, OLD = ".partial", ".old"


def remove(path: Path) -> None:
    """Delete a file or a folder, if there is one."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def swap_in(staged: Path, path: Path) -> None:
    """Replace `path` (a file, a folder or nothing) by `staged`: the old one goes to `<path>.old` first, so that at
    every moment a whole checkpoint exists under one of the two names."""
    old = path.with_name(path.name + OLD)
    remove(old)
    if path.exists():
        path.rename(old)
    staged.rename(path)
    remove(old)


def recover_checkpoint(path: str | Path) -> Path:
    """`path`, after renaming `<path>.old` back to it when a crash between `swap_in`'s two renames left only that."""
    path = Path(path)
    old = path.with_name(path.name + OLD)
    if not path.exists() and old.exists():
        log.warning("%s is missing and %s holds the checkpoint before an interrupted save: renaming it back", path,
                    old.name)
        try:
            old.rename(path)
        except FileNotFoundError:  # another rank of the same launch renamed it first
            pass
    return path


class StagedSave:
    """Mixin for a Lightning strategy (before it in the bases): `save_checkpoint` writes into `<path>.partial` with
    the strategy's own method on every rank, then rank 0 swaps it in (`swap_in`) after a barrier."""

    def save_checkpoint(self, checkpoint: dict[str, Any], filepath: Any, storage_options: Any | None = None) -> None:
        path = Path(self.broadcast(str(filepath)))  # type: ignore[attr-defined]
        staged = path.with_name(path.name + STAGED)
        if self.is_global_zero:  # type: ignore[attr-defined]
            remove(staged)  # a save that crashed before
        self.barrier("staged_checkpoint_clear")  # type: ignore[attr-defined]
        super().save_checkpoint(checkpoint, staged, storage_options=storage_options)  # type: ignore[misc]
        self.barrier("staged_checkpoint_written")  # type: ignore[attr-defined]
        if self.is_global_zero:  # type: ignore[attr-defined]
            swap_in(staged, path)
        self.barrier("staged_checkpoint_swapped")  # type: ignore[attr-defined]
