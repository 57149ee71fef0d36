"""Token caches: pre-computed image tokens (GAIA-1 tokenizer output or real commaVQ tokens) on disk.

A cache is one `.npy` file or a folder of them, each a driving segment of shape (T, n) or
(T, h, w) (commaVQ ships (1200, 8, 16) int16 per minute; its example file is (1200, 128) int64).
An optional `<stem>.actions.npy` beside a segment holds (T, 2) speed and curvature.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from gaia_app.data.clip import ClipError


@dataclass
class TokenSegment:
    """tokens: (T, n) int64; actions: (T, 2) float32 or None; name: the file stem."""

    name: str
    tokens: np.ndarray
    actions: np.ndarray | None


def load_segment(path: Path, frame_stride: int = 1) -> TokenSegment:
    """Read one token file (and its actions), keep every `frame_stride`-th step."""
    tokens = np.load(path)
    if tokens.ndim not in (2, 3) or tokens.dtype.kind not in "iu":
        raise ClipError(f"{path}: expected integer tokens (T, n) or (T, h, w), got {tokens.dtype} {tokens.shape}")
    tokens = tokens.reshape(len(tokens), -1).astype(np.int64)[::frame_stride]
    actions_path = path.with_name(path.stem + ".actions.npy")
    actions = None
    if actions_path.exists():
        actions = np.load(actions_path).astype(np.float32)[::frame_stride]
        if actions.shape != (len(tokens), 2):
            raise ClipError(f"{actions_path}: actions shape {actions.shape}, expected ({len(tokens)}, 2) after stride {frame_stride}")
    return TokenSegment(path.stem, tokens, actions)


def find_segments(path: str | Path) -> list[Path]:
    """The token files of a cache: the file itself, or every `*.npy` in a folder except actions."""
    root = Path(path)
    if root.is_file():
        return [root]
    files = sorted(p for p in root.glob("*.npy") if not p.name.endswith(".actions.npy"))
    if not files:
        raise ClipError(f"token cache '{root}': no .npy token files found")
    return files


class TokenWindows(Dataset):
    """Windows of `seq_len` steps from token segments → {"tokens": (t, n) int64, "actions"?: (t, 2)}.

    `spans` lists (segment index, first step, last step exclusive) regions to cut windows from,
    so that train and validation can use disjoint parts of one segment.
    """

    def __init__(self, segments: list[TokenSegment], spans: list[tuple[int, int, int]], seq_len: int, stride: int):
        self.segments, self.seq_len = segments, seq_len
        self.index = [(s, start) for s, lo, hi in spans for start in range(lo, hi - seq_len + 1, stride)]
        if not self.index:
            raise ClipError(f"token cache: no window of {seq_len} steps fits in spans {spans}")

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        s, start = self.index[i]
        seg = self.segments[s]
        item = {"tokens": torch.from_numpy(seg.tokens[start : start + self.seq_len])}
        if seg.actions is not None:
            item["actions"] = torch.from_numpy(seg.actions[start : start + self.seq_len])
        return item


def split_spans(segments: list[TokenSegment], val_fraction: float, seq_len: int) -> tuple[list, list]:
    """Train/val spans: whole segments when there are several, else the last part of the only one
    with a gap of one window so no step is on both sides."""
    if len(segments) > 1:
        n_val = max(1, round(val_fraction * len(segments)))
        train = [(i, 0, len(s.tokens)) for i, s in enumerate(segments[:-n_val])]
        val = [(i, 0, len(s.tokens)) for i, s in enumerate(segments) if i >= len(segments) - n_val]
        return train, val
    total = len(segments[0].tokens)
    n_val = max(seq_len, int(round(val_fraction * total)))
    if total < 2 * seq_len + n_val:
        raise ClipError(f"token segment '{segments[0].name}': {total} steps too short for train+val windows of {seq_len}")
    return [(0, 0, total - n_val)], [(0, total - n_val, total)]
