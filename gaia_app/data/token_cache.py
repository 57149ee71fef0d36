"""Token caches: pre-computed image tokens (GAIA-1 tokenizer output or real commaVQ tokens) on disk.

A cache is one `.npy` file or a folder of them, each a driving segment of shape (T, n) or
(T, h, w) (commaVQ ships (1200, 8, 16) int16 per minute; its example file is (1200, 128) int64).
`generate.py mode=tokenize` writes one folder per clip, `<root>/<clip_id>/<camera>.npy`, and a manifest
`<root>/cache.json` (gaia_app/data/cache_manifest.py); flat folders of `.npy` files are read too.
Optional sidecars beside a segment `<stem>.npy`, written by `generate.py mode=tokenize`:
    <stem>.actions.npy      (T, 2) float32 speed (m/s) and curvature (1/m)
    <stem>.timestamps.npy   (T,) float64 seconds of each step
    <stem>.text.json        list of T captions (null where a frame has none)
Every file is written atomically (`write_segment`); the token file is written last, so its presence
marks a finished segment.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from gaia_app.data.clip import ClipError
from gaia_app.data.latent_windows import change_probabilities
from gaia_app.data.names import inside
from gaia_app.utils.run_dir import atomic_save_npy, atomic_write_text

SIDECARS = (".actions.npy", ".timestamps.npy", ".text.json")
WINDOW_SAMPLING = ("uniform", "action_change")


@dataclass
class TokenSegment:
    """tokens: (T, n) int64 as loaded ((T, h, w) or (T, n) integer to write); name: the file stem;
    actions: (T, 2) float32 or None; timestamps: (T,) float64 seconds or None; text: T captions (None entries
    allowed) or None."""

    name: str
    tokens: np.ndarray
    actions: np.ndarray | None
    timestamps: np.ndarray | None = None
    text: list[str | None] | None = None


def sidecar(path: Path, suffix: str) -> Path:
    """`<stem><suffix>` beside the token file `<stem>.npy`."""
    return path.with_name(path.stem + suffix)


def load_segment(path: Path, frame_stride: int = 1) -> TokenSegment:
    """Read one token file (and its sidecars), keep every `frame_stride`-th step."""
    found = {suffix: sidecar(path, suffix) for suffix in SIDECARS if sidecar(path, suffix).exists()}
    return read_segment(path.stem, path, found, frame_stride, str(path))


def read_segment(name: str, tokens_file: Any, sidecars: dict[str, Any], frame_stride: int, where: str,
                 stored_dtype: bool = False) -> TokenSegment:
    """A segment from its token file and its sidecars {suffix: file}, each a path or a file object (e.g. a shard
    member in memory); `where` names the token file in errors. Tokens become int64 unless `stored_dtype` keeps the
    file's (compact) integer type."""
    tokens = np.load(tokens_file)
    if tokens.ndim not in (2, 3) or tokens.dtype.kind not in "iu":
        raise ClipError(f"{where}: expected integer tokens (T, n) or (T, h, w), got {tokens.dtype} {tokens.shape}")
    tokens = tokens.reshape(len(tokens), -1)[::frame_stride]
    tokens = tokens if stored_dtype else tokens.astype(np.int64)
    stem = where.removesuffix(".npy")
    actions = _load_sidecar(sidecars.get(".actions.npy"), stem + ".actions.npy", np.float32, (len(tokens), 2),
                            frame_stride)
    timestamps = _load_sidecar(sidecars.get(".timestamps.npy"), stem + ".timestamps.npy", np.float64, (len(tokens),),
                               frame_stride)
    text = None
    if ".text.json" in sidecars:
        source = sidecars[".text.json"]
        text = json.loads(source.read_text() if isinstance(source, Path) else source.read())[::frame_stride]
        if len(text) != len(tokens):
            raise ClipError(f"{stem}.text.json: {len(text)} captions, "
                            f"expected {len(tokens)} after stride {frame_stride}")
    return TokenSegment(name, tokens, actions, timestamps, text)


def _load_sidecar(source: Any, where: str, dtype: type, shape: tuple[int, ...], frame_stride: int) -> np.ndarray | None:
    """A per-step array beside a token file (a path or file object), strided like the tokens; None when absent."""
    if source is None:
        return None
    array = np.load(source).astype(dtype)[::frame_stride]
    if array.shape != shape:
        raise ClipError(f"{where}: shape {array.shape}, expected {shape} after stride {frame_stride}")
    return array


def segment_path(root: str | Path, name: str) -> Path:
    """The token file of segment `name` (`<clip_id>/<camera>` or a plain stem), which must stay under `root`."""
    return inside(root, *f"{name}.npy".split("/"))


def segment_done(root: str | Path, name: str) -> bool:
    """True when the token file of segment `name` exists (it is written last, see `write_segment`)."""
    return segment_path(root, name).is_file()


def write_segment(root: str | Path, segment: TokenSegment) -> Path:
    """Write a segment and its sidecars, each atomically, the token file last; returns the token file.

    segment.tokens: (T, h, w) or (T, n) integer; stored as int16 when the codebook fits (like commaVQ).
    """
    path = segment_path(root, segment.name)
    path.parent.mkdir(parents=True, exist_ok=True)
    t = len(segment.tokens)
    if segment.actions is not None:
        atomic_save_npy(sidecar(path, ".actions.npy"), np.asarray(segment.actions, np.float32).reshape(t, 2))
    if segment.timestamps is not None:
        atomic_save_npy(sidecar(path, ".timestamps.npy"), np.asarray(segment.timestamps, np.float64).reshape(t))
    if segment.text is not None:
        atomic_write_text(sidecar(path, ".text.json"), json.dumps(list(segment.text)))
    tokens = np.asarray(segment.tokens)
    dtype = np.int16 if tokens.size == 0 or tokens.max() < np.iinfo(np.int16).max else np.int32
    atomic_save_npy(path, tokens.astype(dtype))
    return path


