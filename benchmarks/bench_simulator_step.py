"""Frames/s of the closed-loop simulator's `step`, side by side in one run (docs/benchmarks.md, "Simulator step";
issue 25, item 2).

One episode: 4 context frames, then `--steps` steps with random commands (every step past the world model's
window slides it); each step samples a frame and decodes it with the tokenizer, as `DrivingSimulator.step` does.
Paths, alternated `--repeats` times (medians):
  session         DrivingSimulator as shipped: one sampling session per episode, its KV cache kept across steps
                  (learned step embeddings re-prefill the window on each slide)
  window per step the previous implementation: every step samples through a fresh window of the last T − 1
                  frames (`Gaia1Pipeline.sample_batch` with one lead step), i.e. re-prefills every step
  full recompute  the session with the sampler's KV cache off (the whole window re-run at every token)
  session, compiled decode   (--compiled) the session with `token_sampler.decode_step=compiled`: each token after
                  a frame's first decoded by the torch.compile'd fixed-shape step on a static KV cache (issue 51)
  ..., K tokens per call     (--tokens-per-call K ...) the same step decoding K tokens per call, each token's
                  draw inside the graph from noise drawn beforehand (the same tokens)
for the shipped reference weights (learned time), and for a world model of the same layout with rotary time
(random weights: `--rope`), where a slide drops the oldest step from the cache. Real-time ratio: frames/s ÷ 6.25.

    python benchmarks/bench_simulator_step.py --steps 16 --repeats 3 --rope
    python benchmarks/bench_simulator_step.py --steps 16 --repeats 3 --full-steps 0 --compiled
    python benchmarks/bench_simulator_step.py --steps 16 --repeats 5 --full-steps 0 --compiled --profile 4
    python benchmarks/bench_simulator_step.py --steps 16 --repeats 5 --full-steps 0 --compiled --tokens-per-call 4 8
    python benchmarks/bench_simulator_step.py --steps 8 --skip 8 --repeats 5 --full-steps 0 --compiled --rope

With --skip, the shipped (learned-time) model's row also times one re-prefill of the window alone: what each slide
costs it.
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
import yaml

from gaia_app.diffusion.ar_sampling import AutoregressiveSampler, WindowStream
from gaia_app.models.gaia1.world_model import WorldModel
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.simulator import DrivingSimulator
from gaia_app.pipelines.simulator_episodes import EpisodeBatch
from gaia_app.weights.folders import shipped_folder

REAL_TIME_HZ = 6.25


class WindowPerStep(EpisodeBatch):
    """The simulator before sessions: every step samples its frame through a fresh window (re-prefill). Unprompted
    only (the episodes here have no prompt)."""

    def advance(self, actions: np.ndarray) -> torch.Tensor:
        self.actions.append(np.asarray(actions, np.float32))
        keep = min(self.tokens.shape[1], int(self.pipeline.world_model.frames) - 1)
        context = self.tokens[:, self.tokens.shape[1] - keep:]
        lead = min(1, self.tokens.shape[1] - keep)
        steps = torch.from_numpy(np.stack(self.actions[len(self.actions) - keep - 1 - lead:], axis=1))
        sampled, _ = self.pipeline.sample_batch(context, 1, None, steps, None, 1, self.generators[0], lead)
        self.tokens = torch.cat([self.tokens, sampled[:, -1:].to(self.tokens.device)], dim=1)
        return sampled[:, -1]


def window_per_step(pipeline: Gaia1Pipeline) -> DrivingSimulator:
    env = DrivingSimulator(pipeline)
    env.episodes = WindowPerStep(pipeline, env.context_frames)
    return env


def reset_and_skip(env: DrivingSimulator, steps: int, seed: int, skip: int) -> list[list[float]]:
    """Reset `env` with `seed`, take `skip` steps of random commands; → the commands of the next `steps` steps."""
    rng = np.random.default_rng(seed)
    env.reset(seed=seed, options={"index": seed})
    commands = [[rng.uniform(6, 14), rng.uniform(-0.03, 0.03)] for _ in range(skip + steps)]
    for action in commands[:skip]:
        env.step(action)
    return commands[skip:]


def episode_rate(env: DrivingSimulator, steps: int, seed: int, skip: int = 0) -> float:
    """Frames/s of `steps` steps after a reset and `skip` untimed steps (the reset's context encoding not counted).
    With skip ≥ T − context frames every timed step slides the window: the rate of a long episode."""
    commands = reset_and_skip(env, steps, seed, skip)
    start = time.perf_counter()
    for action in commands:
        env.step(action)
    return steps / (time.perf_counter() - start)


def rope_pipeline(shipped: Gaia1Pipeline) -> Gaia1Pipeline:
    """The shipped tokenizer with a random world model of the shipped layout (world_model.yaml), rotary time."""
    layout = yaml.safe_load((shipped_folder("gaia1") / "world_model.yaml").read_text())["nets"]["net"]
    layout = {k: v for k, v in layout.items() if not k.startswith("_")} | {"temporal_encoding": "rope"}
    torch.manual_seed(0)
    return Gaia1Pipeline(shipped.tokenizer, WorldModel(**layout).eval(), shipped.image_size, rate=shipped.rate)


def with_sampler(pipeline: Gaia1Pipeline, sampler: AutoregressiveSampler) -> DrivingSimulator:
    """A simulator over the same nets, sampling with `sampler`."""
    return DrivingSimulator(Gaia1Pipeline(pipeline.tokenizer, pipeline.world_model, pipeline.image_size,
                                          sampler=sampler, rate=pipeline.rate))


def paths(pipeline: Gaia1Pipeline, full: bool, compiled: bool = False,
          blocks: tuple[int, ...] = ()) -> dict[str, DrivingSimulator]:
    envs = {"session": DrivingSimulator(pipeline), "window per step": window_per_step(pipeline)}
    picker = pipeline.rollouts.sampler.picker
    if compiled:
        envs["session, compiled decode"] = with_sampler(pipeline, AutoregressiveSampler(picker, decode_step="compiled"))
    for block in blocks:
        envs[f"session, compiled decode, {block} tokens per call"] = with_sampler(
            pipeline, AutoregressiveSampler(picker, decode_step="compiled", tokens_per_call=block))
    if full:
        envs["full recompute"] = with_sampler(pipeline, AutoregressiveSampler(picker, use_cache=False))
    return envs


def window_prefill_ms(env: DrivingSimulator, repeats: int) -> dict[str, Any]:
    """Milliseconds of one re-prefill of the window, alone: what a slide costs a net with learned step embeddings
    (GAIA-1 §2.1), whose every key changes with the window's start. Run on the open session of `env` after a
    slide, whose window holds T steps: its first T − 1 in full and the last one's text, every guidance stream
    stacked on the batch (the positions a slide re-feeds), into a fresh eager KV cache. Medians of `repeats`, after
    one untimed run."""
    session = env.episodes.session
    if session is None or session.dropped_steps == 0:
        raise ValueError("window_prefill_ms times a window after a slide: step the env past T − context frames first")
    tokens, t = session.tokens, session.tokens.shape[1] - 1

    def prefill() -> float:
        start = time.perf_counter()
        with torch.no_grad():
            WindowStream(session.net, True, session.capacity).feed(session.prefill(tokens, t))
        return 1000 * (time.perf_counter() - start)

    prefill()
    runs = [prefill() for _ in range(repeats)]
    x = session.prefill(tokens, t)
    return {"ms": statistics.median(runs), "runs": runs, "positions": int(x.shape[1]), "batch": int(x.shape[0]),
            "budget_ms_at_3x": 1000 / (3 * REAL_TIME_HZ)}


def profile_table(env: DrivingSimulator, steps: int, rows: int = 12, skip: int = 0) -> str:
    """torch.profiler's operators by self CPU time over `steps` steps of a warm env (after `skip` untimed ones):
    where a step's time goes."""
    from torch.profiler import ProfilerActivity, profile

    commands = reset_and_skip(env, steps, seed=0, skip=skip)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for action in commands:
            env.step(action)
    return prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--rope", action="store_true", help="also a rotary-time world model of the shipped layout")
    parser.add_argument("--skip", type=int, default=0,
                        help="untimed steps after each reset; ≥ T − 4 (8 for the shipped weights) times only steps "
                             "that slide the window, as in a long episode")
    parser.add_argument("--full-steps", type=int, default=2, help="steps of the (slow) full-recompute path; 0: skip")
    parser.add_argument("--compiled", action="store_true", help="also the session with the compiled decode step")
    parser.add_argument("--tokens-per-call", type=int, nargs="*", default=[],
                        help="also the compiled session decoding this many tokens per call, the draw inside (each)")
    parser.add_argument("--profile", type=int, default=0,
                        help="after the timed runs, print torch.profiler's top operators over this many steps of the "
                             "session (with --compiled: of the compiled session)")
    parser.add_argument("--out", default="outputs/bench_simulator_step.json")
    args = parser.parse_args()
    shipped = Gaia1Pipeline.from_weights(shipped_folder("gaia1"), video_decoder=False)
    models = {"shipped (learned time)": shipped} | ({"rotary time (random weights)": rope_pipeline(shipped)}
                                                    if args.rope else {})
    results: dict[str, Any] = {"threads": torch.get_num_threads(), "steps": args.steps, "skip": args.skip}
    for label, pipeline in models.items():
        envs = paths(pipeline, args.full_steps > 0, args.compiled, tuple(args.tokens_per_call))
        runs: dict[str, list[float]] = {name: [] for name in envs}
        for env in envs.values():  # warm-up
            episode_rate(env, 1, seed=99)
        for repeat in range(args.repeats):  # alternated, so every path sees the same machine
            for name, env in envs.items():
                steps = args.full_steps if name == "full recompute" else args.steps
                skip = 0 if name == "full recompute" else args.skip  # its few steps are too slow to skip many
                runs[name].append(episode_rate(env, steps, seed=repeat, skip=skip))
        row = {name: {"frames_per_s": statistics.median(r), "real_time_ratio": statistics.median(r) / REAL_TIME_HZ,
                      "runs": r} for name, r in runs.items()}
        row["session_over_window_per_step"] = row["session"]["frames_per_s"] / row["window per step"]["frames_per_s"]
        if args.compiled:
            compiled_rate = row["session, compiled decode"]["frames_per_s"]
            row["compiled_over_session"] = compiled_rate / row["session"]["frames_per_s"]
        for block in args.tokens_per_call:
            name = f"session, compiled decode, {block} tokens per call"
            row[f"{block}_per_call_over_session"] = row[name]["frames_per_s"] / row["session"]["frames_per_s"]
        results[label] = row
        if args.skip and not pipeline.world_model.rolling_cache:
            row["window_prefill"] = prefill = window_prefill_ms(envs["session"], args.repeats)
            print(f"{label}: one re-prefill of the window ({prefill['batch']} × {prefill['positions']} positions) "
                  f"{prefill['ms']:.1f} ms; a whole step at 3× real time may take {prefill['budget_ms_at_3x']:.1f} ms")
        if args.profile:
            print(profile_table(envs["session, compiled decode" if args.compiled else "session"], args.profile,
                                skip=args.skip))
        for name in envs:
            print(f"{label} {name}: {row[name]['frames_per_s']:.2f} frames/s "
                  f"({row[name]['real_time_ratio']:.2f}× real time)")
        print(f"{label}: session / window per step {row['session_over_window_per_step']:.2f}×")
        if args.compiled:
            print(f"{label}: compiled decode / session {row['compiled_over_session']:.2f}×")
        for block in args.tokens_per_call:
            print(f"{label}: {block} tokens per call / session {row[f'{block}_per_call_over_session']:.2f}×")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
