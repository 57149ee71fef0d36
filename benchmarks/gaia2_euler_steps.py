r"""How few Euler steps a GAIA-2 rollout needs: FVMD of rollouts at each step count against the real continuations,
the same scenes and noise for every count, as a ratio to 50 steps with a paired 95 % interval (issue 51, item 2:
"the fewest steps that keep its FVMD within 10 %"; the GPU times them in `gpu_checks.py`'s gaia2_rollout).

    python benchmarks/gaia2_euler_steps.py --weights gaia2 --steps 50 20 10 5 --out outputs/gaia2_euler_steps -- \
        context.seed=<an unused world> model.evaluate.contexts=16

Everything after `--` is a Hydra override of generate.yaml (model=gaia2 data=synthetic_rig mode=evaluate). Scenes
and the continuation are those of mode=evaluate's fidelity table (gaia_app/protocols/gaia2_evaluate.py): the
context latent steps given clean, the rest generated in one chunk under the scene's own conditions, every camera
scored from the last context frame on. Each step count reuses each scene's noise seed. FVMD's motion features are
computed once per clip (and saved, features.npz); the intervals are the jackknife's over scenes (their cameras
together), paired across rows. Rows:
each step count, the tokenized real continuation (ceiling) and the last context frame held (floor).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from tqdm import tqdm

from gaia_app.data.transforms import to_float
from gaia_app.diffusion.flow_matching import FlowSampler
from gaia_app.eval.frechet import FrechetStatistics, frechet_distance
from gaia_app.eval.fvmd import FEATURE_DIM, FVMD
from gaia_app.pipelines.gaia2_edits import cut_steps
from gaia_app.protocols import gaia2_evaluate
from gaia_app.protocols.fidelity import held_frame
from gaia_app.protocols.loading import load_gaia2
from gaia_app.utils.run_dir import atomic_write_text

CONF = Path(__file__).resolve().parents[1] / "conf"


def fvmd_of(real: np.ndarray, generated: np.ndarray) -> float:
    """FVMD from per-clip motion features (n, FEATURE_DIM) of the real and the generated clips."""
    stats = [FrechetStatistics(FEATURE_DIM).update(torch.from_numpy(x)) for x in (real, generated)]
    return frechet_distance(*stats)


def intervals(features: dict[str, np.ndarray], real: np.ndarray, cameras: int, reference: str
              ) -> dict[str, dict[str, float]]:
    """FVMD of every row and its ratio to `reference`, each with a 95 % interval from the jackknife over scenes:
    leave one scene (its `cameras` clips) out, for every row at once, and take ±1.96 jackknife standard errors.
    A jackknife never repeats a clip, and a repeated clip would bias a Fréchet distance (as a bootstrap's resamples
    do). Arrays are (scenes · cameras, FEATURE_DIM)."""
    scenes = real.shape[0] // cameras
    keep = [np.setdiff1d(np.arange(real.shape[0]), np.arange(s * cameras, (s + 1) * cameras)) for s in range(scenes)]
    reference_values = np.array([fvmd_of(real[k], features[reference][k]) for k in keep])
    out = {}
    for name, rows in features.items():
        values = np.array([fvmd_of(real[k], rows[k]) for k in keep])
        value, ratio = fvmd_of(real, rows), fvmd_of(real, rows) / fvmd_of(real, features[reference])
        spread = {key: 1.96 * np.sqrt((scenes - 1) / scenes * np.sum((x - x.mean()) ** 2))
                  for key, x in (("fvmd", values), ("ratio", values / reference_values))}
        out[name] = {"fvmd": value, "fvmd_low": value - spread["fvmd"], "fvmd_high": value + spread["fvmd"],
                     "ratio": ratio, "ratio_low": ratio - spread["ratio"], "ratio_high": ratio + spread["ratio"]}
    return {name: {k: float(v) for k, v in row.items()} for name, row in out.items()}


def fewest_within(rows: dict[str, dict[str, float]], steps: list[int], tolerance: float = 0.10) -> dict[str, Any]:
    """The fewest step count whose FVMD ratio to the reference is within `tolerance`: by the point estimate, and by
    the interval's upper end (the stricter reading)."""
    point = [k for k in steps if rows[f"{k} steps"]["ratio"] <= 1 + tolerance]
    strict = [k for k in steps if rows[f"{k} steps"]["ratio_high"] <= 1 + tolerance]
    return {"tolerance": tolerance, "point": min(point) if point else None, "interval": min(strict) if strict else None}


