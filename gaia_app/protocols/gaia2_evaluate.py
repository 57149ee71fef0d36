"""`generate.py model=gaia2 mode=evaluate`: agent control and action adherence of the GAIA-2 latent world model on
held-out synthetic rig scenes (GAIA-2 report, evaluation; docs/latent_world_model.md).

Scenes are clips `0..contexts-1` of the world `context.seed` rendered with the rig of `data` (data=synthetic_rig);
probes train in the same run on clips of `model.evaluate.probe_seed`.

Agent control (every camera, every frame of model.steps latent steps generated from scratch under the scene's
conditions): the pooled IoU of a segmentation probe's agent masks with (a) the scene's true agent masks and (b) the
conditioning boxes projected into each camera, for
    real frames                 the rendered scene (what the probe reaches on real images)
    tokenized real              the scene's latents decoded (the ceiling through this tokenizer)
    model, agent conditions     generated with every condition
    model, plain CFG ×s         the same with classifier-free guidance on the agents over the whole scene
                                (s = cfg_scale; the three guided rows are skipped at 0)
    model, selective CFG ×s     spatially selective guidance: only the tokens inside the agent boxes are guided, and
                                the second pass sees those tokens alone (the report's saving)
    ..., full second pass       the same regions guided from a full unconditional pass (the straightforward variant)
    ..., paired agent passes    the same regions guided by the direction between a conditional and an unconditional
                                pass over the agent tokens alone (the report's dual pass for the agent tokens only)
    model, agents dropped       generated with the agent condition dropped (the floor)
Each IoU carries a 95 % interval (scenes resampled), the guided rows their paired difference to plain CFG on the
same scenes and noise, and every model row its paired difference to the agents-dropped row (the agent target's
comparison: boxes given against dropped, issue 50).
Action adherence (the front camera or the whole rig, `model.evaluate.probe_cameras`): GAIA-1's controllability
protocol, contrast errors against a re-simulated ceiling, a floor with actions dropped and the real continuation
(gaia_app/protocols/gaia2_actions.py).
Fidelity (every camera; the metrics of `evaluate.metrics`, shared with GAIA-1's mode=evaluate and scored by the same
code, protocols/evaluate.score): the context steps continued under the scene's own conditions, scored from the first
generated frame against the real continuation, next to the tokenized real clip (ceiling) and the last context frame
held (floor).
Cross-view consistency (every overlapping camera pair, every frame of model.steps latent steps generated from
scratch; gaia_app/eval/cross_view.py): the seam error, the mean absolute difference between a camera and its
neighbour warped onto it by the homography at infinity over their shared pixels, for the real frames (ceiling),
the tokenized real clip, the model's cameras generated together, and each camera generated alone under the same
conditions (a one-camera rig; the floor: nothing ties the views together). Intervals over scenes.
Writes gaia2_evaluation.json and gaia2_evaluation.md (the four tables) into the run dir.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from tqdm.auto import tqdm

from gaia_app.data.latent_cache import LatentClip
from gaia_app.data.synthetic.generate import SyntheticSample
from gaia_app.data.transforms import to_float
from gaia_app.eval.agent_iou import overlap_counts, predicted_agents, train_agent_probe
from gaia_app.eval.cross_view import overlapping_pairs, seam_errors
from gaia_app.eval.intervals import mean_interval, ratio_interval
from gaia_app.eval.report import ARROWS
from gaia_app.models.gaia2.conditioning import project_boxes
from gaia_app.pipelines.gaia2 import Gaia2Pipeline
from gaia_app.pipelines.gaia2_edits import cut_steps
from gaia_app.pipelines.gaia2_world_model import Guidance
from gaia_app.protocols import gaia2_actions
from gaia_app.protocols.fidelity import check_metrics, feature_metrics, held_frame, score
from gaia_app.protocols.gaia2_action_probe import action_probe
from gaia_app.protocols.gaia2_twin_probe import twin_probe
from gaia_app.protocols.loading import load_gaia2
from gaia_app.utils.run_dir import atomic_write_text


def rig_samples(cfg: DictConfig, seed: int, count: int, frames: int) -> list[SyntheticSample]:
    """`count` clips (with their simulation) of the synthetic world `seed` with the rig of `cfg.data`, `frames` long."""
    if "source" not in cfg.data or "cameras" not in cfg.data.source:
        raise ValueError("model=gaia2 mode=evaluate renders the rig of `data`: use data=synthetic_rig")
    world = gaia2_actions.rig_world(cfg, seed, count, frames)
    return [world.sample(i) for i in range(count)]


def agent_masks(sample: SyntheticSample, frames: int) -> torch.Tensor:
    """(v, T, H, W) bool: any agent visible at each pixel of every camera."""
    views = range(sample.clip.num_views)
    return torch.from_numpy(np.stack([np.stack([sample.instance_ids(t, v) >= 0 for t in range(frames)])
                                      for v in views]))


def box_masks(cond: Any, frames: int, temporal: int) -> torch.Tensor:
    """(v, T, H, W) bool: the conditioning agent boxes projected into every camera (a latent step's boxes on its
    frames)."""
    height, width = cond.image_size
    boxes, _, visible = project_boxes(cond.agents, cond.intrinsics, cond.extrinsics, cond.image_size)  # (1, t, v, N, 4)
    ys = (torch.arange(height) + 0.5) / height
    xs = (torch.arange(width) + 0.5) / width
    x0, y0, x1, y1 = (boxes[0, ..., i, None, None].cpu() for i in range(4))  # (t, v, N, 1, 1)
    inside = (xs > x0) & (xs < x1) & (ys[:, None] > y0) & (ys[:, None] < y1) & visible[0, ..., None, None].cpu()
    per_step = inside.any(dim=2)  # (t, v, H, W)
    return per_step.repeat_interleave(temporal, dim=0)[:frames].transpose(0, 1)


def train_segmentation_probe(cfg: DictConfig, frames: int) -> tuple[Any, dict[str, float]]:
    """The agent segmentation probe (every camera of `probe_clips` clips of the probe world) and its fit."""
    e = cfg.model.evaluate
    samples = rig_samples(cfg, e.probe_seed, e.probe_clips, frames)
    images = torch.cat([to_float(torch.from_numpy(s.clip.frames)) for s in samples])  # (N·v, T, 3, H, W)
    masks = torch.cat([agent_masks(s, frames) for s in samples])
    return train_agent_probe(images, masks, steps=e.probe_steps, seed=cfg.seed)


def train_probes_for(cfg: DictConfig, frames: int, run_dir: Path | None = None) -> tuple[Any, Any, dict[str, Any]]:
    """The agent segmentation probe (train_segmentation_probe) and the action table's probes: the inverse-dynamics
    probe (the front camera or the rig: `model.evaluate.action_probe` loaded, or trained and saved to
    `run_dir`/action_probe; protocols/gaia2_action_probe.py) and, with `model.evaluate.speed_probe=twin`, the twin
    probe (`model.evaluate.twin_probe` or `run_dir`/twin_probe; protocols/gaia2_twin_probe.py), else None."""
    segmentation, agent_fit = train_segmentation_probe(cfg, frames)
    dynamics, action_info = action_probe(cfg, frames, None if run_dir is None else run_dir / "action_probe")
    twin, twin_info = twin_probe(cfg, frames, None if run_dir is None else run_dir / "twin_probe")
    return segmentation, (dynamics, twin), {
        "agent_probe": agent_fit, "action_probe": action_info.get("fit"),
        **({"action_probe_from": action_info["loaded_from"]} if "loaded_from" in action_info else {}),
        **({"twin_probe": twin_info.get("fit"), "twin_probe_from": twin_info.get("loaded_from")} if twin_info else {})}


def scene_overlaps(predicted: list[torch.Tensor], masks: list[torch.Tensor],
                   regions: list[torch.Tensor] | None = None) -> tuple[list[int], list[int]]:
    """Per scene, the (intersection, union) pixel counts of the probe's masks predicted on its video with its masks
    (v, T, H, W), within its region (v, T, H, W) where `regions` is given."""
    counts = [overlap_counts(p, mask, region)
              for p, mask, region in zip(predicted, masks, regions or [None] * len(masks))]
    return [i for i, _ in counts], [u for _, u in counts]


def row_overlaps(probe: Any, videos: list[torch.Tensor], truth: list[torch.Tensor],
                 boxes: list[torch.Tensor]) -> dict[str, tuple[list[int], list[int]]]:
    """The counts of every agent-table metric for one row's per-scene videos (v, T, 3, H, W), the probe run once per
    video: IoU with the true agent masks and with the conditioning boxes, and where guidance can act: the IoU with
    the agent masks inside the boxes, and the share of the area outside every box that the probe calls agent (false
    alarms there: spatially selective CFG leaves those tokens unguided, plain CFG guides them)."""
    predicted = [predicted_agents(probe, video) for video in videos]
    return {"iou_agent_masks": scene_overlaps(predicted, truth),
            "iou_conditioning_boxes": scene_overlaps(predicted, boxes),
            "iou_inside_boxes": scene_overlaps(predicted, truth, boxes),
            "agent_share_outside_boxes": scene_overlaps(predicted, [torch.ones_like(b) for b in boxes],
                                                        [~b for b in boxes])}


DROPPED_ROW = "model, agents dropped"  # the agent table's floor: generated with the agent condition dropped


def iou_rows(probe: Any, rows: dict[str, list[torch.Tensor]], truth: list[torch.Tensor], boxes: list[torch.Tensor],
             reference: str | None) -> dict[str, dict[str, Any]]:
    """Per row: the pooled IoU with the true agent masks and with the box masks, each with its interval over scenes,
    and for the guided rows other than `reference` their paired difference to it."""
    overlaps = {name: row_overlaps(probe, videos, truth, boxes) for name, videos in rows.items()}
    table: dict[str, dict[str, Any]] = {}
    for name, counts in overlaps.items():
        table[name] = {}
        for metric, (intersections, unions) in counts.items():
            estimate = ratio_interval(intersections, unions)
            table[name][metric] = estimate.mean
            table[name][f"{metric}_interval"] = estimate.as_dict()
            if reference is not None and "CFG" in name and name != reference:
                difference = ratio_interval(intersections, unions, minus=overlaps[reference][metric])
                table[name][f"{metric}_minus_plain"] = difference.as_dict()
    # the agent target compares boxes given with dropped; both rows share each scene's noise, so pair them by scene
    if DROPPED_ROW in overlaps:
        dropped = overlaps[DROPPED_ROW]["iou_agent_masks"]
        for name in (n for n in overlaps if n.startswith("model, ") and n != DROPPED_ROW):
            table[name]["iou_agent_masks_minus_dropped"] = ratio_interval(
                *overlaps[name]["iou_agent_masks"], minus=dropped).as_dict()
    return table


# the guided rows of the agent table: key → (row label before "×s", spatial, spatial_pass); "plain" first, the
# reference every other guided row is differenced against
GUIDED_VARIANTS = {"plain": ("plain CFG", False, "agent_tokens"),
                   "selective": ("selective CFG", True, "agent_tokens"),
                   "full": ("selective CFG", True, "full"),
                   "paired": ("selective CFG", True, "paired")}
PASS_SUFFIX = {"agent_tokens": "", "full": ", full second pass", "paired": ", paired agent passes"}


def guided_rows(scale: float, variants: Sequence[str] = tuple(GUIDED_VARIANTS)) -> dict[str, Guidance]:
    """The agent table's guided rows at guidance `scale`: row name → Guidance on the agents, for the `variants`
    (keys of GUIDED_VARIANTS; "plain" is always run, as every other guided row is measured against it)."""
    unknown = sorted(set(variants) - set(GUIDED_VARIANTS))
    if unknown:
        raise ValueError(f"guided variants {unknown}: expected some of {list(GUIDED_VARIANTS)}")
    rows = {}
    for key, (label, spatial, spatial_pass) in GUIDED_VARIANTS.items():
        if key == "plain" or key in variants:
            name = f"model, {label} ×{scale:g}{PASS_SUFFIX[spatial_pass] if spatial else ''}"
            rows[name] = Guidance(scale, ("agents",), spatial, spatial_pass)
    return rows


def agent_table(cfg: DictConfig, pipeline: Gaia2Pipeline, scenes: list[tuple[SyntheticSample, LatentClip]],
                probe: Any, generator: torch.Generator, variants: Sequence[str] = tuple(GUIDED_VARIANTS),
                unguided: bool = True) -> tuple[dict[str, Any], dict[str, list[torch.Tensor]]]:
    """Rows of the agent-control table (module docstring), and the per-scene videos (v, T, 3, H, W) of its real,
    tokenized and conditioned rows, which the cross-view table scores too (empty without `unguided`). `variants`
    picks the guided rows (guided_rows); `unguided=False` leaves out the two unguided model rows (agent conditions,
    agents dropped) for a comparison of guidance variants alone."""
    e, steps = cfg.model.evaluate, cfg.model.steps
    frames = steps * pipeline.temporal
    guided = guided_rows(e.cfg_scale, variants)
    rows: dict[str, list[torch.Tensor]] = {"real frames": [], "tokenized real": []}
    if unguided:
        rows["model, agent conditions"] = []
    if e.cfg_scale:
        rows.update({name: [] for name in guided})
    if unguided:
        rows[DROPPED_ROW] = []
    truth, boxes = [], []
    world, plain = pipeline.world, pipeline.world.guidance
    for sample, clip in tqdm(scenes, desc="agent control"):
        real, cond = pipeline.window(clip, 0, steps)
        truth.append(agent_masks(sample, frames))
        boxes.append(box_masks(cond, frames, pipeline.temporal))
        rows["real frames"].append(to_float(torch.from_numpy(sample.clip.frames[:, :frames])))
        rows["tokenized real"].append(pipeline.decode(real)[0].cpu())
        shape = tuple(real.shape)
        noise_seed = int(torch.randint(2**31, (), generator=generator))
        runs = [("model, agent conditions", plain, ()), *((name, g, ()) for name, g in guided.items()),
                (DROPPED_ROW, plain, ("agents",))]
        for name, guidance, drop in runs:
            if name not in rows:
                continue
            world.guidance = guidance
            x = world.from_scratch(shape, cond.without(*drop), torch.Generator(real.device).manual_seed(noise_seed))
            rows[name].append(pipeline.decode(x)[0].cpu())
        world.guidance = plain
    reference = next(iter(guided)) if e.cfg_scale else None
    table = {"scenes": len(scenes), "latent_steps": steps, "frames": frames,
             "rows": iou_rows(probe, rows, truth, boxes, reference)}
    return table, {name: rows[name] for name in SHARED_VIDEOS if name in rows}


def fidelity_table(cfg: DictConfig, pipeline: Gaia2Pipeline, scenes: list[tuple[SyntheticSample, LatentClip]],
                   probe: Any, generator: torch.Generator) -> dict[str, Any]:
    """Rows of the fidelity table (module docstring); clips are (scene, camera) pairs."""
    g = cfg.model
    c, new, tau = g.context_steps, g.steps - g.context_steps, pipeline.temporal
    first, frames = c * tau, g.steps * tau
    real, masks, model, tokenized = [], [], [], []
    for sample, clip in tqdm(scenes, desc="fidelity"):
        real.append(to_float(torch.from_numpy(sample.clip.frames[:, :frames])))
        masks.append(agent_masks(sample, frames))
        latents, cond = pipeline.window(clip, 0, g.steps)
        noise_seed = int(torch.randint(2**31, (), generator=generator))
        x = pipeline.world.rollout(latents[:, :, :c], [cond], new,
                                   torch.Generator(latents.device).manual_seed(noise_seed))
        model.append(pipeline.decode(x)[0].cpu())
        tokenized.append(pipeline.decode(latents)[0].cpu())
    real_clips, mask_clips = torch.cat(real), torch.cat(masks)  # (N·v, T, 3, H, W), (N·v, T, H, W)
    held = held_frame(real_clips, first)
    metrics, networks = list(cfg.evaluate.metrics), feature_metrics(cfg.evaluate)
    agents = (probe, mask_clips) if "agent_iou" in metrics else None
    candidates = {"model (rollouts)": torch.cat(model), "tokenized real (ceiling)": torch.cat(tokenized),
                  "held frame (floor)": held}
    return {"clips": int(real_clips.shape[0]), "context_frames": first, "generated_frames": frames - first,
            "rows": {name: score(metrics, real_clips, video, first, networks, agents)
                     for name, video in candidates.items()}}


def one_camera(clip: LatentClip, camera: int) -> LatentClip:
    """`clip` seen by camera `camera` alone (a one-camera rig with the same labels)."""
    return replace(clip, mean=clip.mean[camera : camera + 1], logvar=clip.logvar[camera : camera + 1],
                   cameras=[clip.cameras[camera]])


# agent-table rows whose videos the cross-view table reuses → its own row names
SHARED_VIDEOS = {"real frames": "real frames (ceiling)", "tokenized real": "tokenized real",
                 "model, agent conditions": "model, cameras generated together"}


def cross_view_table(cfg: DictConfig, pipeline: Gaia2Pipeline, scenes: list[tuple[SyntheticSample, LatentClip]],
                     shared: dict[str, list[torch.Tensor]], generator: torch.Generator) -> dict[str, Any]:
    """Rows of the cross-view table (module docstring): seam error per scene, mean ± 95 % interval over scenes.
    shared: the agent table's per-scene videos (real, tokenized, generated with every camera together); only the
    floor, each camera generated alone, is sampled here."""
    steps = cfg.model.steps
    rows: dict[str, list[float]] = {name: [] for name in [*SHARED_VIDEOS.values(),
                                                          "model, each camera generated alone (floor)"]}
    _, cond = pipeline.window(scenes[0][1], 0, steps)
    intrinsics, extrinsics = cond.intrinsics[0].cpu(), cond.extrinsics[0].cpu()
    pairs = overlapping_pairs(intrinsics, extrinsics, *cond.image_size)
    if not pairs:
        raise ValueError(f"model=gaia2 mode=evaluate: the cameras {[c.name for c in scenes[0][1].cameras]} of `data` "
                         "do not overlap; cross-view consistency needs adjacent views (e.g. front, front_left)")
    for k, (_, clip) in enumerate(tqdm(scenes, desc="cross-view")):
        noise_seed = int(torch.randint(2**31, (), generator=generator))
        alone = []
        for camera in range(len(clip.cameras)):
            single, single_cond = pipeline.window(one_camera(clip, camera), 0, steps)
            x = pipeline.world.from_scratch(tuple(single.shape), single_cond,
                                            torch.Generator(single.device).manual_seed(noise_seed + camera))
            alone.append(pipeline.decode(x)[0, 0].cpu())
        videos = {row: shared[name][k] for name, row in SHARED_VIDEOS.items()}
        videos["model, each camera generated alone (floor)"] = torch.stack(alone)
        for name, video in videos.items():
            rows[name].append(float(seam_errors(video, intrinsics, extrinsics, pairs).mean()))
    names = [c.name for c in scenes[0][1].cameras]
    return {"scenes": len(scenes), "frames": steps * pipeline.temporal,
            "pairs": [f"{names[a]}/{names[b]}" for a, b in pairs],
            "rows": {name: mean_interval(values).as_dict() for name, values in rows.items()}}


def markdown(results: dict[str, Any]) -> str:
    """The four tables of a GAIA-2 evaluation."""
    fidelity = results["fidelity"]
    names = list(next(iter(fidelity["rows"].values())))
    lines = [f"Fidelity ({fidelity['clips']} held-out clips (scene × camera), {fidelity['context_frames']} context + "
             f"{fidelity['generated_frames']} generated frames)", "",
             "| rollouts vs real continuations | " + " | ".join(f"{n} {ARROWS[n]}" for n in names) + " |",
             "|---" + "|---:" * len(names) + "|"]
    lines += [f"| {row} | " + " | ".join(f"{values[n]:.3f}" for n in names) + " |"
              for row, values in fidelity["rows"].items()]
    lines.append("")
    lines += agent_markdown(results["agents"], results["cameras"])
    lines += ["", *gaia2_actions.markdown(results["actions"])]
    views = results["cross_view"]
    lines += ["", f"Cross-view consistency ({views['scenes']} held-out scenes × {views['frames']} frames, camera pairs "
              f"{', '.join(views['pairs'])}; seam error: mean |camera − neighbour warped by the homography "
              "at infinity| "
              "over the shared pixels, ± 95 % interval over scenes)", "",
              "| frames | seam error ↓ |", "|---|---:|"]
    lines += [f"| {name} | {row['mean']:.4f} ± {(row['high'] - row['low']) / 2:.4f} |"
              for name, row in views["rows"].items()]
    return "\n".join(lines) + "\n"


def agent_markdown(agents: dict[str, Any], cameras: list[str]) -> list[str]:
    """The agent-control table's lines."""
    title = (f"Agent control ({agents['scenes']} held-out scenes × {len(cameras)} cameras × "
             f"{agents['frames']} frames, generated from scratch; pooled IoU [95 % interval, scenes resampled]; guided "
             "rows: paired difference to plain CFG on the same scenes and noise)")
    lines = [title, "",
             "| frames | IoU with agent masks ↑ | IoU with conditioning boxes ↑ | agent masks − plain CFG | "
             "IoU inside the boxes ↑ (− plain) | agent share outside the boxes ↓ (− plain) |",
             "|---|---:|---:|---:|---:|---:|"]
    lines += [f"| {name} | {iou_cell(row, 'iou_agent_masks')} | {iou_cell(row, 'iou_conditioning_boxes')} | "
              f"{difference_cell(row.get('iou_agent_masks_minus_plain'))} | "
              f"{region_cell(row, 'iou_inside_boxes')} | "
              f"{region_cell(row, 'agent_share_outside_boxes')} |" for name, row in agents["rows"].items()]
    paired = [f"{name} {difference_cell(row['iou_agent_masks_minus_dropped'])}"
              for name, row in agents["rows"].items() if "iou_agent_masks_minus_dropped" in row]
    if paired:
        lines += ["", "IoU with agent masks minus the agents-dropped row, paired by scene (same noise): "
                  + "; ".join(paired)]
    return lines


