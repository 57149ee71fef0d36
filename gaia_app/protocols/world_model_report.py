"""Held-out cross-entropy of a GAIA-1 world model per conditioning mode, against the token baselines.

    python -m gaia_app.protocols.world_model_report --ckpt <world model last.ckpt> --tokens <cache root> --out <dir>

The cache root holds train/ and val/ (generate.py mode=tokenize); val/ is the held-out world. Every val segment
is cut into non-overlapping windows of the model's T steps, and frames 2..T are scored (GAIA-1 §2.3, eq. 1):
- model, per trained mode: unconditional, actions, text (each window's own captions and actions);
- copy previous frame (optimally smoothed) and the unigram of the train tokens (gaia_app/eval/token_baselines.py);
- the gain from actions: unconditional − actions per window, with a Student-t 95 % interval over windows.
Writes cross_entropy.json and cross_entropy.md into --out.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from gaia_app.data.collate import collate_token_windows
from gaia_app.data.token_cache import TokenWindows, find_segments, load_segment
from gaia_app.eval.intervals import mean_interval
from gaia_app.eval.token_baselines import copy_previous_cross_entropy, unigram_cross_entropy
from gaia_app.lit.checkpoint import load_module
from gaia_app.lit.gaia1_world_model import MODE_STREAMS, WorldModelModule
from gaia_app.utils.run_dir import atomic_write_text

MODES = ("unconditional", "actions", "text")


def windows(root: Path, steps: int) -> TokenWindows:
    """Non-overlapping windows of `steps` steps over every segment under `root`."""
    segments = [load_segment(path) for path in find_segments(root)]
    return TokenWindows(segments, [(i, 0, len(s.tokens)) for i, s in enumerate(segments)], steps, steps)


@torch.no_grad()
def per_window_cross_entropy(module: WorldModelModule, batch: dict[str, Any], mode: str) -> torch.Tensor:
    """(b,) mean nats/token of frames 2..T of each window under conditioning `mode`."""
    dropped, _ = MODE_STREAMS[mode]
    cond = module.conditions(batch, force_drop={name: name in dropped for name in ("text", "actions")})
    tokens = batch["tokens"]
    logits = module.world_model(tokens, cond)[:, 1:]
    nll = torch.nn.functional.cross_entropy(logits.flatten(0, 2), tokens[:, 1:].flatten(), reduction="none")
    return nll.view(tokens.shape[0], -1).mean(dim=1)


def report(ckpt: str | Path, tokens_root: str | Path, batch: int = 8) -> dict[str, Any]:
    module = load_module(ckpt).eval()
    if not isinstance(module, WorldModelModule):
        raise TypeError(f"--ckpt {ckpt} holds a {type(module).__name__} checkpoint, expected a WorldModelModule")
    net, root = module.world_model, Path(tokens_root)
    val = windows(root / "val", net.frames)
    scores: dict[str, list[float]] = {mode: [] for mode in MODES}
    stacked = []
    for start in tqdm(range(0, len(val), batch), desc="cross-entropy", unit="batch"):
        items = [val[i] for i in range(start, min(start + batch, len(val)))]
        windows_batch = collate_token_windows(items)
        stacked.append(windows_batch["tokens"])
        for mode in MODES:
            scores[mode] += per_window_cross_entropy(module, windows_batch, mode).tolist()
    val_tokens = torch.cat(stacked)
    train_tokens = torch.cat([torch.from_numpy(load_segment(p).tokens) for p in find_segments(root / "train")])
    copy, eps = copy_previous_cross_entropy(val_tokens, net.vocab_size)
    gain = [u - a for u, a in zip(scores["unconditional"], scores["actions"])]
    return {"windows": len(val), "steps": net.frames, "tokens_scored": int(val_tokens[:, 1:].numel()),
            "model": {mode: mean_interval(values).as_dict() for mode, values in scores.items()},
            "action_gain": mean_interval(gain).as_dict(),
            "copy_previous": copy, "copy_previous_eps": eps,
            "unigram": unigram_cross_entropy(train_tokens, val_tokens[:, 1:], net.vocab_size)}


def markdown(results: dict[str, Any]) -> str:
    def cell(e: dict[str, float]) -> str:
        return f"{e['mean']:.4f} [{e['low']:.4f}, {e['high']:.4f}]"

    lines = [f"Held-out cross-entropy (nats/token, frames 2..{results['steps']} of {results['windows']} windows, "
             "95 % intervals over windows)", "", "| predictor | cross-entropy |", "|---|---|"]
    for mode in MODES:
        lines.append(f"| model, {mode} | {cell(results['model'][mode])} |")
    lines += [f"| copy previous frame (ε = {results['copy_previous_eps']:.3f}) | {results['copy_previous']:.4f} |",
              f"| unigram of the train tokens | {results['unigram']:.4f} |",
              f"| gain from actions (unconditional − actions) | {cell(results['action_gain'])} |"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", required=True)
    parser.add_argument("--tokens", required=True, help="token cache root with train/ and val/")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--batch", type=int, default=8)
    args = parser.parse_args(argv)
    results = report(args.ckpt, args.tokens, args.batch)
    atomic_write_text(args.out / "cross_entropy.json", json.dumps(results, indent=2))
    atomic_write_text(args.out / "cross_entropy.md", markdown(results))
    print(markdown(results))


if __name__ == "__main__":
    main()
