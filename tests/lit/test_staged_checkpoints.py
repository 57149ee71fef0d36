"""gaia_app/lit/staged_checkpoints.py: a checkpoint folder that every rank writes is staged beside the old one and
swapped in whole, so a crash while saving never leaves a folder of two steps; `ckpt_path=last` recovers a swap
interrupted between its renames."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch

from gaia_app.lit.staged_checkpoints import StagedSave, recover_checkpoint, swap_in
from gaia_app.tasks.train import resume_path


class FolderWriter:
    """A stand-in for a sharded strategy on one process: each 'rank' file of the step goes into the folder."""

    is_global_zero = True
    crash_after: int | None = None  # raise after writing this many shard files (a crash mid-save)

    def broadcast(self, obj: Any) -> Any:
        return obj

    def barrier(self, name: str | None = None) -> None:
        pass

    def save_checkpoint(self, checkpoint: dict[str, Any], filepath: Any, storage_options: Any | None = None) -> None:
        folder = Path(filepath)
        folder.mkdir(parents=True, exist_ok=True)
        for rank, shard in enumerate(checkpoint["shards"]):
            if self.crash_after is not None and rank >= self.crash_after:
                raise RuntimeError("killed while saving")
            (folder / f"__{rank}_0.distcp").write_text(f"step {checkpoint['step']} {shard}")


class StagedWriter(StagedSave, FolderWriter):
    pass


def contents(folder: Path) -> dict[str, str]:
    return {p.name: p.read_text() for p in sorted(folder.iterdir())}


def test_a_second_save_replaces_the_folder_whole(tmp_path: Path) -> None:
    last = tmp_path / "last.ckpt"
    writer = StagedWriter()
    writer.save_checkpoint({"step": 1, "shards": ["a", "b", "c"]}, last)
    writer.save_checkpoint({"step": 2, "shards": ["a", "b"]}, last)
    # nothing of step 1 is left (written in place, its third shard would have stayed beside step 2's)
    assert contents(last) == {"__0_0.distcp": "step 2 a", "__1_0.distcp": "step 2 b"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt"]


def test_a_crash_while_saving_leaves_the_previous_checkpoint_untouched(tmp_path: Path) -> None:
    last = tmp_path / "last.ckpt"
    writer = StagedWriter()
    writer.save_checkpoint({"step": 1, "shards": ["a", "b"]}, last)
    writer.crash_after = 1
    with pytest.raises(RuntimeError, match="killed while saving"):
        writer.save_checkpoint({"step": 2, "shards": ["a", "b"]}, last)
    assert contents(last) == {"__0_0.distcp": "step 1 a", "__1_0.distcp": "step 1 b"}
    writer.crash_after = None  # the next save clears the crashed one's partial folder
    writer.save_checkpoint({"step": 3, "shards": ["a", "b"]}, last)
    assert contents(last)["__1_0.distcp"] == "step 3 b"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt"]


def test_in_place_writing_would_mix_steps(tmp_path: Path) -> None:
    """The failure the staging prevents, shown on the unstaged writer."""
    last = tmp_path / "last.ckpt"
    writer = FolderWriter()
    writer.save_checkpoint({"step": 1, "shards": ["a", "b"]}, last)
    writer.crash_after = 1
    with pytest.raises(RuntimeError):
        writer.save_checkpoint({"step": 2, "shards": ["a", "b"]}, last)
    assert contents(last) == {"__0_0.distcp": "step 2 a", "__1_0.distcp": "step 1 b"}


def test_a_swap_interrupted_between_its_renames_is_recovered_by_ckpt_path_last(tmp_path: Path) -> None:
    checkpoints = tmp_path / "checkpoints"
    checkpoints.mkdir()
    (checkpoints / "last.ckpt.old").write_bytes(b"whole")  # the old one moved aside, the new one not yet in
    assert recover_checkpoint(checkpoints / "last.ckpt") == checkpoints / "last.ckpt"
    assert (checkpoints / "last.ckpt").read_bytes() == b"whole" and not (checkpoints / "last.ckpt.old").exists()
    (checkpoints / "last.ckpt").unlink()
    torch.save({"state_dict": {"w": torch.zeros(1)}, "global_step": 3}, checkpoints / "last.ckpt.old")
    assert resume_path("last", tmp_path) == str(checkpoints / "last.ckpt")
    assert torch.load(checkpoints / "last.ckpt", weights_only=True)["global_step"] == 3


def test_swap_in_replaces_a_file_by_a_folder_and_keeps_nothing_aside(tmp_path: Path) -> None:
    path, staged = tmp_path / "last.ckpt", tmp_path / "last.ckpt.partial"
    path.write_bytes(b"one file")
    staged.mkdir()
    (staged / ".metadata").write_bytes(b"dcp")
    swap_in(staged, path)
    assert contents(path) == {".metadata": "dcp"} and sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt"]


def test_an_explicit_checkpoint_path_is_recovered_too(tmp_path: Path) -> None:
    torch.save({"state_dict": {"w": torch.zeros(1)}, "global_step": 5}, tmp_path / "last.ckpt.old")
    assert resume_path(str(tmp_path / "last.ckpt"), tmp_path) == str(tmp_path / "last.ckpt")
    assert (tmp_path / "last.ckpt").exists()
