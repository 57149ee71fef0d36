r"""How far the action table's commanded contrasts move each GAIA-2 world model's AdaLN modulation, read off the
weights (gaia_app/protocols/gaia2_action_modulation.py): no scenes, no sampling, a few seconds per weights folder.

    python benchmarks/gaia2_action_modulation.py --weights gaia2 my_weights_1x my_weights_8x --out outputs/modulation

The commands, frame rate and steps are those of the action table (generate.yaml with model=gaia2
data=synthetic_rig; Hydra overrides after `--`); the latent step's frames from each folder's tokenizer. Writes
action_modulation.{json,md} into --out.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gaia2_contrast_trace import compose_config  # noqa: E402

from gaia_app.protocols.gaia2_action_modulation import action_modulation  # noqa: E402
from gaia_app.protocols.loading import load_gaia2  # noqa: E402
from gaia_app.utils.run_dir import atomic_write_text  # noqa: E402


def readings(folders: list[str], start_speeds: list[float], taus: list[float], overrides: list[str]
             ) -> dict[str, Any]:
    """{"settings": …, "weights": {folder: action_modulation}} on the action table's commands."""
    cfg = compose_config(folders[0], overrides)  # commands, rate and steps: the table's, the same for every folder
    g = cfg.model
    steps = int(g.steps - g.context_steps)
    rate = float(cfg.data.fps or cfg.data.source.fps)  # the rate the scenes are rendered at when not resampled
    out = {}
    for folder in folders:
        pipeline = load_gaia2(compose_config(folder, overrides))
        out[folder] = action_modulation(pipeline.world.model.eval(), [tuple(c) for c in g.evaluate.commands],
                                        start_speeds, steps, pipeline.temporal, rate, taus)
    return {"settings": {"commands": [list(c) for c in g.evaluate.commands], "start_speeds": start_speeds,
                         "taus": taus, "generated_steps": steps, "rate": rate, "overrides": overrides},
            "weights": out}


def markdown(result: dict[str, Any]) -> str:
    s = result["settings"]
    lines = [f"Relative change of the AdaLN vector and modulations between the two commands of each contrast "
             f"(mean [smallest, largest] over start speeds {s['start_speeds']} m/s, τ {s['taus']} and the "
             f"{s['generated_steps']} generated latent steps at {s['rate']:g} Hz); overrides: "
             f"{' '.join(s['overrides']) or '(none)'}", "",
             "| weights | contrast | Fourier features, distance | AdaLN vector, relative "
             "| blocks' modulation, relative (mean over blocks) | … absolute | output layer, relative |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for folder, contrasts in result["weights"].items():
        for name, reading in contrasts.items():
            cells = [reading["summary"][key]
                     for key in ("features", "conditioner", "blocks_mean", "blocks_mean_change", "output")]
            lines.append(f"| {folder} | {name} ({' − '.join(reading['commands'])}) | "
                         + " | ".join(f"{c['mean']:.4f} [{c['min']:.4f}, {c['max']:.4f}]" for c in cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", nargs="+", required=True, help="weights folders (gaia2 or paths)")
    parser.add_argument("--start-speeds", nargs="+", type=float, default=[6.0, 10.0, 14.0],
                        help="speeds (m/s) the commands start from (default %(default)s: the worlds' context speeds)")
    parser.add_argument("--taus", nargs="+", type=float, default=[0.0, 0.5, 0.9],
                        help="flow times, 0 pure noise (default %(default)s)")
    parser.add_argument("--out", type=Path, help="folder for action_modulation.{json,md}")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of generate.yaml (after --)")
    args = parser.parse_args(argv)
    result = readings(args.weights, args.start_speeds, args.taus, args.overrides)
    table = markdown(result)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out / "action_modulation.json", json.dumps(result, indent=2))
        atomic_write_text(args.out / "action_modulation.md", table)
    print(table)
    return result


if __name__ == "__main__":
    main()