def iou_cell(row: dict[str, Any], metric: str) -> str:
    interval = row.get(f"{metric}_interval")
    return f"{row[metric]:.3f}" + (f" [{interval['low']:.3f}, {interval['high']:.3f}]" if interval else "")


def region_cell(row: dict[str, Any], metric: str) -> str:
    """'value' and, for the guided rows, '(difference to plain CFG [interval])'; blank for tables without it."""
    if metric not in row:
        return ""
    difference = row.get(f"{metric}_minus_plain")
    return f"{row[metric]:.3f}" + (f" ({difference_cell(difference)})" if difference else "")


def difference_cell(difference: dict[str, float] | None) -> str:
    if difference is None:
        return ""
    return f"{difference['mean']:+.3f} [{difference['low']:+.3f}, {difference['high']:+.3f}]"


def gaia2_evaluate(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Run the protocol of the module docstring; returns the results (also written to the run dir)."""
    e = cfg.model.evaluate
    if e.contexts < 1:
        raise ValueError(f"model.evaluate.contexts={e.contexts}: expected at least 1")
    check_metrics(cfg.evaluate)
    gaia2_actions.check_action_agents(cfg)
    gaia2_actions.probe_mirror(cfg)
    pipeline = load_gaia2(cfg)
    frames = cfg.model.steps * pipeline.temporal
    segmentation, (dynamics, twin), fit = train_probes_for(cfg, frames, run_dir)
    scenes = [(s, cut_steps(pipeline.encode(s.clip), cfg.model.steps))
              for s in rig_samples(cfg, cfg.context.seed, e.contexts, frames)]
    generator = torch.Generator().manual_seed(int(cfg.seed))
    fidelity = fidelity_table(cfg, pipeline, scenes, segmentation, generator)
    agents, shared = agent_table(cfg, pipeline, scenes, segmentation, generator)
    results = {"cameras": [c.name for c in scenes[0][1].cameras], "probe_fit": fit, "fidelity": fidelity,
               "agents": agents, "actions": gaia2_actions.action_table(cfg, pipeline, scenes, dynamics, generator,
                                                                     twin=twin),
               "cross_view": cross_view_table(cfg, pipeline, scenes, shared, generator)}
    atomic_write_text(run_dir / "gaia2_evaluation.json", json.dumps(results, indent=2))
    table = markdown(results)
    atomic_write_text(run_dir / "gaia2_evaluation.md", table)
    print(table)  # the tables the command is run for
    return results
