"""`generate.py mode=controllability`: how well rollouts follow commanded actions and text prompts.

Protocol (gaia_app/eval/controllability.py has the metrics, gaia_app/eval/intervals.py the 95 % intervals), in
one run:
1. Probes: loaded from `controllability.probes` (a folder written by an earlier run), or trained on clips of
   the world `controllability.probe_seed` (weather and time of day drawn uniformly; `driven_share` of the clips
   leave the policy at a random step and follow a random open-loop command, the situation the ceiling
   re-simulates) and saved to the run dir's probes/.
2. Actions: `controllability.contexts` clips of the world `context.seed` give the contexts; each command of
   `controllability.commands` (speed and curvature presets) is commanded on the future steps.
   ceiling   = the same scenes re-simulated by the synthetic world with the commanded actions;
   tokenized = the ceiling's frames encoded and decoded by the tokenizer: the best a world model over these
               tokens can show (a diagnostic; targets use the ceiling);
   model     = mode=action rollouts with those commands; with `controllability.shared_noise` the futures of one
               context share their sampling noise across commands (counterfactual futures, as the ceiling's
               re-simulations share their world), so their difference is the commands' and not sampling luck;
   floor     = mode=video rollouts (no actions) scored against the same commands;
   reference = the real continuation under the clip's own policy, scored against the same commands: what a
               perfect model that ignored the commands would score. It checks the probes without any model:
               they can judge adherence only if the ceiling's error is at most half of it.
   Intervals are over contexts (each context's error averaged over the commands).
   Fidelity (`controllability.fidelity`): the tokenized, model and floor futures and the held last context frame
   against the ceiling's real continuations: psnr / ssim / lpips per frame, fvmd / fid / fdd between the sets.
3. Text: each prompt of `controllability.prompts` (attribute → values) generates from text alone.
   ceiling = real held-out clips that have the value (world drawn uniformly over weather and time of day);
   tokenized = those clips encoded and decoded by the tokenizer (a diagnostic, as above);
   model   = mode=text_only rollouts with the prompt;
   floor   = unconditional rollouts (one shared set of `controllability.floor_repeats`, generated in batches of
             text_repeats) scored against each target.
   A rollout (or real clip) reads a value when most of its frames are probed as that value; the table gives
   the share of rollouts that read the prompted value, with Wilson intervals.
Writes controllability.json, controllability.md and probes/ into the run dir.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from gaia_app.data.clip import Clip
from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.data.synthetic.commands import command_profile, draw_command
from gaia_app.data.synthetic.generate import SyntheticSample
from gaia_app.data.synthetic.scenario import TIMES_OF_DAY, WEATHERS, Scenario
from gaia_app.eval.controllability import (
    ProbeClips,
    attribute_shares,
    cat_probe_clips,
    contrast_errors,
    contrast_pairs,
    load_probes,
    phase_clips,
    probe_clips,
    probed_actions,
    realised_contrasts,
    save_probes,
    strided_actions,
    train_probes,
)
from gaia_app.eval.intervals import mean_interval, share_interval
from gaia_app.models.probes import ATTRIBUTES
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.gaia1_inputs import future_actions, future_frames
from gaia_app.protocols.fidelity import check_metrics, fidelity_table, held_frame, table_markdown
from gaia_app.protocols.loading import load_pipeline
from gaia_app.utils.run_dir import atomic_write_text
from gaia_app.weights.folders import shipped_folder

SOURCE_FPS = 25.0
FIDELITY_SETTINGS = "controllability.fidelity"
# the adherence metrics with targets: contrast errors of speed (accelerate vs brake) and curvature (left vs right)
CONTRASTS = ("speed_contrast", "curvature_contrast")
# every weather and time of day equally often: probes see enough snow and night, ceilings have clips of each value
UNIFORM_MIX = {"weather_mix": dict.fromkeys(WEATHERS, 1.0), "time_of_day_mix": dict.fromkeys(TIMES_OF_DAY, 1.0)}


def world(seed: int, count: int, height: int, width: int, frames: int, rate: float, scenario: Scenario | None = None,
          balanced: bool = False, mix: Mapping[str, Mapping[str, float]] | None = None,
          every_frame: bool = True) -> SyntheticClipDataset:
    """Clips 0..count-1 of the synthetic world `seed`, long enough for `frames` frames at `rate`.
    balanced: weather and time of day drawn uniformly instead of the world's default mix; mix: other
    {"weather_mix": ..., "time_of_day_mix": ...} (e.g. a training run's). every_frame=False renders only the frames
    at `rate` (the same frames resampling would keep; a quarter of the rendering at 6.25 Hz)."""
    clip_len = math.ceil((frames - 1) / rate * SOURCE_FPS) + 1
    return SyntheticClipDataset(num_clips=count, seed=seed, height=height, width=width, clip_len=clip_len,
                                scenario=scenario, render_rate=None if every_frame else rate,
                                **(UNIFORM_MIX if balanced else dict(mix or {})))


def world_samples(seed: int, count: int, height: int, width: int, frames: int, rate: float,
                  scenario: Scenario | None = None, start: int = 0) -> list[SyntheticSample]:
    """Samples start..start+count-1 of the synthetic world `seed` (clip + simulation, e.g. for instance masks)."""
    clips = world(seed, start + count, height, width, frames, rate, scenario)
    return [clips.sample(i) for i in range(start, start + count)]


def world_clips(seed: int, count: int, height: int, width: int, frames: int, rate: float,
                start: int = 0, balanced: bool = False, mix: Mapping[str, Mapping[str, float]] | None = None) -> list:
    """The clips start..start+count-1 of the synthetic world `seed`."""
    clips = world(seed, start + count, height, width, frames, rate, balanced=balanced, mix=mix, every_frame=False)
    return [clips[i] for i in range(start, start + count)]


def drive(source: np.ndarray, actions: np.ndarray, t0: int, rate: float) -> np.ndarray:
    """25 Hz actions (T, 2): the source's own before step t0, then the per-step `actions` (t, 2) of each step
    (a step's action covers the source frames up to the next step)."""
    step = np.floor(np.arange(len(source)) * rate / SOURCE_FPS + 1e-9).astype(int)
    return np.where((step >= t0)[:, None], actions[np.minimum(step, len(actions) - 1)], source)


def driven_clip(seed: int, index: int, height: int, width: int, actions: np.ndarray, t0: int, rate: float,
                balanced: bool = False, every_frame: bool = True) -> Clip:
    """Clip `index` of the world `seed`, its scene driven open-loop by per-step `actions` (t, 2) from step t0 on
    (every_frame=False: only the frames at `rate` rendered, see `world`)."""
    frames = len(actions)
    source = world(seed, index + 1, height, width, frames, rate, balanced=balanced).simulated_actions(index)
    driven = Scenario(ego_actions=drive(source.astype(np.float64), actions, t0, rate))
    return world(seed, index + 1, height, width, frames, rate, driven, balanced, every_frame=every_frame)[index]


def resimulate(seed: int, index: int, height: int, width: int, actions: np.ndarray, t0: int, rate: float) -> ProbeClips:
    """The `driven_clip` at `rate`: what a perfect model would show for these actions."""
    clip = driven_clip(seed, index, height, width, actions, t0, rate, every_frame=False)
    return probe_clips([clip], rate, len(actions))


def commanded_actions(contexts: ProbeClips, t0: int, frames: int, rate: float,
                      commands: list[tuple[str, str]]) -> torch.Tensor:
    """(C·N, t0 + f, 2): each context's own actions, then each command's presets from its last speed (command-major)."""
    rows = []
    for speed, curvature in commands:
        for past in contexts.actions[:, :t0].numpy():
            future = future_actions(speed, curvature, frames, rate, float(past[-1, 0]))
            rows.append(np.concatenate([past, future]))
    return torch.from_numpy(np.stack(rows)).float()


def random_command(rng: np.random.Generator, source: np.ndarray, t0: int, frames: int, rate: float) -> np.ndarray:
    """(frames, 2) per-step actions: the source's own (25 Hz, sampled at each step) before t0, then a random constant
    acceleration and curvature (gaia_app/data/synthetic/commands.py) from the speed at step t0 − 1."""
    own = source[np.minimum(np.round(np.arange(frames) * SOURCE_FPS / rate).astype(int), len(source) - 1)]
    acceleration, curvature = draw_command(rng)
    future = command_profile(float(own[t0 - 1, 0]), acceleration, curvature, frames - t0, 1.0 / rate)
    return np.concatenate([own[:t0], future]).astype(np.float64)


def probe_training_data(seed: int, count: int, height: int, width: int, frames: int, rate: float,
                        driven_share: float) -> ProbeClips:
    """Every phase (gaia_app.eval.controllability.phase_clips) of `count` clips of the world `seed` (weather and time
    of day uniform): `frames` steps at `rate` each. `driven_share` of the clips switch at a random step t0 ∈
    [1, frames − 1] to a random open-loop command."""
    rng = np.random.default_rng([seed, 1])
    clips = world(seed, count, height, width, frames + 1, rate, balanced=True)  # + 1 step: room for every phase
    parts = []
    for i in range(count):
        if rng.random() < driven_share:
            t0 = int(rng.integers(1, frames))
            actions = random_command(rng, clips.simulated_actions(i).astype(np.float64), t0, frames + 1, rate)
            clip = driven_clip(seed, i, height, width, actions, t0, rate, balanced=True)
        else:
            clip = clips[i]
        parts.append(phase_clips(clip, rate, frames))
    return cat_probe_clips(parts)


def probes_for(cfg: DictConfig, pipeline: Gaia1Pipeline, frames: int, run_dir: Path) -> tuple[Any, Any, dict]:
    """Load `controllability.probes`, or train probes for this pipeline's image size and rate and save them."""
    c, size, rate = cfg.controllability, tuple(pipeline.image_size), float(pipeline.rate)
    if c.probes:
        return load_probes(c.probes, size, rate)
    if cfg.get("weights"):  # shipped weights carry the probes they were measured with
        return load_probes(shipped_folder(cfg.weights) / "probes", size, rate)
    data = probe_training_data(c.probe_seed, c.probe_clips, *size, frames, rate, c.driven_share)
    dynamics, scene, fit = train_probes(data, c.probe_steps, seed=cfg.seed)
    info = {"image_size": list(size), "rate": rate, "frames": frames, "probe_seed": int(c.probe_seed),
            "probe_clips": int(c.probe_clips), "probe_steps": int(c.probe_steps), "driven_share": float(c.driven_share),
            "fit": fit}
    save_probes(run_dir / "probes", dynamics, scene, info)
    return dynamics, scene, info


def rollout_frames(pipeline: Gaia1Pipeline, context: torch.Tensor | None, frames: int, batch: int,
                   text: torch.Tensor | None, actions: torch.Tensor | None, generator: torch.Generator,
                   noise_groups: torch.Tensor | None = None) -> torch.Tensor:
    """Rollouts of `batch` sequences (contexts (b, t0, 3, H, W) or none) → their frames (b, t, 3, H, W) at the world
    rate. noise_groups (b,) int64: sequences that share their sampling noise (None: each its own)."""
    h, w = pipeline.token_grid
    if context is None:
        tokens = torch.zeros(batch, 0, h, w, dtype=torch.long)
    else:
        tokens = torch.stack([pipeline.encode(c) for c in context])
    sampled, _ = pipeline.sample_batch(tokens, frames, text, actions, None, 1, generator, noise_groups=noise_groups)
    return pipeline.render(sampled, generator)[0]


def tokenized(pipeline: Gaia1Pipeline, video: torch.Tensor, tokens: torch.Tensor | None = None) -> torch.Tensor:
    """Real frames (b, t, 3, H, W) → the same frames encoded and decoded by the tokenizer, frame by frame
    (`tokens`: their tokens (b, t, h, w), when already encoded)."""
    if len(video) == 0:
        return video
    tokens = torch.stack([pipeline.encode(clip) for clip in video]) if tokens is None else tokens
    return pipeline.tokenizer_frames(tokens)


def future_nats(pipeline: Gaia1Pipeline, tokens: torch.Tensor, actions: torch.Tensor, t0: int) -> torch.Tensor:
    """(b,) mean nats/token of frames t0.. of `tokens` (b, t, h, w) given the frames before them and `actions`
    (b, t, 2): teacher-forced and unguided."""
    cond = pipeline.rollouts.conditions(len(tokens), tokens.shape[1], None, actions.float().to(pipeline.device))
    return pipeline.frame_log_perplexity(tokens.to(pipeline.device), cond, t0)[:, t0:].mean(dim=1)


def command_discrimination(pipeline: Gaia1Pipeline, real: torch.Tensor, commanded: torch.Tensor, t0: int,
                           pairs: list[tuple[int, int]]) -> dict[str, Any]:
    """Do the world model's predictions follow the commands? Per contrasted pair (high, low) and context: nats/token
    of each of the two real futures given the other command minus given its own, averaged over the two (> 0: the
    right command explains the real future better; 0: the commands are ignored). Teacher-forced and unguided, so it
    has none of the rollouts' sampling noise. real (C, N, t, h, w): tokens of the re-simulated futures of C commands;
    commanded (C, N, t, 2)."""
    rows = {}
    for name, (high, low) in zip(CONTRASTS, pairs):
        own = [future_nats(pipeline, real[i], commanded[i], t0) for i in (high, low)]
        other = [future_nats(pipeline, real[i], commanded[j], t0) for i, j in ((high, low), (low, high))]
        gain = (other[0] - own[0] + other[1] - own[1]) / 2
        rows[name] = mean_interval(gain.tolist()).as_dict() | {"own_nats": float((own[0] + own[1]).mean() / 2)}
    return rows


def error_row(probe, video: torch.Tensor, commanded: torch.Tensor, start: int, commands: int,
              stride: int = 1, draws: int = 1) -> dict[str, Any]:
    """Of a command-major batch, with 95 % intervals over contexts: the contrast errors (speed: accelerate vs
    brake, curvature: left vs right, gaia_app.eval.controllability.contrast_errors), the MAE against every command,
    and the MAE per command. The probe reads frame pairs `stride` apart (eval.controllability.strided_actions).

    video (C·N·draws, f, 3, H, W): command-major, then context, then `draws` futures of each context sampled with
    other noise; commanded (C·N, f, 2). A context's scores are the means over its draws, so the intervals stay over
    contexts (draws of one context are not independent) while the sampling noise in each context's score shrinks."""
    if draws < 1 or len(video) != len(commanded) * draws:
        raise ValueError(f"error_row: {len(video)} videos for {len(commanded)} commanded futures × {draws} draws")
    commanded = commanded.repeat_interleave(draws, dim=0)
    probed = probed_actions(probe, video, start, stride).unflatten(0, (commands, -1))  # (C, N·D, s, 2)
    wanted = strided_actions(commanded, stride)[:, start - 1 : -1].unflatten(0, (commands, -1))
    errors = by_context((probed - wanted).abs().mean(dim=2).transpose(0, 1), draws).transpose(0, 1)  # (C, N, 2)
    per_context = errors.mean(dim=0)
    contrast = by_context(contrast_errors(probed, wanted), draws)
    # per_context: for differences paired by context between runs on the same contexts (other weights or guidance)
    row = {name: mean_interval(contrast[:, k].tolist()).as_dict() | {"per_context": contrast[:, k].tolist()}
           for k, name in enumerate(CONTRASTS)}
    realised, commanded_difference = (by_context(x, draws) for x in realised_contrasts(probed, wanted))
    spread = realised.std(dim=0) if len(realised) > 1 else torch.zeros(2)
    # per_context: kept so that runs with other sampling seeds can split the spread into within- and between-context
    row["realised"] = {name: mean_interval(realised[:, k].tolist()).as_dict() | {
        "sd": float(spread[k]), "commanded": float(commanded_difference[:, k].mean()),
        "per_context": realised[:, k].tolist()}
        for k, name in enumerate(CONTRASTS)}
    row |= {name: mean_interval(per_context[:, k].tolist()).as_dict()
            for k, name in enumerate(("speed_mae", "curvature_mae"))}
    row["per_command"] = errors.mean(dim=1).tolist()
    row["draws"] = draws
    return row


def by_context(scores: torch.Tensor, draws: int) -> torch.Tensor:
    """(N, ...) means over each context's `draws` consecutive rows of (N·draws, ...)."""
    return scores.unflatten(0, (-1, draws)).mean(dim=1)


def action_table(cfg: DictConfig, pipeline: Gaia1Pipeline, probe, generator: torch.Generator) -> dict[str, Any]:
    """Ceiling / model / floor / reference action errors over every context and command, with targets."""
    c, rate, (height, width) = cfg.controllability, pipeline.rate, pipeline.image_size
    t0, frames = cfg.context.frames, future_frames(cfg.seconds, rate, at_least=2)
    total = t0 + frames
    contexts = probe_clips(world_clips(cfg.context.seed, c.contexts, height, width, total, rate), rate, total)
    commands = [tuple(cmd) for cmd in c.commands]
    commanded = commanded_actions(contexts, t0, frames, rate, commands)
    pairs = contrast_pairs(commanded[:, t0:-1].unflatten(0, (len(commands), -1)))  # fails before any rollout
    n = c.contexts
    repeat = lambda x: x.repeat(len(commands), *[1] * (x.ndim - 1))  # noqa: E731  (command-major, like `commanded`)
    ceiling = torch.cat([resimulate(cfg.context.seed, i % n, height, width, commanded[i].numpy(), t0, rate).frames
                         for i in range(len(commanded))])
    real_tokens = torch.stack([pipeline.encode(clip) for clip in ceiling])
    videos = {
        "ceiling": ceiling,
        "tokenized": tokenized(pipeline, ceiling, real_tokens),
        "model": rollout_frames(pipeline, repeat(contexts.frames[:, :t0]), frames, len(commanded), None, commanded,
                                generator, context_groups(len(commands), n) if c.shared_noise else None),
        "floor": repeat(rollout_frames(pipeline, contexts.frames[:, :t0], frames, n, None, None, generator)),
        "reference": repeat(contexts.frames),
    }
    rows = {name: error_row(probe, video, commanded, t0 + 1, len(commands)) for name, video in videos.items()}
    contrasted = {metric: ["/".join(commands[high]), "/".join(commands[low])]
                  for metric, (high, low) in zip(CONTRASTS, pairs)}
    per_command = (len(commands), n)
    discrimination = command_discrimination(pipeline, real_tokens.unflatten(0, per_command),
                                            commanded.unflatten(0, per_command), t0, pairs)
    return {"commands": [list(cmd) for cmd in commands], "contexts": n, "scored_steps": frames - 1, "rows": rows,
            "contrasts": contrasted, "checks": action_checks(rows), "discrimination": discrimination,
            "fidelity": fidelity_rows(c.fidelity, videos, t0)}


FIDELITY_ROWS = {"tokenized": "tokenized real (ceiling)", "model": "model (rollouts)", "floor": "no actions (floor)",
                 "held": "held last context frame"}


def fidelity_rows(settings: DictConfig, videos: dict[str, torch.Tensor], t0: int) -> dict[str, Any]:
    """Each row's futures (C·N, T, 3, H, W) against the real continuations under the same commands (the ceiling's
    re-simulations), with the metrics of `controllability.fidelity` (issue 49 item 4)."""
    candidates = {**{key: videos[key] for key in ("tokenized", "model", "floor")},
                  "held": held_frame(videos["ceiling"], t0)}
    return fidelity_table(settings, FIDELITY_SETTINGS, videos["ceiling"], candidates, t0)


def check_fidelity(settings: DictConfig) -> None:
    """Named errors before any work: unknown metrics, missing local weights; agent_iou needs masks this protocol
    does not have (mode=evaluate scores it)."""
    check_metrics(settings, FIDELITY_SETTINGS)
    if "agent_iou" in settings.metrics:
        raise ValueError(f"{FIDELITY_SETTINGS}.metrics has agent_iou: the controllability table has no agent masks; "
                         "mode=evaluate scores it")


def context_groups(commands: int, contexts: int) -> torch.Tensor:
    """Noise groups (C·N,) of a command-major batch: the futures of one context share their noise."""
    return torch.arange(contexts).repeat(commands)


def action_checks(rows: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per metric: can the probe judge adherence (ceiling ≤ ½ floor and ≤ ½ reference), and does the model reach
    the target (model ≤ floor − ½ (floor − ceiling))?"""
    checks = {}
    for metric in CONTRASTS:
        ceiling, model, floor, reference = (rows[k][metric]["mean"] for k in ("ceiling", "model", "floor", "reference"))
        target = floor - 0.5 * (floor - ceiling)
        checks[metric] = {"probe_reads_it": ceiling <= 0.5 * floor and ceiling <= 0.5 * reference,
                          "ceiling_over_floor": ceiling / floor if floor else math.inf,
                          "ceiling_over_reference": ceiling / reference if reference else math.inf,
                          "target": target, "model_meets_target": model <= target}
    return checks


def share_row(probe, video: torch.Tensor, attr: str, index: int) -> dict[str, Any]:
    """Rollouts reading value `index` of `attr` (majority of frames), Wilson interval, and the frame accuracy."""
    shares = attribute_shares(probe, video, {attr: torch.full((len(video),), index)})[attr]
    row = share_interval(int((shares > 0.5).sum()), len(shares)).as_dict()
    row["frame_accuracy"] = float(shares.mean())
    return row


def text_table(cfg: DictConfig, pipeline: Gaia1Pipeline, probe, generator: torch.Generator) -> dict[str, Any]:
    """Ceiling / model / floor share of rollouts reading each prompted attribute value."""
    c, rate, (height, width) = cfg.controllability, pipeline.rate, pipeline.image_size
    frames = future_frames(cfg.seconds, rate)
    targets = [(attr, value) for attr, values in c.prompts.items() for value in values]
    repeats, floor_repeats = c.text_repeats, c.floor_repeats
    if repeats < 1 or floor_repeats < 1:
        raise ValueError(f"controllability.text_repeats={repeats}, floor_repeats={floor_repeats}: expected ≥ 1 each")
    floor = torch.cat([rollout_frames(pipeline, None, frames, min(repeats, floor_repeats - start), None, None,
                                      generator)
                       for start in range(0, floor_repeats, repeats)])
    real = probe_clips(world_clips(cfg.context.seed, c.real_clips, height, width, frames, rate, start=c.contexts,
                                   balanced=True), rate, frames)
    rows: dict[str, dict[str, Any]] = {"ceiling": {}, "tokenized": {}, "model": {}, "floor": {}}
    for attr, value in targets:
        key, index = f"{attr}={value}", ATTRIBUTES[attr].index(value)
        text = pipeline.encode_text_batch([[c.prompt_text[attr][value]] * frames] * repeats)
        model = rollout_frames(pipeline, None, frames, repeats, text, None, generator)
        has_value = real.labels[attr][:, 0] == index
        rows["ceiling"][key] = share_row(probe, real.frames[has_value], attr, index) if has_value.any() else None
        rows["tokenized"][key] = (share_row(probe, tokenized(pipeline, real.frames[has_value]), attr, index)
                                  if has_value.any() else None)
        rows["model"][key] = share_row(probe, model, attr, index)
        rows["floor"][key] = share_row(probe, floor, attr, index)
    chance = {f"{attr}={value}": 1.0 / len(ATTRIBUTES[attr]) for attr, value in targets}
    checks = {key: {"probe_reads_it": bool(row and row["frame_accuracy"] >= 0.9)}
              for key, row in rows["ceiling"].items()}
    return {"targets": [f"{a}={v}" for a, v in targets], "rollouts_per_prompt": repeats,
            "floor_rollouts": floor_repeats, "chance": chance,
            "rows": rows, "checks": checks}


ACTION_ROWS = {"ceiling": "ceiling (real, re-simulated)", "tokenized": "ceiling through the tokenizer (diagnostic)",
               "model": "model (action-conditioned)",
               "floor": "floor (actions dropped)", "reference": "reference (real continuation, commands ignored)"}
REALISED_ROWS = {"ceiling": "ceiling (real, re-simulated)", "tokenized": "ceiling through the tokenizer",
                 "model": "model (action-conditioned)", "floor": "floor (actions dropped)"}
TEXT_ROWS = {"ceiling": "ceiling (real clips)", "tokenized": "ceiling through the tokenizer (diagnostic)",
             "model": "model (text-prompted)", "floor": "floor (no text)"}


def markdown(results: dict[str, Any]) -> str:
    """The two tables of a controllability run, with 95 % intervals and the probe checks."""
    actions, text = results["actions"], results["text"]
    speed, curvature = (" vs ".join(actions["contrasts"][m]) for m in CONTRASTS)
    lines = [f"Action adherence over {actions['contexts']} held-out contexts × {len(actions['commands'])} commands "
             f"({', '.join('/'.join(c) for c in actions['commands'])}), {actions['scored_steps']} scored steps each; "
             "± 95 % interval over contexts. Contrast error: |probed difference − commanded difference| of the "
             f"horizon-mean speed ({speed}) and curvature ({curvature}) of two futures of one context; a rollout "
             "that ignores its commands scores the commanded difference. MAE: mean |probed − commanded| over all "
             "commands (diagnostic; it carries the probe's per-scene bias).", "",
             *action_rows_markdown(actions, ACTION_ROWS), "", *realised_rows_markdown(actions),
             *discrimination_markdown(actions), *fidelity_markdown(actions["fidelity"])]
    lines += ["", f"Text adherence: share of rollouts ({text['rollouts_per_prompt']} per prompt, generated from the "
              f"prompt alone; {text.get('floor_rollouts', text['rollouts_per_prompt'])} unprompted rollouts for the "
              "floor, "
              "shared by every prompt) whose frames mostly read the prompted value; [95 % Wilson interval].", "",
              "| text adherence | " + " | ".join(text["targets"]) + " |", "|---" * (len(text["targets"]) + 1) + "|"]
    for key, name in TEXT_ROWS.items():
        lines.append(f"| {name} | " + " | ".join(share_cell(text["rows"][key][t]) for t in text["targets"]) + " |")
    lines.append("| chance | " + " | ".join(f"{text['chance'][t]:.2f}" for t in text["targets"]) + " |")
    lines.append("| probe check: real-frame accuracy ≥ 0.9 | " + " | ".join(
        f"{'yes' if text['checks'][t]['probe_reads_it'] else 'NO'} ({cell_accuracy(text['rows']['ceiling'][t])})"
        for t in text["targets"]) + " |")
    return "\n".join(lines) + "\n"


def fidelity_markdown(fidelity: dict[str, Any]) -> list[str]:
    """The fidelity table: each row's futures against the real continuations under the same commands."""
    return ["", "Fidelity against the real continuations under the same commands (per generated frame; fvmd, fid, "
            "fdd between the sets of clips):", "", *table_markdown(fidelity, FIDELITY_ROWS)]


def action_rows_markdown(actions: dict[str, Any], names: dict[str, str]) -> list[str]:
    """The action table's header, one line per row of `names` (key → label), its targets and probe checks."""
    lines = ["| action adherence | speed contrast error (m/s) ↓ | curvature contrast error (1/m) ↓ | "
             "speed MAE (m/s) ↓ | curvature MAE (1/m) ↓ |", "|---|---|---|---|---|"]
    for key, name in names.items():
        row = actions["rows"][key]
        lines.append(f"| {name} | {fmt(row['speed_contrast'], 3)} | {fmt(row['curvature_contrast'], 4)} | "
                     f"{fmt(row['speed_mae'], 3)} | {fmt(row['curvature_mae'], 4)} |")
    checks = actions["checks"]
    lines.append("| target: model ≤ floor − ½ (floor − ceiling) | " + " | ".join(
        f"{checks[m]['target']:.{d}f} ({'met' if checks[m]['model_meets_target'] else 'missed'})"
        for m, d in zip(CONTRASTS, (3, 4))) + " | | |")
    lines.append("| probe check: ceiling ≤ ½ floor and ≤ ½ reference | " + " | ".join(
        f"{'yes' if checks[m]['probe_reads_it'] else 'NO'} ({checks[m]['ceiling_over_floor']:.2f}, "
        f"{checks[m]['ceiling_over_reference']:.2f})" for m in CONTRASTS) + " | | |")
    return lines


def realised_rows_markdown(actions: dict[str, Any]) -> list[str]:
    """Diagnostic table: the signed probed difference of the contrasted futures against the commanded one, with
    its spread over contexts (the error's two sources: a command shown too weakly, and futures that scatter)."""
    rows = {key: actions["rows"][key].get("realised") for key in REALISED_ROWS}
    if any(row is None for row in rows.values()):  # results written before the diagnostic existed
        return []
    commanded = rows["ceiling"]
    header = (f"| realised difference (diagnostic) | speed (m/s), commanded "
              f"{commanded['speed_contrast']['commanded']:.3f}"
              f" | curvature (1/m), commanded {commanded['curvature_contrast']['commanded']:.4f} |")
    lines = [header, "|---|---|---|"]
    for key, name in REALISED_ROWS.items():
        cells = [f"{fmt(rows[key][m], d)} (sd {rows[key][m]['sd']:.{d}f})" for m, d in zip(CONTRASTS, (3, 4))]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def discrimination_markdown(actions: dict[str, Any]) -> list[str]:
    """One diagnostic line: how much better the world model explains the real futures given their own command."""
    rows = actions.get("discrimination")
    if not rows:  # results written before the diagnostic existed
        return []
    cells = [f"{name.split('_')[0]} {fmt(rows[name], 4)}" for name in CONTRASTS]
    line = ("Command discrimination (diagnostic; teacher-forced, unguided): nats/token of the real futures given the "
            "contrasted command minus given their own, > 0 when the commands steer the predictions: ")
    return ["", line + ", ".join(cells) + "."]


def fmt(estimate: dict[str, float], digits: int) -> str:
    return f"{estimate['mean']:.{digits}f} ± {(estimate['high'] - estimate['low']) / 2:.{digits}f}"


def share_cell(row: dict[str, float] | None) -> str:
    return "n/a (no real clip)" if row is None else f"{row['mean']:.2f} [{row['low']:.2f}, {row['high']:.2f}]"


def cell_accuracy(row: dict[str, float] | None) -> str:
    return "no clip" if row is None else f"{row['frame_accuracy']:.2f}"


def controllability(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Run the protocol of the module docstring; returns the results (also written to the run dir)."""
    check_fidelity(cfg.controllability.fidelity)
    # the probes read frames decoded one by one by the tokenizer (as when they were checked on real frames)
    pipeline = load_pipeline(cfg, video_decoder=False)
    t = cfg.context.frames + future_frames(cfg.seconds, pipeline.rate, at_least=2)
    dynamics, scene, probe_info = probes_for(cfg, pipeline, t, Path(run_dir))
    generator = torch.Generator(device=pipeline.device).manual_seed(int(cfg.seed))
    results = {"probes": probe_info, "actions": action_table(cfg, pipeline, dynamics, generator),
               "text": text_table(cfg, pipeline, scene, generator)}
    atomic_write_text(run_dir / "controllability.json", json.dumps(results, indent=2))
    atomic_write_text(run_dir / "controllability.md", markdown(results))
    return results
