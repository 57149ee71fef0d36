r"""What a frame costs: tokens per frame, the tokenizer's time per frame, and what a finer token grid would cost the
GAIA-1 world model (the road-users issue asks each tokenizer choice to say what it costs the world model per frame).

    python benchmarks/bench_tokens_per_frame.py [--weights gaia1 gaia2] [--repeats 5] [--json OUT]

Rows, measured side by side in one run (medians over --repeats rounds, candidates alternated within a round):
- each tokenizer: what it hands the world model per 64 × 112 frame (GAIA-1: h·w ids of log2 K bits; GAIA-2: latent
  values per frame, C·h·w / τ) and its encode + decode time per frame (GAIA-1 on 12 frames, GAIA-2 on one 8-frame clip);
- the GAIA-1 world model of the shipped preset (random weights: time only) on a 12-step window of 8 × 14 = 112 tokens
  per frame (what ships, also with the agent-weighted tokenizer) against the same model on a 16 × 28 = 448-token grid
  (D = 4 instead of 8, the "more tokens per frame" design): one training step (forward, loss, backward) and one
  forward per frame of the window.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from gaia_app.models.gaia1.world_model import next_token_loss
from gaia_app.weights.folders import build, load_nets, read_config, shipped_folder, weight_files

FRAMES = 12  # the shipped GAIA-1 window (1.9 s at 6.25 Hz)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--json", type=Path, default=None)
    return p.parse_args(argv)


def median_ms(fn: Callable[[], object], repeats: int) -> list[float]:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append((time.perf_counter() - start) * 1e3)
    return times


def tokenizer_candidates() -> dict[str, tuple[Callable[[], object], int, dict]]:
    """name → (one timed call, frames it covers, what a frame hands the world model)."""
    g1 = load_nets("gaia1", "tokenizer")[0]["net"]
    g2 = load_nets("gaia2", "video_tokenizer")[0]["net"]
    frames = torch.rand(FRAMES, 3, 64, 112) * 2 - 1
    clip = torch.rand(1, 1, 8, 3, 64, 112) * 2 - 1
    with torch.no_grad():
        grid = g1.encode(frames[:1]).shape[-2:]
        latent = g2.encode(clip).mean.shape  # (1, 1, t, C, h, w)
    ids = grid[0] * grid[1]
    values = latent[3] * latent[4] * latent[5] * latent[2] / clip.shape[2]
    return {
        "GAIA-1 tokenizer (encode + decode)": (torch.no_grad()(lambda: g1.decode(g1.encode(frames))), FRAMES,
                                               {"per_frame": f"{ids} ids",
                                                "bits_per_frame": ids * math.log2(g1.codebook_size)}),
        "GAIA-2 video tokenizer (encode + decode)": (torch.no_grad()(lambda: g2.decode(g2.encode(clip).mode())), 8,
                                                     {"per_frame": f"{values:g} latent values",
                                                      "bits_per_frame": 16 * values}),
    }


def world_model_candidates() -> dict[str, tuple[Callable[[], object], int, dict]]:
    """The shipped GAIA-1 world-model preset at 112 and at 448 tokens per frame: a training step and a forward."""
    config = read_config(weight_files(shipped_folder("gaia1"), "world_model")[1])["nets"]["net"]
    out = {}
    for tokens in (112, 448):
        torch.manual_seed(0)
        net = build({**config, "image_tokens": tokens}, f"world model at {tokens} tokens")
        ids = torch.randint(0, 1024, (1, FRAMES, tokens))
        actions = torch.zeros(1, FRAMES, 2)

        def train_step(net=net, ids=ids, actions=actions) -> None:
            net.train()
            net.zero_grad()
            next_token_loss(net, ids, net.conditioner(1, FRAMES, None, actions)).backward()

        @torch.no_grad()
        def forward(net=net, ids=ids, actions=actions) -> None:
            net.eval()
            net(ids, net.conditioner(1, FRAMES, None, actions))

        out[f"GAIA-1 world model, {tokens} tokens per frame: training step"] = (train_step, FRAMES, {"tokens": tokens})
        out[f"GAIA-1 world model, {tokens} tokens per frame: forward"] = (forward, FRAMES, {"tokens": tokens})
    return out


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    candidates = {**tokenizer_candidates(), **world_model_candidates()}
    for fn, _, _ in candidates.values():  # warm-up
        fn()
    times: dict[str, list[float]] = {name: [] for name in candidates}
    names = list(candidates)
    for round_ in range(args.repeats):
        for name in names if round_ % 2 == 0 else reversed(names):
            times[name] += median_ms(candidates[name][0], 1)
    rows = {name: {"ms_per_frame": statistics.median(t) / candidates[name][1], "ms_per_call": t, **candidates[name][2]}
            for name, t in times.items()}
    print(f"torch threads: {torch.get_num_threads()}\n\n| what | per frame | ms per frame |\n|---|---|---:|")
    for name, row in rows.items():
        what = row.get("per_frame", f"{row.get('tokens')} tokens")
        print(f"| {name} | {what} | {row['ms_per_frame']:.1f} |")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return rows


if __name__ == "__main__":
    main()
