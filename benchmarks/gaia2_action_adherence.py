r"""GAIA-2 action adherence of several weights folders, or guidance scales, side by side in one run: one action
probe, the same held-out scenes, commands and noise for every folder and scale. The table is the one of
`generate.py model=gaia2 mode=evaluate` (gaia_app/protocols/gaia2_actions.py) without the other tables, so two versions
of the weights compare in about a third of two evaluations' time. `--scales` replaces model.guidance.scale by each
of its values in turn (0: unguided), `--intervals` model.guidance.interval (the flow times at which a solver step is
guided). The real continuations of the ceiling row depend on neither the weights nor the scale: they are rendered
once and shared by every variant. Everything after `--` is a Hydra override of generate.yaml.

    python benchmarks/gaia2_action_adherence.py --weights gaia2 my_weights --out outputs/adherence -- \
        model.evaluate.contexts=16 model.evaluate.probe_clips=256 model.evaluate.probe_steps=3000 \
        model.guidance.scale=4 'model.guidance.conditions=[action]'
    python benchmarks/gaia2_action_adherence.py --weights gaia2 --scales 4 8 --tables actions fidelity \
        --out outputs/scales -- \
        model.evaluate.noise_draws=2 'model.guidance.conditions=[action]' 'evaluate.metrics=[psnr,ssim,fvmd]'

`--tables fidelity` gives (or `--tables actions fidelity` adds) the evaluation's fidelity table for each variant
(its rollouts under the scenes' own actions against the real continuations: what a guidance scale costs in PSNR,
SSIM and motion statistics, FVMD).

The action probe is trained once per run (about half its time on a CPU) and saved to `--out`/action_probe; `--probe
<that folder>` loads it in a later run instead (protocols/gaia2_action_probe.py: it must read the same rig, size,
rate, cameras and stride, and come from another world than the one scored). With `model.evaluate.speed_probe=twin`
the speed contrast is read by the twin probe (protocols/gaia2_twin_probe.py), trained once and saved to
`--out`/twin_probe, or loaded with `model.evaluate.twin_probe=<folder>`.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig

from gaia_app.eval.intervals import mean_interval
from gaia_app.eval.report import ARROWS
from gaia_app.pipelines.gaia2_edits import cut_steps
from gaia_app.protocols import gaia2_actions
from gaia_app.protocols.controllability import CONTRASTS
from gaia_app.protocols.fidelity import check_metrics
from gaia_app.protocols.gaia2_action_probe import action_probe
from gaia_app.protocols.gaia2_evaluate import fidelity_table, rig_samples
from gaia_app.protocols.gaia2_twin_probe import twin_probe
from gaia_app.protocols.loading import load_gaia2
from gaia_app.utils.run_dir import atomic_write_text

CONF = Path(__file__).resolve().parents[1] / "conf"


def with_weights(cfg: DictConfig, folder: str, scale: float | None = None,
                 interval: tuple[float, float] | None = None) -> DictConfig:
    """A copy of `cfg` with weights=`folder` and, unless None, model.guidance.scale=`scale` and
    model.guidance.interval=`interval`."""
    copy = cfg.copy()
    copy.weights = folder
    if scale is not None:
        copy.model.guidance.scale = float(scale)
    if interval is not None:
        copy.model.guidance.interval = list(interval)
    return copy


def variant_name(folder: str, scale: float | None, interval: tuple[float, float] | None = None) -> str:
    name = folder if scale is None else f"{folder}, guidance ×{scale:g}"
    return name if interval is None else f"{name}, τ ∈ [{interval[0]:g}, {interval[1]:g}]"


def parse_interval(text: str) -> tuple[float, float]:
    """'lo,hi' → (lo, hi): an --intervals value (flow times at which a solver step is guided)."""
    parts = text.split(",")
    try:
        lo, hi = (float(x) for x in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--intervals {text!r}: expected lo,hi, e.g. 0,0.5") from None
    return lo, hi


TABLES = ("actions", "fidelity")


def adherence(folders: list[str], overrides: list[str], scales: list[float] | None = None,
              tables: tuple[str, ...] = ("actions",),
              intervals: list[tuple[float, float]] | None = None, probe_to: Path | None = None) -> dict[str, Any]:
    """For each weights folder (× each guidance scale of `scales` × each guidance interval of `intervals`) on one set
    of scenes: {"tables": {name: action
    table}} with "probe_fit" (one probe for all: its info and fit, gaia2_action_probe.action_probe) when `tables` has
    "actions", and {"fidelity": {name: the evaluation's fidelity table}} when it has "fidelity" (what the guidance
    costs in PSNR / SSIM / FVMD; `evaluate.metrics` without agent_iou). A trained probe is saved to `probe_to`."""
    GlobalHydra.instance().clear()  # a caller's Hydra (tests compose many configs) must not block this one
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("generate", ["model=gaia2", "data=synthetic_rig", "mode=evaluate", f"weights={folders[0]}",
                                   *overrides])
    gaia2_actions.check_action_agents(cfg)
    gaia2_actions.probe_stride(cfg)
    gaia2_actions.probe_mirror(cfg)
    if not tables or set(tables) - set(TABLES):
        raise ValueError(f"--tables {list(tables)}: choose from {list(TABLES)}")
    if "fidelity" in tables:
        check_metrics(cfg.evaluate)
        if "agent_iou" in cfg.evaluate.metrics:
            raise ValueError("--fidelity scores evaluate.metrics without a segmentation probe: drop agent_iou, e.g. "
                             "'evaluate.metrics=[psnr,ssim,fvmd]'")
    if scales is not None and any(scale < 0 for scale in scales):
        raise ValueError(f"--scales {scales}: guidance scales must be ≥ 0")
    pipelines = {variant_name(folder, scale, interval): load_gaia2(with_weights(cfg, folder, scale, interval))
                 for folder in folders for scale in (scales or [None]) for interval in (intervals or [None])}
    # (a bad folder or interval fails here, before any probe or rollout)
    frames = cfg.model.steps * next(iter(pipelines.values())).temporal
    started = time.perf_counter()
    probe, fit = action_probe(cfg, frames, probe_to) if "actions" in tables else (None, None)
    twin, twin_fit = (twin_probe(cfg, frames, probe_to.parent / "twin_probe" if probe_to else None)
                      if "actions" in tables else (None, None))
    samples = rig_samples(cfg, cfg.context.seed, cfg.model.evaluate.contexts, frames)
    actions, fidelities, ceilings = {}, {}, {}  # the real continuations are rendered once for every variant
    for name, pipeline in pipelines.items():
        scenes = [(s, cut_steps(pipeline.encode(s.clip), cfg.model.steps)) for s in samples]
        generator = torch.Generator().manual_seed(int(cfg.seed))  # the same noise for every folder and scale
        if "actions" in tables:
            actions[name] = gaia2_actions.action_table(cfg, pipeline, scenes, probe, generator, ceilings, twin)
        if "fidelity" in tables:
            fidelities[name] = fidelity_table(cfg, pipeline, scenes, None, torch.Generator().manual_seed(int(cfg.seed)))
    return {"probe_fit": fit, **({"twin_probe_fit": twin_fit} if twin_fit else {}),
            "seconds": time.perf_counter() - started, "overrides": overrides, "scales": scales,
            "intervals": intervals,
            "tables": actions, **({"fidelity": fidelities} if "fidelity" in tables else {})}


def markdown(result: dict[str, Any]) -> str:
    """One action table per folder (the evaluation's layout), each headed by its folder."""
    lines = [f"Overrides: {' '.join(result['overrides']) or '(none)'}; {result['seconds']:.0f} s", ""]
    lines += fidelity_lines(result.get("fidelity"))
    first = next(iter(result["tables"]), None)
    for name, table in result["tables"].items():
        lines += [f"### weights={name}", "", *gaia2_actions.markdown(table), ""]
        if name != first:
            lines += [paired_line(result["tables"][first], table, first), ""]
    return "\n".join(lines)


def fidelity_lines(fidelity: dict[str, Any] | None) -> list[str]:
    """One table: each variant's rollouts (scenes' own actions, every camera) against the real continuations, next to
    the tokenized real clip and the held frame."""
    if not fidelity:
        return []
    some = next(iter(fidelity.values()))
    names = list(some["rows"]["model (rollouts)"])
    lines = [(f"Fidelity ({some['clips']} clips (scene × camera), {some['context_frames']} context + "
              f"{some['generated_frames']} generated frames)"), "",
             "| rollouts vs real continuations | " + " | ".join(f"{n} {ARROWS[n]}" for n in names) + " |",
             "|---" + "|---:" * len(names) + "|"]
    rows = {name: table["rows"]["model (rollouts)"] for name, table in fidelity.items()}
    rows |= {row: values for row, values in some["rows"].items() if row != "model (rollouts)"}
    return lines + [f"| {row} | " + " | ".join(f"{values[n]:.3f}" for n in names) + " |"
                    for row, values in rows.items()] + [""]


def paired_line(reference: dict[str, Any], table: dict[str, Any], name: str) -> str:
    """The model row's contrast errors minus those of `reference` (the first table), paired by scene, ± 95 %."""
    cells = []
    for metric in CONTRASTS:
        ours, theirs = (t["rows"]["model"][metric]["per_context"] for t in (table, reference))
        difference = mean_interval([a - b for a, b in zip(ours, theirs)])
        digits = 4 if "curvature" in metric else 3
        cells.append(f"{metric.replace('_', ' ')} {difference.mean:+.{digits}f} [{difference.low:+.{digits}f}, "
                     f"{difference.high:+.{digits}f}]")
    return f"Model row minus weights={name}'s, paired by scene (same noise): " + "; ".join(cells)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", nargs="+", required=True, help="weights folders (gaia2 or paths)")
    parser.add_argument("--scales", nargs="+", type=float, help="guidance scales, each replacing model.guidance.scale")
    parser.add_argument("--intervals", nargs="+", type=parse_interval,
                        help="guidance intervals lo,hi (flow time), each replacing model.guidance.interval")
    parser.add_argument("--tables", nargs="+", choices=TABLES, default=["actions"],
                        help="actions (default) and/or fidelity: the evaluation's fidelity table per variant")
    parser.add_argument("--out", type=Path, help="folder for action_adherence.{json,md} and the trained action_probe/")
    parser.add_argument("--probe", type=Path, help="an earlier run's action_probe folder, loaded instead of training")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of generate.yaml (after --)")
    args = parser.parse_args(argv)
    overrides = [*args.overrides, *([f"model.evaluate.action_probe={args.probe}"] if args.probe else [])]
    result = adherence(args.weights, overrides, args.scales, tuple(args.tables), args.intervals,
                       args.out / "action_probe" if args.out else None)
    table = markdown(result)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out / "action_adherence.json", json.dumps(result, indent=2))
        atomic_write_text(args.out / "action_adherence.md", table)
    print(table)
    return result


if __name__ == "__main__":
    main()
