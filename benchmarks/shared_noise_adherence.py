r"""GAIA-1 action adherence with and without shared sampling noise, side by side over several sampling seeds.

The action table of `generate.py mode=controllability` (gaia_app/protocols/controllability.py) contrasts two futures of
one context (accelerate vs brake, left vs right). Sampled independently, the two futures differ by their commands
and by sampling luck; with `controllability.shared_noise` they share every Gumbel draw (counterfactual futures,
ar_sampling.shared_gumbel), as the ceiling's re-simulations share their world. Each future's own distribution is
the same either way, so the mean realised difference cannot change, only its spread. This script measures both on
the same contexts, probes and seeds: the model row of the action table per seed and coupling, the ceiling and floor
once, the target, and the per-context difference shared − independent (95 % over contexts, seeds averaged).

    python benchmarks/shared_noise_adherence.py --weights gaia1 --seeds 42 1 2 3 4 5 --out outputs/shared_noise -- \
        context.seed=2000 controllability.contexts=32

Everything after `--` is a Hydra override of generate.yaml (the protocol's context length, horizon and guidance are
the defaults below). Writes results.json and results.md into --out.
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
from tqdm import tqdm

from gaia_app.eval.controllability import contrast_pairs, probe_clips
from gaia_app.eval.intervals import mean_interval
from gaia_app.pipelines.gaia1_inputs import future_frames
from gaia_app.protocols.controllability import (
    CONTRASTS,
    commanded_actions,
    context_groups,
    error_row,
    probes_for,
    resimulate,
    rollout_frames,
    world_clips,
)
from gaia_app.protocols.loading import load_pipeline
from gaia_app.utils.run_dir import atomic_write_text

CONF = Path(__file__).resolve().parents[1] / "conf"
# the shipped weights' protocol (gaia_app/weights/MANIFEST.md, controllability)
PROTOCOL = ["mode=controllability", "context.frames=4", "seconds=1.25", "guidance.scale=1.5", "guidance.text_scale=3"]
COUPLINGS = ("independent", "shared")


def compare(weights: str, seeds: list[int], overrides: list[str], out: Path,
            couplings: tuple[str, ...] = COUPLINGS) -> dict[str, Any]:
    """The action rows (ceiling, floor, model per seed and coupling) and, with both couplings, their paired
    differences."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("generate", [*PROTOCOL, f"weights={weights}", *overrides])
    started = time.perf_counter()
    pipeline = load_pipeline(cfg, video_decoder=False)
    c, rate, (height, width) = cfg.controllability, pipeline.rate, pipeline.image_size
    t0, frames = cfg.context.frames, future_frames(cfg.seconds, rate, at_least=2)
    probe = probes_for(cfg, pipeline, t0 + frames, out)[0]  # the weights' own probes
    total = t0 + frames
    contexts = probe_clips(world_clips(cfg.context.seed, c.contexts, height, width, total, rate), rate, total)
    commands = [tuple(cmd) for cmd in c.commands]
    commanded = commanded_actions(contexts, t0, frames, rate, commands)
    contrast_pairs(commanded[:, t0:-1].unflatten(0, (len(commands), -1)))  # refuses commands with nothing to contrast
    n, repeat = c.contexts, len(commands)
    row = lambda video: error_row(probe, video, commanded, t0 + 1, repeat)  # noqa: E731
    ceiling = torch.cat([resimulate(cfg.context.seed, i % n, height, width, commanded[i].numpy(), t0, rate).frames
                         for i in range(len(commanded))])
    context = contexts.frames[:, :t0].repeat(repeat, 1, 1, 1, 1)
    floor = rollout_frames(pipeline, contexts.frames[:, :t0], frames, n, None, None,
                           torch.Generator().manual_seed(int(cfg.seed))).repeat(repeat, 1, 1, 1, 1)
    rows: dict[str, Any] = {"ceiling": row(ceiling), "floor": row(floor)}
    for seed in tqdm(seeds, desc="sampling seeds"):
        for coupling in couplings:
            groups = context_groups(repeat, n) if coupling == "shared" else None
            video = rollout_frames(pipeline, context, frames, len(commanded), None, commanded,
                                   torch.Generator().manual_seed(seed), groups)
            rows[f"{coupling}, seed {seed}"] = row(video)
    return {"weights": weights, "overrides": overrides, "seeds": seeds, "contexts": n, "couplings": list(couplings),
            "seconds": time.perf_counter() - started, "rows": rows, "summary": summary(rows, seeds, couplings)}