def euler_steps(weights: str, steps: list[int], overrides: list[str], features_out: Path | None = None
                ) -> dict[str, Any]:
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("generate", ["model=gaia2", "data=synthetic_rig", "mode=evaluate", f"weights={weights}",
                                   *overrides])
    pipeline = load_gaia2(cfg)
    g, tau = cfg.model, pipeline.temporal
    c, new = g.context_steps, g.steps - g.context_steps
    first, frames = c * tau, g.steps * tau
    samples = gaia2_evaluate.rig_samples(cfg, cfg.context.seed, g.evaluate.contexts, frames)
    solver, fvmd = pipeline.world.sampler, FVMD()
    names = [f"{k} steps" for k in steps]
    features: dict[str, list[np.ndarray]] = {name: [] for name in [*names, "tokenized real (ceiling)",
                                                                   "held frame (floor)"]}
    real_features, seconds = [], {name: 0.0 for name in names}
    generator = torch.Generator().manual_seed(int(cfg.seed))
    for sample in tqdm(samples, desc="scenes"):
        clip = cut_steps(pipeline.encode(sample.clip), g.steps)
        real = to_float(torch.from_numpy(sample.clip.frames[:, :frames]))  # (v, T, 3, H, W)
        real_features.append(fvmd.features(real[:, first - 1:]).numpy())
        latents, cond = pipeline.window(clip, 0, g.steps)
        noise_seed = int(torch.randint(2**31, (), generator=generator))
        for k, name in zip(steps, names):
            pipeline.world.sampler = FlowSampler(k, solver.schedule, solver.solver, solver.threshold)
            start = time.perf_counter()
            x = pipeline.world.rollout(latents[:, :, :c], [cond], new,
                                       torch.Generator(latents.device).manual_seed(noise_seed))
            seconds[name] += time.perf_counter() - start
            features[name].append(fvmd.features(pipeline.decode(x)[0].cpu()[:, first - 1:]).numpy())
        features["tokenized real (ceiling)"].append(
            fvmd.features(pipeline.decode(latents)[0].cpu()[:, first - 1:]).numpy())
        features["held frame (floor)"].append(fvmd.features(held_frame(real, first)[:, first - 1:]).numpy())
    pipeline.world.sampler = solver
    cameras = real_features[0].shape[0]
    stacked = {name: np.concatenate(rows) for name, rows in features.items()}
    real_stacked = np.concatenate(real_features)
    if features_out is not None:  # the per-clip motion features, so the statistics can be redone without the model
        np.savez(features_out, real=real_stacked, **{name: rows for name, rows in stacked.items()})
    rows = intervals(stacked, real_stacked, cameras, f"{max(steps)} steps")
    for name in names:
        rows[name]["seconds_per_rollout"] = seconds[name] / len(samples)
    return {"weights": weights, "overrides": overrides, "scenes": len(samples), "cameras": cameras,
            "generated_frames": frames - first, "rows": rows,
            "fewest_within_10_percent": fewest_within(rows, sorted(steps))}


def markdown(result: dict[str, Any]) -> str:
    lines = [f"{result['scenes']} scenes × {result['cameras']} cameras, {result['generated_frames']} generated frames "
             "each; FVMD ↓ against the real continuations, 95 % jackknife intervals over scenes", "",
             "| rollouts | FVMD | ÷ the most steps | s / rollout (this machine) |", "|---|---:|---:|---:|"]
    for name, row in result["rows"].items():
        timing = f"{row['seconds_per_rollout']:.2f}" if "seconds_per_rollout" in row else ""
        lines.append(f"| {name} | {row['fvmd']:.2f} [{row['fvmd_low']:.2f}, {row['fvmd_high']:.2f}] | "
                     f"{row['ratio']:.3f} [{row['ratio_low']:.3f}, {row['ratio_high']:.3f}] | {timing} |")
    fewest = result["fewest_within_10_percent"]
    lines += ["", f"Fewest steps within 10 % of the most: {fewest['point']} (point estimate), "
                  f"{fewest['interval']} (the interval's upper end)"]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default="gaia2")
    parser.add_argument("--steps", type=int, nargs="+", default=[50, 20, 10, 5])
    parser.add_argument("--out", default="outputs/gaia2_euler_steps")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of generate.yaml, after --")
    args = parser.parse_args()
    if min(args.steps) < 2:
        raise SystemExit(f"--steps {args.steps}: the linear-quadratic schedule needs at least 2 steps")
    torch.set_grad_enabled(False)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = euler_steps(args.weights, args.steps, args.overrides, out / "features.npz")
    atomic_write_text(out / "gaia2_euler_steps.json", json.dumps(result, indent=2))
    table = markdown(result)
    atomic_write_text(out / "gaia2_euler_steps.md", table)
    print(table)


if __name__ == "__main__":
    main()
