"""Sharded streaming vs folder loading, side by side in one run (docs/benchmarks.md, "Sharded streaming").

Builds two local datasets, shards each with `python -m gaia_app.data.shard`'s code, then reads one training epoch
through both loaders, alternating the two `--repeats` times, and reports samples/s (median and range) and the ratio:
- a GAIA-1 token cache: `--segments` segments of `--steps` steps of 18×32 = 576 tokens (GAIA-1 §2.3), windows of
  26 steps (§4.2) at stride `--stride`: TokenCacheDataModule (every segment loaded into memory at setup, the setup
  counted) vs TokenShardDataModule;
- 288×512 clips (GAIA-1 §4.2 resolution): `--clips` synthetic clips of 64 frames at 25 Hz in the clip-folder format,
  windows of 16 frames at 6.25 Hz: ClipDataModule over ClipFolderDataset vs ClipShardDataModule.
Both loaders of a pair use the same batch size, workers and validation share.

Paper rate to keep fed (GAIA-1 §4.2): the world model trained 100k steps in 15 days at batch 128 on 64 A100s:
128 / (15 · 86400 / 100000) = 9.9 windows/s for the whole job, 0.15 windows/s per GPU.

    python benchmarks/bench_shard_throughput.py --workers 2 --repeats 3 --out outputs/bench_shards
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from gaia_app.data.clip_folder import ClipFolderDataset
from gaia_app.data.clip_writer import write_clip
from gaia_app.data.datamodules import ClipDataModule, TokenCacheDataModule
from gaia_app.data.shard import write_shards
from gaia_app.data.shard_datamodules import ClipShardDataModule, TokenShardDataModule
from gaia_app.data.synthetic import generate_clip
from gaia_app.data.token_cache import TokenSegment, write_segment

PAPER_RATE = 128 / (15 * 86400 / 100_000)  # windows/s of GAIA-1's world-model run (§4.2)


def make_tokens(root: Path, segments: int, steps: int) -> Path:
    rng = np.random.default_rng(0)
    for i in range(segments):
        actions = np.stack([np.full(steps, 10.0 + i % 7), rng.normal(0, 0.01, steps)], 1).astype(np.float32)
        write_segment(root, TokenSegment(f"drive{i:04d}/front", rng.integers(0, 8192, (steps, 18, 32)), actions,
                                         np.arange(steps) / 6.25))
    return root


def make_clips(root: Path, clips: int) -> Path:
    for seed in range(clips):
        write_clip(generate_clip(seed=seed, height=288, width=512, cameras=["front"], clip_len=64, fps=25.0), root)
    return root


def epoch_rate(make: Any, key: str) -> float:
    """Samples/s of one training epoch, building the module (e.g. scanning the clip folders) and setup included."""
    start = time.perf_counter()
    module = make()
    module.setup("fit")
    count = sum(len(batch[key]) for batch in module.train_dataloader())
    return count / (time.perf_counter() - start)


def compare(name: str, folder: Any, shards: Any, key: str, repeats: int) -> dict[str, Any]:
    """Alternate the two loaders `repeats` times (fresh modules each time) → rates and their ratio."""
    rates: dict[str, list[float]] = {"folder": [], "shards": []}
    for _ in range(repeats):
        rates["folder"].append(epoch_rate(folder, key))
        rates["shards"].append(epoch_rate(shards, key))
    row = {side: {"median": statistics.median(v), "min": min(v), "max": max(v)} for side, v in rates.items()}
    row["ratio_median"] = row["shards"]["median"] / row["folder"]["median"]
    row["ratio_worst"] = row["shards"]["min"] / row["folder"]["max"]
    print(f"{name}: folder {row['folder']['median']:.1f}/s, shards {row['shards']['median']:.1f}/s, "
          f"ratio {row['ratio_median']:.2f} (worst pairing {row['ratio_worst']:.2f})")
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--segments", type=int, default=64)
    parser.add_argument("--steps", type=int, default=160)
    parser.add_argument("--stride", type=int, default=1)
    parser.add_argument("--shard-size", default="4MB")
    parser.add_argument("--clips", type=int, default=24)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="outputs/bench_shards")
    args = parser.parse_args()
    out = Path(args.out)
    common = {"batch_size": 8, "num_workers": args.workers}
    tokens = out / "tokens"
    if not tokens.exists():
        make_tokens(tokens, args.segments, args.steps)
    # shards small enough that every worker gets several (a worker without a shard idles)
    write_shards("tokens", tokens, out / "token_shards", args.shard_size, val_fraction=0.1, progress=False)
    clips = out / "clips"
    if not clips.exists():
        make_clips(clips, args.clips)
    write_shards("clips", clips, out / "clip_shards", args.shard_size, val_fraction=0.1, split_by="clip",
                 progress=False)
    window = {"seq_len": 26, "stride": args.stride}
    video = {"clip_len": 16, "fps": 6.25, "height": 288, "width": 512}
    results = {
        "paper_rate_windows_per_s": PAPER_RATE,
        "paper_rate_per_gpu": PAPER_RATE / 64,
        "tokens": compare("token cache (26-step windows)",
                          lambda: TokenCacheDataModule(str(tokens), val_fraction=0.1, **window, **common),
                          lambda: TokenShardDataModule(str(out / "token_shards"), shuffle_buffer=1024, **window,
                                                       **common),
                          "tokens", args.repeats),
        "clips": compare("288×512 clips (16 frames at 6.25 Hz)",
                         lambda: ClipDataModule(ClipFolderDataset(clips), val_fraction=0.1, split_by="clip", **video,
                                                **common),
                         lambda: ClipShardDataModule(str(out / "clip_shards"), shuffle_buffer=16, **video, **common),
                         "video", args.repeats),
        "settings": vars(args),
    }
    (out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"paper rate to keep fed: {PAPER_RATE:.1f} windows/s per job, {PAPER_RATE / 64:.2f} per GPU")


if __name__ == "__main__":
    main()
