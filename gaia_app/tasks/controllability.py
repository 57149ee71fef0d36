"""`generate.py mode=controllability`: how well rollouts follow commanded actions and text prompts.

Protocol (gaia_app/eval/controllability.py has the metrics), all in one run:
1. Probes are trained on synthetic clips of the world with `controllability.probe_seed`.
2. Actions: `controllability.contexts` clips of the world with `context.seed` give the context; each of
   `controllability.commands` (speed and curvature presets) is commanded on the future steps.
   model   = mode=action rollouts with those commands;
   floor   = mode=video rollouts (no actions) scored against the same commands;
   ceiling = the same scenes re-simulated by the synthetic world with the commanded actions.
3. Text: each prompt of `controllability.prompts` (attribute → value) generates from text alone.
   model   = mode=text_only rollouts with the prompt;
   floor   = unconditional rollouts scored against the same targets;
   ceiling = the probe on real held-out frames that have that value.
Writes controllability.json and controllability.md (the table) into the run dir.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.data.synthetic.generate import SyntheticSample
from gaia_app.data.synthetic.scenario import Scenario
from gaia_app.eval.controllability import ProbeClips, action_error, attribute_accuracy, probe_clips, train_probes
from gaia_app.models.probes import ATTRIBUTES
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.gaia1_inputs import future_actions
from gaia_app.tasks.rollout import load_pipeline
from gaia_app.utils.run_dir import atomic_write_text

SOURCE_FPS = 25.0


def world_samples(seed: int, count: int, height: int, width: int, frames: int, rate: float,
                  scenario: Scenario | None = None, start: int = 0) -> list[SyntheticSample]:
    """Samples start..start+count-1 of the synthetic world `seed` (clip + simulation, e.g. for instance masks),
    long enough for `frames` frames at `rate`."""
    clip_len = math.ceil((frames - 1) / rate * SOURCE_FPS) + 1
    world = SyntheticClipDataset(num_clips=start + count, seed=seed, height=height, width=width, clip_len=clip_len,
                                 scenario=scenario)
    return [world.sample(i) for i in range(start, start + count)]


def world_clips(seed: int, count: int, height: int, width: int, frames: int, rate: float,
                scenario: Scenario | None = None, start: int = 0) -> list:
    """The clips of `world_samples`."""
    return [s.clip for s in world_samples(seed, count, height, width, frames, rate, scenario, start)]


def commanded_actions(contexts: ProbeClips, t0: int, frames: int, rate: float,
                      commands: list[tuple[str, str]]) -> torch.Tensor:
    """(C·N, t0 + f, 2): each context's own actions, then each command's presets from its last speed."""
    rows = []
    for speed, curvature in commands:
        for past in contexts.actions[:, :t0].numpy():
            future = future_actions(speed, curvature, frames, rate, float(past[-1, 0]))
            rows.append(np.concatenate([past, future]))
    return torch.from_numpy(np.stack(rows)).float()


def resimulate(seed: int, index: int, height: int, width: int, actions: np.ndarray, t0: int, rate: float) -> torch.Tensor:
    """The scene of clip `index` driven open-loop by per-step `actions` (t, 2) from step t0 on → frames (t, 3, H, W).

    Source frames before step t0 keep the clip's own 25 Hz actions; later ones hold the commanded action of
    their step (a step's action covers the source frames up to the next step).
    """
    frames = len(actions)
    source = world_clips(seed, 1, height, width, frames, rate, start=index)[0].actions.astype(np.float64)
    step = np.floor(np.arange(len(source)) * rate / SOURCE_FPS + 1e-9).astype(int)
    driven = np.where((step >= t0)[:, None], actions[np.minimum(step, frames - 1)], source)
    clip = world_clips(seed, 1, height, width, frames, rate, Scenario(ego_actions=driven), start=index)[0]
    return probe_clips([clip], rate, frames).frames[0]


def rollout_frames(pipeline: Gaia1Pipeline, context: torch.Tensor | None, frames: int, batch: int,
                   text: torch.Tensor | None, actions: torch.Tensor | None, generator: torch.Generator) -> torch.Tensor:
    """Rollouts of `batch` sequences (contexts (b, t0, 3, H, W) or none) → their frames (b, t, 3, H, W) at the world rate."""
    h, w = pipeline.token_grid
    if context is None:
        tokens = torch.zeros(batch, 0, h, w, dtype=torch.long)
    else:
        tokens = torch.stack([pipeline.encode(c) for c in context])
    sampled, _ = pipeline.sample_batch(tokens, frames, text, actions, None, 1, generator)
    return pipeline.render(sampled, generator)[0]


def action_table(cfg: DictConfig, pipeline: Gaia1Pipeline, probe, generator: torch.Generator) -> dict[str, Any]:
    """Ceiling / model / floor action errors over every context and command."""
    c, rate, (height, width) = cfg.controllability, pipeline.rate, pipeline.image_size
    t0, frames = cfg.context.frames, max(2, math.ceil(cfg.seconds * rate))
    total = t0 + frames
    contexts = probe_clips(world_clips(cfg.context.seed, c.contexts, height, width, total, rate), rate, total)
    commands = [tuple(cmd) for cmd in c.commands]
    commanded = commanded_actions(contexts, t0, frames, rate, commands)
    n = c.contexts
    repeat = lambda x: x.repeat(len(commands), *[1] * (x.ndim - 1))  # noqa: E731  (command-major, like `commanded`)
    model = rollout_frames(pipeline, repeat(contexts.frames[:, :t0]), frames, len(commanded), None, commanded, generator)
    floor = repeat(rollout_frames(pipeline, contexts.frames[:, :t0], frames, n, None, None, generator))
    ceiling = torch.stack([resimulate(cfg.context.seed, i % n, height, width, commanded[i].numpy(), t0, rate)
                           for i in range(len(commanded))])
    rows = {name: action_error(probe, video, commanded, t0 + 1) for name, video in
            (("ceiling (real, re-simulated)", ceiling), ("model (action-conditioned)", model), ("floor (actions dropped)", floor))}
    return {"commands": [list(cmd) for cmd in commands], "contexts": n, "scored_steps": frames - 1, "rows": rows}


def text_table(cfg: DictConfig, pipeline: Gaia1Pipeline, probe, generator: torch.Generator) -> dict[str, Any]:
    """Ceiling / model / floor accuracy per prompted attribute value."""
    c, rate, (height, width) = cfg.controllability, pipeline.rate, pipeline.image_size
    frames = max(1, math.ceil(cfg.seconds * rate))
    targets = [(attr, value) for attr, values in c.prompts.items() for value in values]
    repeats = c.text_repeats
    captions = [[c.prompt_text[attr][value]] * frames for attr, value in targets for _ in range(repeats)]
    text = pipeline.encode_text_batch(captions)
    model = rollout_frames(pipeline, None, frames, len(captions), text, None, generator)
    floor = rollout_frames(pipeline, None, frames, len(captions), None, None, generator)
    real = probe_clips(world_clips(cfg.context.seed, c.real_clips, height, width, frames, rate, start=c.contexts),
                       rate, frames)
    rows: dict[str, dict[str, float]] = {"ceiling (real frames)": {}, "model (text-prompted)": {}, "floor (no text)": {}}
    for j, (attr, value) in enumerate(targets):
        index = ATTRIBUTES[attr].index(value)
        batch = slice(j * repeats, (j + 1) * repeats)
        target = {attr: torch.full((repeats,), index)}
        has_value = real.labels[attr][:, 0] == index
        key = f"{attr}={value}"
        rows["ceiling (real frames)"][key] = (attribute_accuracy(probe, real.frames[has_value], {attr: real.labels[attr][has_value, 0]})[attr]
                                              if has_value.any() else float("nan"))
        rows["model (text-prompted)"][key] = attribute_accuracy(probe, model[batch], target)[attr]
        rows["floor (no text)"][key] = attribute_accuracy(probe, floor[batch], target)[attr]
    chance = {f"{attr}={value}": 1.0 / len(ATTRIBUTES[attr]) for attr, value in targets}
    return {"targets": [f"{a}={v}" for a, v in targets], "rollouts_per_prompt": repeats, "chance": chance, "rows": rows}


def markdown(results: dict[str, Any]) -> str:
    """The two tables of a controllability run."""
    actions = results["actions"]
    lines = ["| action adherence | speed MAE (m/s) | curvature MAE (1/m) |", "|---|---|---|"]
    lines += [f"| {name} | {row['speed_mae']:.3f} | {row['curvature_mae']:.4f} |" for name, row in actions["rows"].items()]
    text = results["text"]
    lines += ["", "| text adherence | " + " | ".join(text["targets"]) + " |", "|---" * (len(text["targets"]) + 1) + "|"]
    lines += [f"| {name} | " + " | ".join(f"{row[t]:.2f}" for t in text["targets"]) + " |" for name, row in text["rows"].items()]
    lines += ["| chance | " + " | ".join(f"{text['chance'][t]:.2f}" for t in text["targets"]) + " |"]
    return "\n".join(lines) + "\n"


def controllability(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Run the protocol of the module docstring; returns the results (also written to the run dir)."""
    pipeline = load_pipeline(cfg)
    c, rate, (height, width) = cfg.controllability, pipeline.rate, pipeline.image_size
    t = cfg.context.frames + max(2, math.ceil(cfg.seconds * rate))
    train = probe_clips(world_clips(c.probe_seed, c.probe_clips, height, width, t, rate), rate, t)
    dynamics, scene, fit = train_probes(train, c.probe_steps, seed=cfg.seed)
    generator = torch.Generator(device=pipeline.device).manual_seed(int(cfg.seed))
    results = {"probe_fit": fit, "actions": action_table(cfg, pipeline, dynamics, generator),
               "text": text_table(cfg, pipeline, scene, generator)}
    atomic_write_text(run_dir / "controllability.json", json.dumps(results, indent=2))
    atomic_write_text(run_dir / "controllability.md", markdown(results))
    return results
