"""Every speed controller of the closed loop on several sampler seeds, side by side (docs/simulator.md).

    python -m gaia_app.tasks.drive --weights gaia1 --seconds 10 --target-speed 12 --seeds 201-216 \\
        --out outputs/drive_seeds
    # other contexts: the k-th seed starts from the k-th clip of --clips (cycled) of world --world-seed
    python -m gaia_app.tasks.drive --seeds 301-308 --world-seed 5151 --clips 0-7 --controllers filtered,none

For each seed, one episode per controller of `drive.CONTROLLERS` (or of `--controllers`, which must hold "none")
from the same context (clip --clip of world --world-seed, or the seed's clip of --clips) and the same sampler
seed, so the controllers are compared on paired episodes. Scores over the last 5 s of each
episode: the mean |probed − target| speed (the score), |mean probed − target| (the offset a controller can
remove), mean |command − target|. Each controller's mean over seeds gets a 95 % percentile bootstrap interval
over seeds, and so does its paired ratio Σ error / Σ error of "none" (the context's speed held). A generated world
has no ground-truth speed: the probe is the only measurement, the command is what the world model was asked for.
Writes drive_seeds.json and prints the table.
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import torch

from gaia_app.eval.intervals import Estimate, ratio_interval
from gaia_app.pipelines.simulator import DrivingSimulator
from gaia_app.tasks.drive import BASELINE, drive, episode_options, make_keeper
from gaia_app.utils.run_dir import atomic_write_text

SCORES = ("probed_speed_error", "probed_mean_offset", "command_error")
def mean_estimate(values: list[float]) -> Estimate:
    """The mean over seeds with its 95 % percentile bootstrap interval."""
    return ratio_interval(values, [1.0] * len(values))


def summary(runs: dict[str, list[dict[str, Any]]]) -> dict[str, dict[str, Any]]:
    """Per controller: each score's mean over seeds and its ratio to the baseline's, with intervals."""
    base = runs[BASELINE]
    out: dict[str, dict[str, Any]] = {}
    for name, episodes in runs.items():
        out[name] = {score: mean_estimate([e[score] for e in episodes]).as_dict() for score in SCORES}
        out[name]["ratio_to_none"] = ratio_interval([e["probed_speed_error"] for e in episodes],
                                                    [e["probed_speed_error"] for e in base]).as_dict()
    return out


def table(rows: dict[str, dict[str, Any]]) -> str:
    """Markdown: one row per controller, mean [95 % interval] over seeds."""
    def cell(e: dict[str, float]) -> str:
        return f"{e['mean']:.2f} [{e['low']:.2f}, {e['high']:.2f}]"

    lines = ["| controller | mean abs probed − target (m/s) | abs mean probed − target (m/s) | "
             "mean abs command − target (m/s) | error ÷ none's |", "|---|---:|---:|---:|---:|"]
    for name, row in rows.items():
        lines.append(f"| {name} | {cell(row['probed_speed_error'])} | {cell(row['probed_mean_offset'])} | "
                     f"{cell(row['command_error'])} | {cell(row['ratio_to_none'])} |")
    return "\n".join(lines)


def evaluate_seeds(args: argparse.Namespace, env: DrivingSimulator, probe: torch.nn.Module,
                   steps: int) -> dict[str, Any]:
    """Run every controller of --controllers on every seed of --seeds (lists, as parse_args leaves them); write
    drive_seeds.json in --out; return its content."""
    seeds, controllers = args.seeds, args.controllers
    clips = [args.clip] if args.clips is None else args.clips
    runs: dict[str, list[dict[str, Any]]] = {name: [] for name in controllers}
    start = time.perf_counter()
    for k, seed in enumerate(seeds):
        options = episode_options(args, clips[k % len(clips)])
        for name in controllers:
            keeper = make_keeper(args, env.pipeline.rate, name)
            runs[name].append(drive(env, probe, None, steps, keeper, args.curvature, seed, progress=False,
                                    options=options))
        print(f"seed {seed}, clip {options['index']}: "
              + ", ".join(f"{n} {runs[n][-1]['probed_speed_error']:.2f}" for n in controllers)
              + f" m/s ({time.perf_counter() - start:.0f} s)", flush=True)
    rows = summary(runs)
    result = {"seeds": seeds, "target_speed": args.target_speed, "seconds": args.seconds,
              "settings": {k: getattr(args, k) for k in ("gain", "max_accel", "process_noise", "probe_noise",
                                                            "curvature", "weights", "guidance", "world_seed")},
              "clips": clips,
              "threads": torch.get_num_threads(), "summary": rows,
              "per_seed": {name: [{k: e[k] for k in ("seed", "context", *SCORES)} for e in episodes]
                           for name, episodes in runs.items()},
              "wall_s": time.perf_counter() - start}
    atomic_write_text(args.out / "drive_seeds.json", json.dumps(result, indent=2))
    print(table(rows))
    print(f"seeds {seeds[0]}..{seeds[-1]} ({len(seeds)}), {result['wall_s']:.0f} s; {args.out / 'drive_seeds.json'}")
    return result
