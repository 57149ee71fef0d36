"""Does the unprompted world model reproduce its data? The floor of the text-adherence table, per token picker.

The floor of `generate.py mode=controllability`'s text table is the share of unprompted rollouts (generated from
nothing, no text, no actions) that the scene probe reads as each value. A world model that learned its data
reproduces the data's mix, so the floor's best possible value is the data's own share of that value as the same
probe reads it. This script measures both side by side: the scene probe's reading of real clips of the default
synthetic mix (and of the same clips through the tokenizer), and of unprompted rollouts under each token picker
(GAIA-1 §5.1: top-k; nucleus top-p; the full distribution), with 95 % Wilson intervals, plus the total variation
distance of each reading from the real clips'.

    python benchmarks/floor_calibration.py --weights gaia1 --rollouts 288 --seed 13 \\
        --pickers top_k,top_p,sample --out outputs/floor_calibration

Only generator seeds are involved in the rollouts (no context clip); the real clips come from the world
`--world-seed`. Writes results.json and results.md into --out.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from tqdm import tqdm

from gaia_app.data.synthetic.export import parse_mix
from gaia_app.diffusion.ar_sampling import AutoregressiveSampler, TokenPicker
from gaia_app.eval.controllability import load_probes, probe_clips
from gaia_app.models.probes import ATTRIBUTES
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.gaia1_inputs import future_frames
from gaia_app.protocols.controllability import (
    rollout_frames,
    share_row,
    tokenized,
    world_clips,
)
from gaia_app.weights.folders import shipped_folder

SCENE = ("time_of_day", "weather")


def reading(probe, video: torch.Tensor) -> dict[str, dict[str, list[float]]]:
    """{attribute: {value: [share, low, high]}}: rollouts whose frames mostly read each value."""
    out: dict[str, dict[str, list[float]]] = {}
    for attr in SCENE:
        out[attr] = {}
        for index, value in enumerate(ATTRIBUTES[attr]):
            row = share_row(probe, video, attr, index)
            out[attr][value] = [round(row["mean"], 3), round(row["low"], 3), round(row["high"], 3)]
    return out


def total_variation(a: dict[str, list[float]], b: dict[str, list[float]]) -> float:
    return round(0.5 * sum(abs(a[v][0] - b[v][0]) for v in a), 3)


def unprompted(folder: Path, picker: TokenPicker, count: int, frames: int, seed: int, batch: int) -> torch.Tensor:
    """(count, frames, 3, H, W) rollouts from nothing of the weights in `folder`, tokens drawn by `picker`."""
    pipeline = Gaia1Pipeline.from_weights(folder, video_decoder=False,
                                          sampler=AutoregressiveSampler(picker, progress=False))
    generator = torch.Generator(device=pipeline.device).manual_seed(seed)
    parts = [rollout_frames(pipeline, None, frames, min(batch, count - start), None, None, generator)
             for start in tqdm(range(0, count, batch), desc=f"{picker.mode} rollouts")]
    return torch.cat(parts)


def markdown(results: dict) -> str:
    lines = [f"Unprompted rollouts ({results['rollouts']} per picker, generator seed {results['seed']}) and real clips "
             f"of the {results.get('time_of_day_mix') or 'default'} mix ({results['real_clips']}, world "
             f"{results['world_seed']}) as the scene probe reads "
             "them; share [95 % Wilson interval]; TV: total variation distance from the real clips' reading.", ""]
    for attr in SCENE:
        values = list(ATTRIBUTES[attr])
        lines += [f"| {attr} | " + " | ".join(values) + " | TV |", "|---" * (len(values) + 2) + "|"]
        for name, row in results["rows"].items():
            cells = [f"{row[attr][v][0]:.2f} [{row[attr][v][1]:.2f}, {row[attr][v][2]:.2f}]" for v in values]
            lines.append(f"| {name} | " + " | ".join(cells) + f" | {results['tv'][name][attr]:.3f} |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--weights", default="gaia1")
    parser.add_argument("--rollouts", type=int, default=288)
    parser.add_argument("--seed", type=int, default=13)
    parser.add_argument("--world-seed", type=int, default=3013)
    parser.add_argument("--real-clips", type=int, default=288)
    parser.add_argument("--time-of-day-mix", help="the real clips' mix, e.g. the weights' training mix "
                        "'day=0.7,dusk=0.2,night=0.1' (default: the synthetic world's)")
    parser.add_argument("--pickers", default="top_k,top_p,sample")
    parser.add_argument("--k", type=int, default=50)
    parser.add_argument("--p", type=float, default=0.9)
    parser.add_argument("--seconds", type=float, default=1.25)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--out", type=Path, default=Path("outputs/floor_calibration"))
    args = parser.parse_args()

    folder = shipped_folder(args.weights)
    pipeline = Gaia1Pipeline.from_weights(folder, video_decoder=False)
    _, scene, _ = load_probes(folder / "probes", tuple(pipeline.image_size), float(pipeline.rate))
    frames = future_frames(args.seconds, pipeline.rate)
    height, width = pipeline.image_size
    start = time.time()
    mix = {"time_of_day_mix": parse_mix(args.time_of_day_mix)} if args.time_of_day_mix else None
    real = probe_clips(world_clips(args.world_seed, args.real_clips, height, width, frames, pipeline.rate, mix=mix),
                       pipeline.rate, frames).frames
    real_row = f"real clips ({args.time_of_day_mix or 'default'} mix)"
    rows = {real_row: reading(scene, real),
            "real clips through the tokenizer": reading(scene, tokenized(pipeline, real))}
    for mode in args.pickers.split(","):
        picker = TokenPicker(mode, k=args.k, p=args.p)
        label = {"top_k": f"top_k k={args.k}", "top_p": f"top_p p={args.p}", "sample": "sample (full)"}.get(mode, mode)
        rows[label] = reading(scene, unprompted(folder, picker, args.rollouts, frames, args.seed, args.batch))
    reference = rows[real_row]
    results = {"time_of_day_mix": args.time_of_day_mix, "rollouts": args.rollouts, "seed": args.seed,
               "world_seed": args.world_seed, "real_clips": args.real_clips, "frames": frames,
               "minutes": round((time.time() - start) / 60, 1), "rows": rows,
               "tv": {name: {attr: total_variation(row[attr], reference[attr]) for attr in SCENE}
                      for name, row in rows.items()}}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    (args.out / "results.md").write_text(markdown(results))
    print(markdown(results))


if __name__ == "__main__":
    main()
