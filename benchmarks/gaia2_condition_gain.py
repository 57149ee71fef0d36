r"""What a trained GAIA-2 latent world model reads from its actions and agents, teacher-forced on held-out windows.

    python benchmarks/gaia2_condition_gain.py --world-model-ckpt WM/checkpoints/last.ckpt \
        --latents data/latents/val --out outputs/condition_gain.json
    python benchmarks/gaia2_condition_gain.py --weights gaia2 --latents data/latents/val   # a weights folder

Every window of `--steps` latent steps at every start of every clip in `--latents`; the first `--context` steps
clean, the rest noised at τ ∈ {0.25, 0.5, 0.75} (or `--taus`) with two fixed noise draws each
(gaia_app/eval/flow_gain.py).
Prints, per variant of the conditions, the velocity MSE and what it saves over dropping both actions and agents,
and the action discrimination: the loss of another window's actions minus that of the window's own, with and
without agents, and per action component (speed or curvature alone swapped) (± 95 % over windows). A model that
steers by its actions has a discrimination interval above 0.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from gaia_app.eval.flow_gain import TAUS, condition_gain_report, every_window
from gaia_app.utils.run_dir import atomic_write_text
from gaia_app.weights.folders import load_nets, shipped_folder
from gaia_app.weights.nets import checkpoint_nets


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--world-model-ckpt", help="a latent world model training checkpoint")
    source.add_argument("--weights", help="or a weights folder (e.g. gaia2)")
    parser.add_argument("--latents", required=True, help="a split folder of a latent cache (e.g. data/latents/val)")
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--context", type=int, default=2)
    parser.add_argument("--taus", type=float, nargs="+", default=list(TAUS),
                        help="flow times to score, in [0, 1) (default %(default)s; 0 is pure noise)")
    parser.add_argument("--out", help="also write the numbers to this JSON file")
    args = parser.parse_args()
    if args.weights:
        nets, config = load_nets(shipped_folder(args.weights), "latent_world_model")
    else:
        nets, config, _ = checkpoint_nets(args.world_model_ckpt, "latent_world_model", "--world-model-ckpt", "cpu")
    net = nets["net"].eval()
    batch = every_window(args.latents, args.steps, list(net.conditioner.metadata_fields))
    report = condition_gain_report(net, batch, float(config.get("latent_scale", 1.0)), args.context, args.taus)
    print(f"{report['windows']} windows of {args.steps} steps, {args.context} clean")
    for name in report["losses"]:
        gain = report["gain_over_neither"][name]
        print(f"  {name:28s} loss {report['losses'][name]:.5f}   saves {gain['mean']:+.5f} "
              f"[{gain['low']:+.5f}, {gain['high']:+.5f}]")
    for agents, d in report["action_discrimination"].items():
        print(f"  action discrimination {agents:15s} {d['mean']:+.5f} [{d['low']:+.5f}, {d['high']:+.5f}]")
    for component, d in report["component_discrimination"].items():
        print(f"  {component} alone swapped (agents given) {d['mean']:+.5f} [{d['low']:+.5f}, {d['high']:+.5f}]")
        for key, label in (("by_tau", "at τ"), ("by_step", "at step"), ("by_clip", "on")):
            for where, e in report[f"component_discrimination_{key}"][component].items():
                print(f"    {label} {where:15s} {e['mean']:+.5f} [{e['low']:+.5f}, {e['high']:+.5f}]")
    if args.out:
        atomic_write_text(Path(args.out), json.dumps(report, indent=2))


if __name__ == "__main__":
    torch.manual_seed(0)
    main()
