r"""Where the GAIA-2 world model loses a commanded contrast: its estimate of the clean future along the sampler against
the real re-simulated continuations' latent contrast (gaia_app/protocols/gaia2_contrast_trace.py), for several
weights folders and guidance scales on the same held-out scenes, commands and noise. No probe: the readout stays in
the latent space, so it is cheap (one rollout per scene and contrast command).

    python benchmarks/gaia2_contrast_trace.py --weights gaia2 my_weights --scales 1 4 --out outputs/trace -- \
        context.seed=5111 model.evaluate.contexts=16 'model.guidance.conditions=[action]'

Everything after `--` is a Hydra override of generate.yaml (model=gaia2 data=synthetic_rig mode=evaluate). With the
action table's settings (context.seed, contexts, seed, guidance) the finished samples are that table's model futures.
Writes contrast_trace.{json,md} into --out.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gaia2_action_adherence import CONF, variant_name, with_weights  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402
from hydra.core.global_hydra import GlobalHydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from gaia_app.pipelines.gaia2_edits import cut_steps  # noqa: E402
from gaia_app.protocols import gaia2_contrast_trace  # noqa: E402
from gaia_app.protocols.gaia2_evaluate import rig_samples  # noqa: E402
from gaia_app.protocols.loading import load_gaia2  # noqa: E402
from gaia_app.utils.run_dir import atomic_write_text  # noqa: E402


def compose_config(folder: str, overrides: list[str]) -> DictConfig:
    """generate.yaml for model=gaia2 data=synthetic_rig mode=evaluate with weights=`folder` and `overrides`."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("generate", ["model=gaia2", "data=synthetic_rig", "mode=evaluate", f"weights={folder}",
                                    *overrides])


def traces(folders: list[str], overrides: list[str], scales: list[float] | None = None) -> dict[str, Any]:
    """{"traces": {variant: contrast trace}} for each folder × guidance scale on one set of scenes and noise."""
    cfg = compose_config(folders[0], overrides)
    gaia2_contrast_trace.check_settings(cfg)  # before any weights load or scene renders
    if scales is not None and any(scale < 0 for scale in scales):
        raise ValueError(f"--scales {scales}: guidance scales must be ≥ 0")
    pipelines = {variant_name(folder, scale): load_gaia2(with_weights(cfg, folder, scale))
                 for folder in folders for scale in (scales or [None])}
    frames = cfg.model.steps * next(iter(pipelines.values())).temporal
    started = time.perf_counter()
    samples = rig_samples(cfg, cfg.context.seed, cfg.model.evaluate.contexts, frames)
    out, ceilings = {}, {}
    for name, pipeline in pipelines.items():
        scenes = [(s, cut_steps(pipeline.encode(s.clip), cfg.model.steps)) for s in samples]
        generator = torch.Generator().manual_seed(int(cfg.seed))  # the action table's noise for every variant
        out[name] = gaia2_contrast_trace.contrast_trace(cfg, pipeline, scenes, generator, ceilings)
    return {"seconds": time.perf_counter() - started, "overrides": overrides, "scales": scales, "traces": out}


def markdown(result: dict[str, Any]) -> str:
    lines = [f"Overrides: {' '.join(result['overrides']) or '(none)'}; {result['seconds']:.0f} s", ""]
    for name, trace in result["traces"].items():
        lines += [f"### weights={name}", "", *gaia2_contrast_trace.markdown(trace, name), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", nargs="+", required=True, help="weights folders (gaia2 or paths)")
    parser.add_argument("--scales", nargs="+", type=float, help="guidance scales, each replacing model.guidance.scale")
    parser.add_argument("--out", type=Path, help="folder for contrast_trace.{json,md}")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of generate.yaml (after --)")
    args = parser.parse_args(argv)
    result = traces(args.weights, args.overrides, args.scales)
    table = markdown(result)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out / "contrast_trace.json", json.dumps(result, indent=2))
        atomic_write_text(args.out / "contrast_trace.md", table)
    print(table)
    return result


if __name__ == "__main__":
    main()
