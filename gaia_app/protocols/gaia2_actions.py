"""Action adherence of the GAIA-2 latent world model, measured as GAIA-1's controllability table measures it
(gaia_app/protocols/controllability.py; docs/latent_world_model.md, "Evaluation").

Legend: N scenes, C commands, f = model.steps · temporal frames, t0 = context_steps · temporal.

- Probe: GAIA-1's inverse-dynamics probe, trained on `model.evaluate.probe_clips` clips of the world `probe_seed`
  rendered at the rig's rate, weather and time of day uniform, and `probe_driven_share` of them leaving their policy
  for a random open-loop command (frames whose motion is not the policy's, as the commanded futures are). It reads
  the rig's front camera (`probe_cameras=front`) or every camera side by side (`rig`: one encoder shared by the
  cameras, pairs mirrored with the rig's left and right cameras swapped); every row below is read the same way.
- For each held-out scene and each command of `model.evaluate.commands` (speed, curvature presets from the scene's
  speed at frame t0 − 1), on frames t0 … f − 1:
    ceiling   = the scene re-simulated by the synthetic world with the commanded actions (every camera rendered;
                as in GAIA-1's ceiling, an open-loop ego has no lead car to follow, so 'follow' scenes lose theirs);
    tokenized = the ceiling encoded and decoded by the tokenizer (a diagnostic);
    model     = the world model continuing the scene's t0 context frames under the commanded actions;
    floor     = the same continuation with the action condition dropped (same noise as the model's futures);
                model and floor sample `model.evaluate.noise_draws` futures per scene (and command), each from its
                own noise, and a scene scores their mean;
    both with the agent boxes dropped (`model.evaluate.action_agents=dropped`, the default) or the real continuation's
    (`real`: boxes that move with the scene's own ego motion, not the command's, so they contradict it);
    reference = the real continuation under the scene's own policy, scored against the command.
- Scores (protocols/controllability.error_row): the contrast errors of speed (accelerate vs brake) and curvature
  (left vs right) and the MAE, 95 % intervals over scenes; the target model ≤ floor − ½ (floor − ceiling) and the probe
  check ceiling ≤ ½ floor and ≤ ½ reference (protocols/controllability.action_checks).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from einops import rearrange
from hydra.utils import instantiate
from omegaconf import DictConfig
from tqdm.auto import tqdm

from gaia_app.data.clip import Clip
from gaia_app.data.latent_cache import LatentClip
from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.data.synthetic.generate import SyntheticSample
from gaia_app.data.synthetic.rig import resolve_camera_names
from gaia_app.data.synthetic.scenario import Scenario
from gaia_app.data.transforms import to_float
from gaia_app.eval.controllability import contrast_pairs, probe_clips, train_probes
from gaia_app.models.probes import InverseDynamicsProbe, TwinDisplacementProbe
from gaia_app.pipelines.gaia2 import Gaia2Pipeline, with_labels
from gaia_app.protocols.controllability import (
    CONTRASTS,
    UNIFORM_MIX,
    action_checks,
    action_rows_markdown,
    commanded_actions,
    error_row,
)

# the agents the model and floor rows see: the real continuation's boxes follow the scene's own ego motion, so they
# contradict the command (and the model may follow them instead); dropped leaves the action alone to steer
AGENT_CHOICES = ("dropped", "real")
ROWS = {"ceiling": "ceiling (re-simulated with the commands)", "tokenized": "tokenized ceiling (diagnostic)",
        "model": "model, commanded actions", "floor": "floor (actions dropped)",
        "reference": "reference (real continuation)"}
SAMPLED = ("model", "floor")  # the rows the world model samples, `model.evaluate.noise_draws` futures per scene
PROBE_CAMERAS = ("front", "rig")  # the action probe reads the rig's first camera, or all of them side by side


def check_action_agents(cfg: DictConfig) -> None:
    """Raise ValueError naming model.evaluate.action_agents unless it is one of AGENT_CHOICES."""
    value = cfg.model.evaluate.action_agents
    if value not in AGENT_CHOICES:
        raise ValueError(f"model.evaluate.action_agents={value!r}: expected one of {AGENT_CHOICES}")


def rig_world(cfg: DictConfig, seed: int, count: int, frames: int, **overrides: Any) -> SyntheticClipDataset:
    """Clips 0..count-1 of the synthetic world `seed` with the rig of `cfg.data` at its rate, `frames` long."""
    make = instantiate(cfg.data.source, _partial_=True)  # overrides pass as objects (a Scenario is no config)
    return make(**{"num_clips": count, "seed": seed, "clip_len": frames, **overrides})


def train_action_probe(cfg: DictConfig, frames: int) -> tuple[InverseDynamicsProbe, dict[str, float]]:
    """The inverse-dynamics probe of the module docstring, and its fit (first/last loss)."""
    e, views = cfg.model.evaluate, probe_views(cfg)
    names, mirror = resolve_camera_names(cfg.data.source.cameras), probe_mirror(cfg)
    world = rig_world(cfg, e.probe_seed, e.probe_clips, frames, cameras=names if views else names[:1],
                      driven_share=e.probe_driven_share, **UNIFORM_MIX)
    clips = [world[i] for i in tqdm(range(e.probe_clips), desc="action probe clips")]
    dynamics, _, fit = train_probes(probe_clips(clips, clips[0].fps, frames, views), e.probe_steps, seed=cfg.seed,
                                    stride=probe_stride(cfg), mirror=mirror)
    return dynamics, fit


def probe_views(cfg: DictConfig) -> list[int] | None:
    """The cameras the action probe reads (`model.evaluate.probe_cameras`): None for the rig's first camera (front),
    every camera index in rig order for rig; ValueError otherwise."""
    value = cfg.model.evaluate.probe_cameras
    if value not in PROBE_CAMERAS:
        raise ValueError(f"model.evaluate.probe_cameras={value!r}: expected one of {PROBE_CAMERAS}")
    return None if value == "front" else list(range(len(resolve_camera_names(cfg.data.source.cameras))))


def probe_mirror(cfg: DictConfig) -> list[int] | None:
    """The rig probe's mirror order (`mirror_order` of the rig's cameras), None for the front camera; ValueError for an
    unknown `model.evaluate.probe_cameras` or a rig without mirror twins (callers check it before rendering)."""
    return mirror_order(resolve_camera_names(cfg.data.source.cameras)) if probe_views(cfg) else None


def mirror_order(names: list[str]) -> list[int]:
    """For each camera of a rig, the index of the camera that a left–right mirror image puts in its place
    (front → front, front_left ↔ front_right); ValueError naming the camera whose mirror twin the rig lacks."""
    swap = {"left": "right", "right": "left"}
    twins = ["_".join(swap.get(part, part) for part in name.split("_")) for name in names]
    missing = [name for name, twin in zip(names, twins) if twin not in names]
    if missing:
        raise ValueError(f"data.source.cameras={names}: the rig probe mirrors its pairs, but {missing} have no "
                         "mirror twin in the rig (use model.evaluate.probe_cameras=front)")
    return [names.index(twin) for twin in twins]


def views_of(frames: torch.Tensor, views: list[int] | None) -> torch.Tensor:
    """A rig's frames (v, t, 3, H, W) → what the action probe reads: the first camera (t, 3, H, W), or the cameras
    `views` (t, k, 3, H, W)."""
    return frames[0] if views is None else rearrange(frames[views], "k t ... -> t k ...")


def probe_stride(cfg: DictConfig) -> int:
    """`model.evaluate.probe_stride`: frames between the two frames the probe reads; ValueError unless in 1..4 (a
    latent step of the shipped tokenizer is 4 frames; the scored pairs must start after the context)."""
    stride = cfg.model.evaluate.probe_stride
    if not isinstance(stride, int) or not 1 <= stride <= 4:
        raise ValueError(f"model.evaluate.probe_stride={stride!r}: expected a whole number of frames in 1..4")
    return stride


def noise_draws(cfg: DictConfig) -> int:
    """`model.evaluate.noise_draws`: futures per scene and command, each from its own noise; ValueError unless ≥ 1."""
    draws = cfg.model.evaluate.noise_draws
    if not isinstance(draws, int) or draws < 1:
        raise ValueError(f"model.evaluate.noise_draws={draws!r}: expected a whole number ≥ 1")
    return draws


def resimulated(cfg: DictConfig, index: int, actions: np.ndarray) -> Clip:
    """Scene `index` of the world `context.seed` (every camera of the rig) driven open-loop by per-frame `actions`
    (f, 2)."""
    world = rig_world(cfg, cfg.context.seed, index + 1, len(actions), scenario=Scenario(ego_actions=actions))
    return world[index]


def action_table(cfg: DictConfig, pipeline: Gaia2Pipeline, scenes: list[tuple[SyntheticSample, LatentClip]],
                 probe: InverseDynamicsProbe, generator: torch.Generator,
                 ceilings: dict[tuple[int, bytes], Clip] | None = None,
                 twin: TwinDisplacementProbe | None = None) -> dict[str, Any]:
    """Rows, targets and probe checks of the action-adherence table (module docstring). With `twin` (a
    TwinDisplacementProbe, `model.evaluate.speed_probe=twin`) the speed contrast is read by it
    (protocols/gaia2_twin_probe.py), the pair probe's reading kept as `speed_contrast_pair`.

    ceilings: a dict shared by tables of the same scenes (benchmarks/gaia2_action_adherence.py compares weights and
    guidance scales): a re-simulated real continuation depends on its scene and actions only, so each is rendered
    once and reused, keyed by (scene, actions)."""
    ceilings = {} if ceilings is None else ceilings
    g = cfg.model
    check_action_agents(cfg)
    stride, views = probe_stride(cfg), probe_views(cfg)
    first, frames = g.context_steps * pipeline.temporal, g.steps * pipeline.temporal
    rate = float(scenes[0][0].clip.fps)
    contexts = probe_clips([sample.clip for sample, _ in scenes], rate, frames, views)
    commands = [tuple(cmd) for cmd in g.evaluate.commands]
    commanded = commanded_actions(contexts, first, frames - first, rate, commands)  # (C·N, f, 2) command-major
    pairs = contrast_pairs(commanded[:, first:-1].unflatten(0, (len(commands), -1)))  # fails before any rollout
    n, draws = len(scenes), noise_draws(cfg)
    noise = scene_noise_seeds(generator, n, draws)
    videos: dict[str, list[torch.Tensor]] = {name: [] for name in ROWS}
    for k in tqdm(range(len(commanded)), desc="action adherence"):
        i = k % n
        _, clip = scenes[i]
        actions = commanded[k].numpy()
        key = (i, actions.tobytes())
        if key not in ceilings:
            ceilings[key] = resimulated(cfg, i, actions.astype(np.float64))
        ceiling = ceilings[key]
        videos["ceiling"].append(views_of(to_float(torch.from_numpy(ceiling.frames)), views))
        tokenized = pipeline.decode(pipeline.window(pipeline.encode(ceiling), 0, g.steps)[0])[0].cpu()
        videos["tokenized"].append(views_of(tokenized, views))
        target = with_labels(clip, first, actions[first:])
        context, _ = pipeline.window(target, 0, g.context_steps)
        _, cond = pipeline.window(target, 0, g.steps)
        cond = cond.without("agents") if g.evaluate.action_agents == "dropped" else cond
        for seed in noise[i]:
            videos["model"].append(continuation(pipeline, context, cond, g.steps - g.context_steps, seed, views))
            # the floor ignores the command: one continuation per scene and draw, scored against every command
            if k < n:
                videos["floor"].append(continuation(pipeline, context, cond.without("action"),
                                                    g.steps - g.context_steps, seed, views))
    videos["floor"] = videos["floor"] * len(commands)
    videos["reference"] = list(contexts.frames) * len(commands)
    # scored: pairs (i − stride, i) of generated frames only, i = first + stride … f − 1
    stacked = {name: torch.stack(video) for name, video in videos.items()}
    row_draws = {name: draws if name in SAMPLED else 1 for name in stacked}
    rows = {name: error_row(probe, video, commanded, first + stride, len(commands), stride, row_draws[name])
            for name, video in stacked.items()}
    if twin is not None:
        from gaia_app.protocols.gaia2_twin_probe import read_speed_with_twins  # it builds on this module

        read_speed_with_twins(rows, stacked, twin, commanded, first, stride, len(commands), pairs[0], rate, row_draws)
    contrasted = {metric: ["/".join(commands[high]), "/".join(commands[low])]
                  for metric, (high, low) in zip(CONTRASTS, pairs)}
    return {"scenes": n, "commands": [list(cmd) for cmd in commands], "agents": g.evaluate.action_agents,
            "context_frames": first, "probe_stride": stride, "noise_draws": draws,
            "probe_cameras": g.evaluate.probe_cameras, "scored_steps": frames - first - stride, "rows": rows,
            "speed_probe": "pair" if twin is None else "twin",
            "contrasts": contrasted, "checks": action_checks(rows)}


def scene_noise_seeds(generator: torch.Generator, scenes: int, draws: int) -> list[list[int]]:
    """`draws` noise seeds per scene, drawn from `generator` scene by scene: a scene's commands and its floor share
    them (benchmarks/gaia2_contrast_trace.py draws them the same way, so its samples are this table's futures)."""
    return [[int(torch.randint(2**31, (), generator=generator)) for _ in range(draws)] for _ in range(scenes)]


def continuation(pipeline: Gaia2Pipeline, context: torch.Tensor, cond: Any, new_steps: int, seed: int,
                 views: list[int] | None = None) -> torch.Tensor:
    """The frames the action probe reads (`views_of`: (f, 3, H, W) front camera, or (f, k, 3, H, W)) of the context
    steps continued by `new_steps` generated ones."""
    x = pipeline.world.rollout(context, [cond], new_steps, torch.Generator(context.device).manual_seed(seed))
    return views_of(pipeline.decode(x)[0].cpu(), views)


def markdown(actions: dict[str, Any]) -> list[str]:
    """The action-adherence table's lines."""
    speed, curvature = (" vs ".join(actions["contrasts"][m]) for m in CONTRASTS)
    cameras = "every camera of the rig" if actions.get("probe_cameras") == "rig" else "front camera"
    return [f"Action adherence ({cameras}, {actions['scenes']} held-out scenes × {len(actions['commands'])} commands "
             f"({', '.join('/'.join(c) for c in actions['commands'])}), {actions['context_frames']} context frames, "
             f"{actions['scored_steps']} scored frame pairs {actions.get('probe_stride', 1)} frame(s) apart each, "
             f"agent boxes {actions['agents']}, "
             f"{actions.get('noise_draws', 1)} sampled future(s) per scene and command (a scene's score: their mean); "
             "± 95 % interval over scenes. Contrast error: |probed "
             f"difference − commanded difference| of the horizon-mean speed ({speed}) and curvature ({curvature}) of "
             "two futures of one scene; MAE: mean |probed − commanded| (diagnostic)"
             + (". Speed contrast read by the twin probe (the two futures' frames side by side at the same instant, "
                "protocols/gaia2_twin_probe.py); the pair probe's in the JSON as speed_contrast_pair"
                if actions.get("speed_probe") == "twin" else ""), "",
             *action_rows_markdown(actions, ROWS)]