def find_segments(path: str | Path) -> list[Path]:
    """The token files of a cache: the file itself, or every `*.npy` in a folder and in its clip folders, except
    sidecars."""
    root = Path(path)
    if root.is_file():
        return [root]
    found = [*root.glob("*.npy"), *root.glob("*/*.npy")]
    files = sorted(p for p in found if not p.name.endswith(SIDECARS) and not p.parent.name.startswith("."))
    if not files:
        raise ClipError(f"token cache '{root}': no .npy token files found")
    return files


class TokenWindows(Dataset):
    """Windows of `seq_len` steps from token segments →
    {"tokens": (t, n) int64, "actions"?: (t, 2), "timestamps"?: (t,) float32 seconds from the window start,
    "text"?: t captions (None where a step has none)}; `collate_token_windows` batches them.

    `spans` lists (segment index, first step, last step exclusive) regions to cut windows from,
    so that train and validation can use disjoint parts of one segment.

    `window_sampling`: "uniform" serves item i from its own start; "action_change" (ours, the GAIA-2 onset sampler of
    latent_windows.py applied to GAIA-1 windows) keeps item i's span, so each span is visited as often as under
    "uniform", and draws any start within it (`stride` applies to uniform starts only) ∝ the square of how far the
    mean command (speed change per step, curvature; `segment_commands`) of the window's steps from `change_after` on
    differs from that of the steps before (`token_action_change_weights`).
    `change_after` is a rollout's context frames (GAIA-1 §4.2 conditions on past frames; controllability: 4).
    """

    def __init__(self, segments: list[TokenSegment], spans: list[tuple[int, int, int]], seq_len: int, stride: int,
                 window_sampling: str = "uniform", change_after: int = 4):
        if window_sampling not in WINDOW_SAMPLING:
            raise ValueError(f"data.window_sampling={window_sampling!r}: expected one of {WINDOW_SAMPLING}")
        self.segments, self.spans, self.seq_len = segments, spans, seq_len
        self.index = [(k, start) for k, (_, lo, hi) in enumerate(spans)
                      for start in range(lo, hi - seq_len + 1, stride)]
        if not self.index:
            raise ClipError(f"token cache: no window of {seq_len} steps fits in spans {spans}")
        self.start_weights: list[torch.Tensor] | None = None
        if window_sampling == "action_change":
            self.start_weights = token_action_change_weights(segments, spans, seq_len, change_after)

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict[str, Any]:
        k, start = self.index[i]
        s, lo = self.spans[k][0], self.spans[k][1]
        if self.start_weights is not None:
            start = lo + int(torch.multinomial(self.start_weights[k], 1).item())
        seg = self.segments[s]
        item = {"tokens": torch.from_numpy(seg.tokens[start : start + self.seq_len])}
        if seg.actions is not None:
            item["actions"] = torch.from_numpy(seg.actions[start : start + self.seq_len])
        if seg.timestamps is not None:
            times = seg.timestamps[start : start + self.seq_len]
            item["timestamps"] = torch.from_numpy(times - times[0]).float()
        if seg.text is not None:
            item["text"] = list(seg.text[start : start + self.seq_len])
        return item


def segment_commands(actions: np.ndarray) -> np.ndarray:
    """(T, 2) speed (m/s), curvature (1/m) per step → (T, 2) (speed change per step, curvature): the command a step
    carries out. The speed's change rather than the speed: a constant braking changes the speed in every window after
    its onset, its rate only at the onset. The first step takes the second's change."""
    speed = actions[:, 0].astype(np.float64)
    change = np.diff(speed, prepend=speed[0] if len(speed) < 2 else 2 * speed[0] - speed[1])
    return np.stack([change, actions[:, 1].astype(np.float64)], axis=1)


def token_action_change_weights(segments: list[TokenSegment], spans: list[tuple[int, int, int]], seq_len: int,
                                change_after: int) -> list[torch.Tensor]:
    """Per span, (starts,) float64 probabilities of its window starts ∝ `action_changes` ** 2 of its commands, each
    component in units of its spread over all spans; a span whose command never changes gets uniform starts.
    ClipError naming a segment without actions; ValueError when `change_after` is outside [1, seq_len − 1]."""
    if not 1 <= change_after < seq_len:
        raise ValueError(f"data.change_after={change_after}: expected a number of steps in [1, seq_len − 1 = "
                         f"{seq_len - 1}]")
    missing = sorted({segments[s].name for s, _, _ in spans if segments[s].actions is None})
    if missing:
        raise ClipError(f"data.window_sampling=action_change needs actions; token segments {missing[:5]} have no "
                        f"'.actions.npy' sidecar")
    return change_probabilities([segment_commands(segments[s].actions[lo:hi]) for s, lo, hi in spans], seq_len,
                                change_after)


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
        raise ClipError(f"token segment '{segments[0].name}': {total} steps too short "
                        f"for train+val windows of {seq_len}")
    return [(0, 0, total - n_val)], [(0, total - n_val, total)]
