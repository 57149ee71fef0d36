"""Can the controllability probes read the controls? Model-free check of gaia_app/protocols/controllability.py.

Trains the probes as `generate.py mode=controllability` does, then scores held-out synthetic contexts without any
world model: the ceiling (scenes re-simulated with each commanded action) against the reference (the real
continuation, which ignores the commands), and the scene probe's accuracy on real frames of every value.
The probes can judge adherence when ceiling ≤ ½ reference (speed and curvature contrast errors) and accuracy ≥ 0.9.

    python benchmarks/probe_quality.py --out outputs/probes_64x112        # the demo's 64×112, 6.25 Hz
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch

from gaia_app.eval.controllability import probe_clips, save_probes, train_probes
from gaia_app.models.probes import ATTRIBUTES
from gaia_app.protocols.controllability import (
    CONTRASTS,
    commanded_actions,
    error_row,
    probe_training_data,
    resimulate,
    share_row,
    world_clips,
)

COMMANDS = [("brake", "straight"), ("accelerate", "straight"), ("keep", "left"), ("keep", "right")]
METRICS = (*CONTRASTS, "speed_mae", "curvature_mae")


def action_rows(args, dynamics) -> dict:
    t0, frames = args.context_frames, max(2, math.ceil(args.seconds * args.rate))
    total = t0 + frames
    contexts = probe_clips(world_clips(args.context_seed, args.contexts, args.height, args.width, total, args.rate),
                           args.rate, total)
    commanded = commanded_actions(contexts, t0, frames, args.rate, COMMANDS)
    n = args.contexts
    ceiling = torch.cat([resimulate(args.context_seed, i % n, args.height, args.width, commanded[i].numpy(), t0,
                                    args.rate).frames for i in range(len(commanded))])
    reference = contexts.frames.repeat(len(COMMANDS), 1, 1, 1, 1)
    return {name: error_row(dynamics, video, commanded, t0 + 1, len(COMMANDS))
            for name, video in (("ceiling", ceiling), ("reference", reference))}


def scene_rows(args, scene) -> dict:
    frames = max(1, math.ceil(args.seconds * args.rate))
    real = probe_clips(world_clips(args.context_seed, args.real_clips, args.height, args.width, frames, args.rate,
                                   start=args.contexts, balanced=True), args.rate, frames)
    rows = {}
    for attr, values in (("time_of_day", ATTRIBUTES["time_of_day"]), ("weather", ATTRIBUTES["weather"])):
        for index, value in enumerate(values):
            has = real.labels[attr][:, 0] == index
            if has.any():
                rows[f"{attr}={value}"] = share_row(scene, real.frames[has], attr, index)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="folder for probes/ and probe_quality.json")
    parser.add_argument("--height", type=int, default=64)
    parser.add_argument("--width", type=int, default=112)
    parser.add_argument("--rate", type=float, default=6.25)
    parser.add_argument("--context-frames", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=1.0)
    parser.add_argument("--probe-seed", type=int, default=4242)
    parser.add_argument("--probe-clips", type=int, default=256)
    parser.add_argument("--probe-steps", type=int, default=1500)
    parser.add_argument("--driven-share", type=float, default=0.5)
    parser.add_argument("--context-seed", type=int, default=1000)
    parser.add_argument("--contexts", type=int, default=32)
    parser.add_argument("--real-clips", type=int, default=48)
    parser.add_argument("--seed", type=int, default=42)
    args = parser.parse_args()
    torch.set_num_threads(max(1, torch.get_num_threads()))
    frames = args.context_frames + max(2, math.ceil(args.seconds * args.rate))
    start = time.perf_counter()
    data = probe_training_data(args.probe_seed, args.probe_clips, args.height, args.width, frames, args.rate,
                               args.driven_share)
    rendered = time.perf_counter()
    dynamics, scene, fit = train_probes(data, args.probe_steps, seed=args.seed)
    trained = time.perf_counter()
    info = {"image_size": [args.height, args.width], "rate": args.rate, "frames": frames, "probe_seed": args.probe_seed,
            "probe_clips": args.probe_clips, "probe_steps": args.probe_steps, "driven_share": args.driven_share,
            "fit": fit}
    save_probes(args.out / "probes", dynamics, scene, info)
    results = {"probes": info, "actions": action_rows(args, dynamics), "scene": scene_rows(args, scene),
               "seconds": {"render_training_clips": rendered - start, "train": trained - rendered,
                           "evaluate": time.perf_counter() - trained}}
    (args.out / "probe_quality.json").write_text(json.dumps(results, indent=2))
    half = lambda e: (e["high"] - e["low"]) / 2  # noqa: E731
    for name, row in results["actions"].items():
        print(f"{name:10s} " + "  ".join(f"{m} {row[m]['mean']:.4f} ± {half(row[m]):.4f}" for m in METRICS))
    ceiling, reference = results["actions"]["ceiling"], results["actions"]["reference"]
    for metric in METRICS:
        print(f"{metric}: ceiling / reference = {ceiling[metric]['mean'] / reference[metric]['mean']:.2f}"
              + (" (need ≤ 0.5)" if metric in CONTRASTS else " (diagnostic)"))
    for key, row in results["scene"].items():
        print(f"{key:20s} frame accuracy {row['frame_accuracy']:.3f}  clips {row['n']}")
    print("seconds", {k: round(v, 1) for k, v in results["seconds"].items()})


if __name__ == "__main__":
    main()
