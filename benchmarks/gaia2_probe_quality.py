r"""Can the GAIA-2 action probe read the commands? Model-free check of gaia_app/protocols/gaia2_actions.py.

Trains the inverse-dynamics probe as `generate.py model=gaia2 mode=evaluate` does (the settings of
`model.evaluate`, given as Hydra overrides), then scores the held-out scenes without any world model: the ceiling
(each scene re-simulated with each commanded action) against the reference (the real continuation, which ignores
the commands and so scores what a model that ignores them would). The evaluation's probe check asks
ceiling ≤ ½ reference for the speed and curvature contrast errors. The tokenized ceiling (the re-simulated frames
through the video tokenizer of `weights`, the shipped one by default) is what a perfect latent world model would
score: if it misses the target floor − ½ (floor − ceiling), the probe, not the world model, bounds the table.

    python benchmarks/gaia2_probe_quality.py model.evaluate.contexts=16 model.evaluate.probe_clips=96 \
        model.evaluate.probe_steps=1500                       # the shipped weights' evaluation protocol
    python benchmarks/gaia2_probe_quality.py … model.evaluate.probe_stride=1   # adjacent frames (before 2026-11-26)
    python benchmarks/gaia2_probe_quality.py … model.evaluate.probe_cameras=rig  # every camera of the rig
    python benchmarks/gaia2_probe_quality.py … model.evaluate.speed_probe=twin   # speed read by the twin probe
    python benchmarks/gaia2_probe_quality.py --twin-out DIR … speed_probe=twin   # and save that twin probe in DIR
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from gaia_app.data.transforms import to_float
from gaia_app.eval.controllability import contrast_pairs, probe_clips
from gaia_app.protocols import gaia2_actions
from gaia_app.protocols.controllability import CONTRASTS, commanded_actions, error_row
from gaia_app.protocols.gaia2_action_probe import action_probe
from gaia_app.protocols.gaia2_evaluate import rig_samples
from gaia_app.protocols.gaia2_twin_probe import read_speed_with_twins, twin_probe
from gaia_app.protocols.loading import load_gaia2

CONF = Path(__file__).resolve().parents[1] / "conf"
TEMPORAL = 4  # frames per latent step of the shipped GAIA-2 tokenizer: the evaluation's frames are model.steps · 4


def probe_quality(overrides: list[str], twin_to: Path | None = None) -> dict[str, dict[str, float]]:
    """{metric: {ceiling, tokenized, reference, ratio, target}} of contrast errors, and the probe's fit, for
    `overrides` of generate.yaml (weights= picks the tokenizer; the shipped one by default). A twin probe trained
    here is saved to `twin_to` (a folder later runs load with model.evaluate.twin_probe)."""
    GlobalHydra.instance().clear()  # a caller's Hydra (tests compose many configs) must not block this one
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("generate", ["model=gaia2", "data=synthetic_rig", "weights=gaia2", *overrides])
    g, e = cfg.model, cfg.model.evaluate
    first, frames = g.context_steps * TEMPORAL, g.steps * TEMPORAL
    started = time.perf_counter()
    probe, info = action_probe(cfg, frames)  # model.evaluate.action_probe=<folder> loads a saved one
    fit = {"action_probe": info.get("fit"), **({"action_probe_from": info["loaded_from"]} if "loaded_from" in info
                                                else {})}
    samples = rig_samples(cfg, cfg.context.seed, e.contexts, frames)
    rate = float(samples[0].clip.fps)
    views = gaia2_actions.probe_views(cfg)
    contexts = probe_clips([s.clip for s in samples], rate, frames, views)
    commands = [tuple(c) for c in e.commands]
    commanded = commanded_actions(contexts, first, frames - first, rate, commands)
    rigs = [to_float(torch.from_numpy(gaia2_actions.resimulated(cfg, k % len(samples), commanded[k].numpy()
                                                                .astype("float64")).frames))
            for k in range(len(commanded))]  # (v, f, 3, H, W) each
    pipeline = load_gaia2(cfg)
    videos = {"ceiling": torch.stack([gaia2_actions.views_of(rig, views) for rig in rigs]),
              "tokenized": torch.stack([gaia2_actions.views_of(tokenized(pipeline, rig), views) for rig in rigs]),
              "reference": torch.cat([contexts.frames] * len(commands))}
    stride = gaia2_actions.probe_stride(cfg)
    rows = {name: error_row(probe, video, commanded, first + stride, len(commands), stride)
            for name, video in videos.items()}
    twin, twin_fit = twin_probe(cfg, frames, twin_to)
    if twin is not None:  # speed_probe=twin: the speed contrast read from the two futures side by side
        speed_pair = contrast_pairs(commanded[:, first:-1].unflatten(0, (len(commands), -1)))[0]
        read_speed_with_twins(rows, videos, twin, commanded, first, stride, len(commands), speed_pair, rate,
                              dict.fromkeys(videos, 1))
        fit = {**fit, "twin_probe": twin_fit.get("fit")}
    metrics = [*CONTRASTS, *(["speed_contrast_pair"] if twin is not None else [])]
    out = {m: {name: rows[name][m]["mean"] for name in videos} for m in metrics}
    for values in out.values():
        values["ratio"] = values["ceiling"] / values["reference"]
        values["target"] = values["reference"] - 0.5 * (values["reference"] - values["ceiling"])  # floor = reference
    out["fit"] = {**fit, "seconds": time.perf_counter() - started}
    return out


@torch.no_grad()
def tokenized(pipeline: Any, rig: torch.Tensor) -> torch.Tensor:
    """One clip of every camera (v, t, 3, H, W) → the same through the pipeline's video tokenizer (posterior mean),
    as the evaluation's tokenized ceiling."""
    tokenizer = pipeline.tokenizer
    return tokenizer.decode(tokenizer.encode(rig[None]).mean).clamp(-1, 1)[0]


def main() -> None:
    args = sys.argv[1:]
    twin_to = Path(args.pop(1)) if args[:1] == ["--twin-out"] and len(args) > 1 else None
    overrides = args[1:] if twin_to else args
    if any(a.startswith("-") for a in overrides):
        sys.exit(__doc__)
    result = probe_quality(overrides, twin_to)
    print(f"overrides: {' '.join(overrides) or '(none)'}; {result['fit']['seconds']:.0f} s")
    print("| contrast error | ceiling | tokenized ceiling | reference | ceiling / reference (want ≤ 0.5) | target |")
    print("|---|---:|---:|---:|---:|---:|")
    for metric in [m for m in result if m != "fit"]:
        r = result[metric]
        print(f"| {metric} | {r['ceiling']:.4f} | {r['tokenized']:.4f} | {r['reference']:.4f} | {r['ratio']:.2f} | "
              f"{r['target']:.4f} |")


if __name__ == "__main__":
    main()
