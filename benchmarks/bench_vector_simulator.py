"""Throughput of N episodes in one vector env against N single envs stepped one after another, side by side in one
run (docs/benchmarks.md, "Vector simulator"; issue 53, item 4).

Both paths drive the same N episodes: seeds s + i, clip 0 of world 1000, 4 context frames, then `--steps` steps
of the same random commands (every step past the world model's window slides it: with the shipped weights'
learned time each slide re-prefills the window, as in a long episode). The vector env (`VectorDrivingSimulator`)
makes one batched world-model forward per image token for all N; the singles (`DrivingSimulator`) make N.
Throughput is env-steps per second (N × steps ÷ wall time, the reset's context encoding not counted), alternated
`--repeats` times (medians). The run also checks that both paths sampled the same tokens.

    OMP_NUM_THREADS=1 python benchmarks/bench_vector_simulator.py --envs 8 --steps 24 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.simulator import DrivingSimulator
from gaia_app.pipelines.vector_simulator import VectorDrivingSimulator
from gaia_app.weights.folders import shipped_folder


def command_batches(steps: int, envs: int, seed: int) -> list[np.ndarray]:
    """`steps` random command batches (envs, 2) float32: 6–14 m/s, |curvature| ≤ 0.03 1/m."""
    rng = np.random.default_rng(seed)
    return [np.stack([rng.uniform(6, 14, envs), rng.uniform(-0.03, 0.03, envs)], -1).astype(np.float32)
            for _ in range(steps)]


def vector_run(envs: VectorDrivingSimulator, commands: list[np.ndarray], seed: int) -> tuple[float, np.ndarray]:
    """(env-steps/s, the last tokens (N, h, w)) of one vector episode."""
    envs.reset(seed=seed)
    start = time.perf_counter()
    for batch in commands:
        *_, infos = envs.step(batch)
    return envs.num_envs * len(commands) / (time.perf_counter() - start), infos["tokens"]


def singles_run(singles: list[DrivingSimulator], commands: list[np.ndarray], seed: int) -> tuple[float, np.ndarray]:
    """(env-steps/s, the last tokens (N, h, w)) of N single episodes, each step taken env after env."""
    for i, env in enumerate(singles):
        env.reset(seed=seed + i)
    start = time.perf_counter()
    for batch in commands:
        infos = [env.step(action)[4] for env, action in zip(singles, batch)]
    return len(singles) * len(commands) / (time.perf_counter() - start), np.stack([i["tokens"] for i in infos])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--envs", type=int, default=8)
    parser.add_argument("--steps", type=int, default=24)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="outputs/bench_vector_simulator.json")
    args = parser.parse_args()
    pipeline = Gaia1Pipeline.from_weights(shipped_folder("gaia1"), video_decoder=False)
    vector = VectorDrivingSimulator(pipeline, args.envs, max_steps=args.steps)
    singles = [DrivingSimulator(pipeline, max_steps=args.steps) for _ in range(args.envs)]
    vector_run(vector, command_batches(1, args.envs, 99), 99)  # warm-up
    singles_run(singles, command_batches(1, args.envs, 99), 99)
    runs: dict[str, list[float]] = {"vector": [], "singles": []}
    same = []
    for repeat in range(args.repeats):  # alternated, so both paths see the same machine
        commands = command_batches(args.steps, args.envs, repeat)
        rate, vector_tokens = vector_run(vector, commands, seed=10 * repeat)
        runs["vector"].append(rate)
        rate, single_tokens = singles_run(singles, commands, seed=10 * repeat)
        runs["singles"].append(rate)
        same.append(bool(np.array_equal(vector_tokens, single_tokens)))
    results: dict[str, Any] = {
        "threads": torch.get_num_threads(), "envs": args.envs, "steps": args.steps, "repeats": args.repeats,
        **{name: {"env_steps_per_s": statistics.median(r), "runs": r} for name, r in runs.items()},
        "same_tokens": same}
    results["vector_over_singles"] = results["vector"]["env_steps_per_s"] / results["singles"]["env_steps_per_s"]
    print(f"N = {args.envs}, {args.steps} steps, {results['threads']} thread(s): vector "
          f"{results['vector']['env_steps_per_s']:.2f} env-steps/s, singles {results['singles']['env_steps_per_s']:.2f}"
          f" env-steps/s, ratio {results['vector_over_singles']:.2f}×; same tokens in every repeat: {all(same)}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
