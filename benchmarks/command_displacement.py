"""How far the GAIA-2 action table's commanded contrasts move the picture (gaia_app/protocols/command_displacement.py):
the pixel displacement between the accelerate and brake futures, and between the left and right ones, of the same
scenes, commands and rig the action table uses, from the rig's geometry (no world model is sampled; the weights
folder gives the latent grid and the steps).

    python benchmarks/command_displacement.py --weights outputs/road_users/w_paper_changes_openloop_8x \
        --out outputs/displacement_5111 -- context.seed=5111 model.evaluate.contexts=16
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from gaia_app.protocols.command_displacement import displacement_table, markdown
from gaia_app.protocols.gaia2_evaluate import rig_samples
from gaia_app.protocols.loading import load_gaia2
from gaia_app.utils.run_dir import atomic_write_text

CONF = Path(__file__).resolve().parents[1] / "conf"


def displacement(folder: str, overrides: list[str]) -> dict[str, Any]:
    """The displacement table of the action table's scenes for the weights `folder` (module docstring)."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("generate", ["model=gaia2", "data=synthetic_rig", "mode=evaluate", f"weights={folder}",
                                   *overrides])
    pipeline = load_gaia2(cfg)
    g = cfg.model
    first, frames = g.context_steps * pipeline.temporal, g.steps * pipeline.temporal
    samples = rig_samples(cfg, cfg.context.seed, g.evaluate.contexts, frames)
    cell_px = float(pipeline.tokenizer.spatial)  # pixels per latent cell
    token_px = cell_px * pipeline.world.model.patch
    table = displacement_table(samples, [tuple(c) for c in g.evaluate.commands], first, frames, cell_px, token_px)
    return {"weights": folder, "overrides": overrides, **table}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", required=True, help="a GAIA-2 weights folder (gaia2 or a path)")
    parser.add_argument("--out", type=Path, help="folder for command_displacement.{json,md}")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of generate.yaml (after --)")
    args = parser.parse_args(argv)
    result = displacement(args.weights, args.overrides)
    table = markdown(result)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out / "command_displacement.json", json.dumps(result, indent=2))
        atomic_write_text(args.out / "command_displacement.md", table)
    print(table)
    return result


if __name__ == "__main__":
    main()
