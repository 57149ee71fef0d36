r"""GAIA-2 agent control under guidance, alone: the agent table of `generate.py model=gaia2 mode=evaluate`
(gaia_app/protocols/gaia2_evaluate.py) without the fidelity, action and cross-view tables, in about a third of an
evaluation's time. Besides the pooled IoU with the agent masks it splits where guidance acts: the IoU inside the
conditioning boxes, and the share of the area outside every box that the probe calls agent. Spatially selective CFG
guides the tokens inside the boxes only; plain CFG also guides the rest of the scene away from the agents-dropped
prediction, which is where the two can differ. Everything after `--` is a Hydra override of generate.yaml.

    python benchmarks/gaia2_agent_guidance.py --weights gaia2 --out outputs/agent_guidance -- \
        model.evaluate.contexts=16 model.evaluate.probe_clips=96 model.evaluate.probe_steps=1500 \
        model.evaluate.cfg_scale=3

`--variants plain,full` runs only plain CFG and the full-second-pass selective rows (besides the unguided ones), and
`--guided-only` leaves the unguided model rows out too, so a confirmatory comparison of two variants affords more
scenes.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from gaia_app.pipelines.gaia2_edits import cut_steps
from gaia_app.protocols import gaia2_evaluate
from gaia_app.protocols.loading import load_gaia2
from gaia_app.utils.run_dir import atomic_write_text

CONF = Path(__file__).resolve().parents[1] / "conf"


def agent_guidance(weights: str, overrides: list[str],
                   variants: Sequence[str] = tuple(gaia2_evaluate.GUIDED_VARIANTS), unguided: bool = True
                   ) -> dict[str, Any]:
    """The agent table (with its inside / outside split) of the weights folder `weights` on held-out scenes, with
    the guided rows `variants` (plain CFG always) and, with `unguided`, the agent-conditioned and agents-dropped
    rows."""
    GlobalHydra.instance().clear()  # a caller's Hydra (tests compose many configs) must not block this one
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("generate", ["model=gaia2", "data=synthetic_rig", "mode=evaluate", f"weights={weights}",
                                   *overrides])
    if not cfg.model.evaluate.cfg_scale:
        raise ValueError("model.evaluate.cfg_scale=0: the guided rows this benchmark compares need a scale")
    pipeline = load_gaia2(cfg)
    frames = cfg.model.steps * pipeline.temporal
    started = time.perf_counter()
    probe, fit = gaia2_evaluate.train_segmentation_probe(cfg, frames)
    scenes = [(s, cut_steps(pipeline.encode(s.clip), cfg.model.steps))
              for s in gaia2_evaluate.rig_samples(cfg, cfg.context.seed, cfg.model.evaluate.contexts, frames)]
    table, _ = gaia2_evaluate.agent_table(cfg, pipeline, scenes, probe, torch.Generator().manual_seed(int(cfg.seed)),
                                          variants, unguided)
    return {"weights": weights, "overrides": overrides, "variants": list(variants), "probe_fit": fit,
            "seconds": time.perf_counter() - started, "cameras": [c.name for c in scenes[0][1].cameras],
            "agents": table}


def markdown(result: dict[str, Any]) -> str:
    lines = [(f"weights={result['weights']}; overrides: {' '.join(result['overrides']) or '(none)'}; "
              f"{result['seconds']:.0f} s"), ""]
    return "\n".join(lines + gaia2_evaluate.agent_markdown(result["agents"], result["cameras"])) + "\n"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default="gaia2", help="weights folder (gaia2 or a path)")
    parser.add_argument("--out", type=Path, help="folder for agent_guidance.{json,md}")
    parser.add_argument("--variants", default=",".join(gaia2_evaluate.GUIDED_VARIANTS),
                        help="guided rows, comma-separated, of " + ", ".join(gaia2_evaluate.GUIDED_VARIANTS)
                        + " (plain always runs; fewer rows fit more scenes in the same time)")
    parser.add_argument("--guided-only", action="store_true",
                        help="leave out the unguided model rows (agent conditions, agents dropped): "
                             "a third less time a scene")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of generate.yaml (after --)")
    args = parser.parse_args(argv)
    result = agent_guidance(args.weights, args.overrides, [v for v in args.variants.split(",") if v],
                            unguided=not args.guided_only)
    table = markdown(result)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out / "agent_guidance.json", json.dumps(result, indent=2))
        atomic_write_text(args.out / "agent_guidance.md", table)
    print(table)
    return result


if __name__ == "__main__":
    main()
