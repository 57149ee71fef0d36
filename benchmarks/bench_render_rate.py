"""Seconds to make the controllability task's real clips, every 25 Hz frame rendered vs only the frames at the world
model's rate (`SyntheticClipDataset(render_rate=...)`), side by side in one run (docs/benchmarks.md, "Rendering
only the kept frames").

The clips are what `mode=controllability` renders for its ceiling rows: `--clips` held-out clips of 12 steps at
6.25 Hz (45 simulation steps at 25 Hz each) and, per clip, one re-simulation driven by a command. Both paths give
the same frames (tests/data/test_synthetic.py); the benchmark also checks that. Paths alternate `--repeats` times
(medians).

    python benchmarks/bench_render_rate.py --clips 8 --repeats 3
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from gaia_app.eval.controllability import probe_clips
from gaia_app.protocols.controllability import commanded_actions, driven_clip, world

RATE, STEPS, T0 = 6.25, 12, 4


def make_clips(seed: int, count: int, every_frame: bool) -> torch.Tensor:
    """(2·count, 12, 3, 64, 112) frames: each held-out clip at 6.25 Hz, then its re-simulation under "brake"."""
    clips = world(seed, count, 64, 112, STEPS, RATE, every_frame=every_frame)
    contexts = probe_clips([clips[i] for i in range(count)], RATE, STEPS)
    actions = commanded_actions(contexts, T0, STEPS - T0, RATE, [("brake", "straight")]).numpy()
    driven = [driven_clip(seed, i, 64, 112, actions[i], T0, RATE, every_frame=every_frame) for i in range(count)]
    return torch.cat([contexts.frames, probe_clips(driven, RATE, STEPS).frames])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clips", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1000)
    args = parser.parse_args()
    seconds: dict[str, list[float]] = {"every 25 Hz frame": [], "only the 6.25 Hz frames": []}
    frames = {}
    for _ in range(args.repeats):
        for name, every_frame in (("every 25 Hz frame", True), ("only the 6.25 Hz frames", False)):
            start = time.perf_counter()
            frames[name] = make_clips(args.seed, args.clips, every_frame)
            seconds[name].append(time.perf_counter() - start)
    same = torch.equal(*frames.values())
    full, cheap = (statistics.median(s) for s in seconds.values())
    print(f"{args.clips} clips + {args.clips} re-simulations of {STEPS} steps at {RATE:g} Hz, "
          f"medians of {args.repeats}:")
    for name, s in seconds.items():
        print(f"  {name}: {statistics.median(s):.2f} s ({', '.join(f'{x:.2f}' for x in s)})")
    print(f"speed-up {full / cheap:.2f}×; identical frames: {same}")
    if not same:
        raise SystemExit("the two paths rendered different frames")


if __name__ == "__main__":
    main()