def summary(rows: dict[str, Any], seeds: list[int], couplings: tuple[str, ...] = COUPLINGS) -> dict[str, Any]:
    """Per coupling and contrast: the mean error over seeds (95 % over contexts), seeds meeting the target, the
    realised difference's within-seed spread; and shared − independent per context (seeds averaged)."""
    out: dict[str, Any] = {}
    for name in CONTRASTS:
        floor, ceiling = rows["floor"][name]["mean"], rows["ceiling"][name]["mean"]
        target = floor - 0.5 * (floor - ceiling)
        per_context = {coupling: torch.tensor([rows[f"{coupling}, seed {s}"][name]["per_context"] for s in seeds])
                       for coupling in couplings}  # (seeds, N)
        entry: dict[str, Any] = {"target": target, "floor": floor, "ceiling": ceiling}
        for coupling, errors in per_context.items():
            seed_means = errors.mean(dim=1)
            realised = [rows[f"{coupling}, seed {s}"]["realised"][name] for s in seeds]
            entry[coupling] = {"over_seeds": mean_interval(errors.mean(dim=0).tolist()).as_dict(),
                               "per_seed": seed_means.tolist(), "seeds_met": int((seed_means <= target).sum()),
                               "realised_mean": sum(r["mean"] for r in realised) / len(realised),
                               "realised_sd": sum(r["sd"] for r in realised) / len(realised)}
        if len(per_context) == 2:
            difference = (per_context["shared"] - per_context["independent"]).mean(dim=0)
            entry["shared_minus_independent"] = mean_interval(difference.tolist()).as_dict()
        out[name] = entry
    return out


def markdown(result: dict[str, Any]) -> str:
    seeds = result["seeds"]
    lines = [f"weights={result['weights']}, {result['contexts']} contexts × 4 commands, sampling seeds "
             f"{', '.join(map(str, seeds))}; overrides: {' '.join(result['overrides']) or '(none)'}; "
             f"{result['seconds'] / 60:.1f} min", "",
             "| contrast | noise | error per seed | mean over seeds (± 95 % over contexts) | seeds meeting the target "
             "| realised difference (mean, sd over contexts) |", "|---|---|---|---|---|---|"]
    for name, entry in result["summary"].items():
        digits = 2 if name.startswith("speed") else 4
        for coupling in result["couplings"]:
            e = entry[coupling]
            o = e["over_seeds"]
            lines.append(f"| {name} | {coupling} | {', '.join(f'{v:.{digits}f}' for v in e['per_seed'])} | "
                         f"{o['mean']:.{digits}f} ± {(o['high'] - o['low']) / 2:.{digits}f} | {e['seeds_met']} of "
                         f"{len(seeds)} | {e['realised_mean']:.{digits}f}, {e['realised_sd']:.{digits}f} |")
    lines += ["", "| contrast | ceiling | floor | target | shared − independent (95 % over contexts) |",
              "|---|---|---|---|---|"]
    for name, entry in result["summary"].items():
        digits = 2 if name.startswith("speed") else 4
        bounds = " | ".join(f"{entry[key]:.{digits}f}" for key in ("ceiling", "floor", "target"))
        d = entry.get("shared_minus_independent")
        paired = (f"{d['mean']:+.{digits}f} [{d['low']:+.{digits}f}, {d['high']:+.{digits}f}]" if d
                  else "— (one coupling)")
        lines.append(f"| {name} | {bounds} | {paired} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default="gaia1")
    parser.add_argument("--seeds", type=int, nargs="+", default=[42, 1, 2])
    parser.add_argument("--out", type=Path, default=Path("outputs/shared_noise"))
    parser.add_argument("--couplings", nargs="+", choices=COUPLINGS, default=list(COUPLINGS),
                        help="the noise variants to roll out (both: their paired difference too)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of generate.yaml, after --")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    result = compare(args.weights, args.seeds, args.overrides, args.out, tuple(args.couplings))
    atomic_write_text(args.out / "results.json", json.dumps(result, indent=2))
    atomic_write_text(args.out / "results.md", markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
