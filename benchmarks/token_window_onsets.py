r"""How much a GAIA-1 training window's command changes where a rollout starts generating, under each way of drawing
windows (`data.window_sampling`, gaia_app/data/token_cache.py). Exact expectations from the samplers' start
probabilities over the training spans of a token cache, no draws.

Per component of the command (speed change per step, curvature), the expected |mean after − mean before|: the
window's steps from `change_after` on against the steps before them, the contrast a rollout from `change_after`
context frames must draw. Token clips carry no open-loop metadata, so this reads the change from the actions.

    python benchmarks/token_window_onsets.py --tokens outputs/paper_faithful/tokens/train --seq-len 12 \
        --change-after 4 --out onsets
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from gaia_app.data.token_cache import (
    TokenSegment,
    find_segments,
    load_segment,
    segment_commands,
    split_spans,
    token_action_change_weights,
)
from gaia_app.utils.run_dir import atomic_write_text

COMPONENTS = ("speed change per step (m/s)", "curvature (1/m)")


def window_contrasts(commands: np.ndarray, seq_len: int, change_after: int) -> np.ndarray:
    """commands (T, 2) → (starts, 2): |mean of the window's steps from change_after on − mean of those before|."""
    windows = np.lib.stride_tricks.sliding_window_view(commands, seq_len, axis=0)  # (starts, 2, seq_len)
    return np.abs(windows[..., change_after:].mean(-1) - windows[..., :change_after].mean(-1))


def expected_contrasts(segments: list[TokenSegment], spans: list[tuple[int, int, int]], seq_len: int,
                       change_after: int) -> dict[str, dict[str, float]]:
    """{sampling: {component: expected contrast}} with every span weighted by its number of windows, as the train
    loader visits them."""
    contrasts = [window_contrasts(segment_commands(segments[s].actions[lo:hi]), seq_len, change_after)
                 for s, lo, hi in spans]
    starts = {"uniform": [np.full(len(c), 1 / len(c)) for c in contrasts],
              "action_change": [w.numpy() for w in token_action_change_weights(segments, spans, seq_len,
                                                                               change_after)]}
    sizes = np.array([len(c) for c in contrasts], np.float64)
    table = {}
    for sampling, probabilities in starts.items():
        per_span = np.stack([(p[:, None] * c).sum(0) for p, c in zip(probabilities, contrasts, strict=True)])
        table[sampling] = dict(zip(COMPONENTS, (sizes @ per_span / sizes.sum()).tolist(), strict=True))
    return table


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tokens", required=True, help="a token cache folder (generate.py mode=tokenize)")
    parser.add_argument("--seq-len", type=int, default=12)
    parser.add_argument("--change-after", type=int, default=4)
    parser.add_argument("--val-fraction", type=float, default=0.1, help="data.val_fraction: its spans are left out")
    parser.add_argument("--out", type=Path, default=None, help="a folder for onsets.json")
    args = parser.parse_args(argv)
    segments = [load_segment(p) for p in find_segments(args.tokens)]
    train, _ = split_spans(segments, args.val_fraction, args.seq_len)
    table = expected_contrasts(segments, train, args.seq_len, args.change_after)
    result = {"tokens": str(args.tokens), "seq_len": args.seq_len, "change_after": args.change_after,
              "training_spans": len(train), "expected_contrast": table}
    for sampling, row in table.items():
        print(f"{sampling:>14}: " + ", ".join(f"{name} {value:.4f}" for name, value in row.items()))
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out / "onsets.json", json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
