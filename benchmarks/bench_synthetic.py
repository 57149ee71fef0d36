"""Throughput of the synthetic world on one CPU thread.

    python benchmarks/bench_synthetic.py                       # 64x112 and 288x512, 1 and 5 cameras
    python benchmarks/bench_synthetic.py --sizes 448x960 --clips 4

Two numbers per setting, in frames per second per camera:
  render   drawing only (sky, ground, objects, weather) for already simulated frames
  clip     end to end: plan, simulate, render, labels and captions (what SyntheticClipDataset pays)
Everything runs single-threaded (cv2.setNumThreads(1), torch.set_num_threads(1)); the clips are
the dataset's own random mix of environments, weather and times of day.
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
import torch

from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.data.synthetic.generate import sample_from_rng


def parse_size(text: str) -> tuple[int, int]:
    height, width = (int(v) for v in text.lower().split("x"))
    return height, width


def bench(height: int, width: int, cameras: int, clips: int, frames: int, seed: int) -> tuple[float, float]:
    """(render frames/s per camera, end-to-end frames/s per camera)."""
    ds = SyntheticClipDataset(num_clips=clips, seed=seed, height=height, width=width, cameras=cameras, clip_len=frames)
    start = time.perf_counter()
    samples = [sample_from_rng(np.random.default_rng([seed, i]), ds.config) for i in range(clips)]
    clip_seconds = time.perf_counter() - start
    start = time.perf_counter()
    for sample in samples:
        for t, state in enumerate(sample.states):
            sample.renderer.render(state, t)
    render_seconds = time.perf_counter() - start
    views = clips * frames * cameras
    return views / render_seconds, views / clip_seconds


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", nargs="+", default=["64x112", "288x512"], help="HxW image sizes")
    p.add_argument("--cameras", nargs="+", type=int, default=[1, 5])
    p.add_argument("--clips", type=int, default=8)
    p.add_argument("--frames", type=int, default=16, help="frames per clip")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    cv2.setNumThreads(1)
    torch.set_num_threads(1)
    print(f"{'size':>9} {'cameras':>7} {'render fps/cam':>15} {'clip fps/cam':>13}")
    for size in args.sizes:
        height, width = parse_size(size)
        for cameras in args.cameras:
            render_fps, clip_fps = bench(height, width, cameras, args.clips, args.frames, args.seed)
            print(f"{size:>9} {cameras:>7} {render_fps:>15.1f} {clip_fps:>13.1f}")


if __name__ == "__main__":
    main()
