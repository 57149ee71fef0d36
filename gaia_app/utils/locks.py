"""One writer per folder: an exclusive lock held while a run, a cache or a shard writer fills a folder.

Two `train.py` runs given the same `hydra.run.dir`, or two `mode=tokenize` runs started on one empty cache folder,
would otherwise both accept the folder and mix their files (one run's checkpoint beside the other's config; two
tokenizers' tokens under one manifest). The lock is an advisory `flock` on `<folder>/.lock`: the kernel drops it
when the process ends, kill -9 included, so a crashed run never leaves a stale lock behind, and the next run simply
takes it. The file holds the owner's pid, for the error message.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

LOCK_FILE = ".lock"


class FolderInUseError(RuntimeError):
    """Another live process holds the folder's lock."""


class FolderLock:
    """An exclusive, non-blocking lock on `folder` (created if missing); `acquire` raises FolderInUseError naming
    `setting` (what chose the folder, e.g. "hydra.run.dir") and the owner's pid when another process holds it."""

    def __init__(self, folder: str | Path, setting: str):
        self.folder, self.setting = Path(folder), setting
        self.handle: IO[str] | None = None

    def acquire(self) -> FolderLock:
        try:
            import fcntl
        except ImportError:  # no flock (Windows): one writer per folder is then the user's to keep
            return self
        self.folder.mkdir(parents=True, exist_ok=True)
        handle = open(self.folder / LOCK_FILE, "a+")  # noqa: SIM115 (held open for the lock's lifetime)
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            owner = handle.read().strip() or "unknown"
            handle.close()
            raise FolderInUseError(
                f"{self.setting}={self.folder} is in use by another running process (pid {owner}): two runs "
                "writing into one folder would mix or lose their outputs; wait for it to finish, or choose "
                f"another {self.setting}") from None
        handle.seek(0)
        handle.truncate()
        handle.write(str(os.getpid()))
        handle.flush()
        self.handle = handle
        return self

    def release(self) -> None:
        if self.handle is not None:
            self.handle.close()  # closing the file drops the flock
            self.handle = None

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


@contextmanager
def folder_lock(folder: str | Path, setting: str) -> Iterator[FolderLock]:
    """`with folder_lock(out_dir, "out_dir"):` write into out_dir as its only writer."""
    with FolderLock(folder, setting) as lock:
        yield lock


def content(folder: Path) -> list[Path]:
    """The entries of `folder` other than its lock file (a folder holding only the lock counts as empty)."""
    return [p for p in folder.iterdir() if p.name != LOCK_FILE] if folder.is_dir() else []
