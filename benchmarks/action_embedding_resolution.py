r"""How far a command moves what the first attention layer of a GAIA-1 world model reads at the action positions
(issue 50, item 2: "embedding scale" among what the paper leaves open).

GAIA-1 §2.1 maps each action scalar to d by its own linear layer; ours first normalises it (model.net.action_norm:
speed by 8 m/s, curvature by 0.03 1/m). A pre-norm block reads LayerNorm(a·w + b + position), which is blind to the
token's scale: a speed change moves the input only as far as a·w turns against the constant part b + position. So a
speed contrast could enter the net too faintly to be learned. This measures it: for each action channel, the norm of
the change of block 0's normalised input at that channel's action position, divided by the input's norm, for a change
of `--speed-step` m/s or `--curvature-step` 1/m, averaged over a grid of base actions and over the window's steps.

    python benchmarks/action_embedding_resolution.py --out resolution \
        --model paper_1x=outputs/paper_faithful/world_model_cpu/checkpoints/last.ckpt \
        --model paper_2x=outputs/paper_faithful/world_model_cpu_2x/checkpoints/last.ckpt

Writes resolution.json and resolution.md into --out. A weights folder works as --model too.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gaia_app.models.gaia1.world_model import WorldModel  # noqa: E402
from gaia_app.utils.run_dir import atomic_write_text  # noqa: E402

BASE_SPEEDS = (4.0, 8.0, 12.0, 16.0, 20.0)  # m/s, the synthetic world's range
BASE_CURVATURES = (-0.02, 0.0, 0.02)  # 1/m
CHANNELS = ("speed", "curvature")


def action_inputs(net: WorldModel, actions: torch.Tensor) -> torch.Tensor:
    """Block 0's normalised inputs at the action positions of every step: actions (k, 2) physical → (k, T, l, d)."""
    tokens = net.conditioner.embed_actions(actions[:, None])[:, 0]  # (k, l, d)
    position = net.spatial[net.m + net.n:][None] + net.temporal[:, None]  # (T, l, d)
    return net.transformer.blocks[0].norm1(tokens[:, None] + position[None])


@torch.no_grad()
def resolution(net: WorldModel, speed_step: float, curvature_step: float) -> dict[str, dict[str, float]]:
    """{changed channel: {token channel: mean ‖Δ input‖ / ‖input‖}} over the base grid and the window's steps.
    A channel's change moves only its own token (the paper's independent linear layers), so the off-diagonal is 0."""
    if net.temporal_encoding != "learned":
        raise ValueError(f"temporal_encoding={net.temporal_encoding!r}: the measure reads learned time embeddings")
    base = torch.tensor([[s, c] for s in BASE_SPEEDS for c in BASE_CURVATURES])
    reference = action_inputs(net, base)
    out = {}
    for channel, step in zip(CHANNELS, (speed_step, curvature_step)):
        moved = base.clone()
        moved[:, CHANNELS.index(channel)] += step
        change = (action_inputs(net, moved) - reference).norm(dim=-1) / reference.norm(dim=-1)  # (k, T, l)
        out[channel] = {token: float(change[..., i].mean()) for i, token in enumerate(CHANNELS)}
    return out


def load(path: Path) -> WorldModel:
    from gaia_app.protocols.action_signal_report import load_world_model

    return load_world_model(path)[0]


def markdown(results: dict[str, Any], speed_step: float, curvature_step: float) -> str:
    lines = [f"| model | speed +{speed_step:g} m/s: speed token | curvature +{curvature_step:g} 1/m: curvature token |",
             "|---|---:|---:|"]
    for name, r in results.items():
        lines.append(f"| {name} | {r['speed']['speed']:.3f} | {r['curvature']['curvature']:.3f} |")
    return "\n".join(lines) + "\n"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", action="append", required=True, help="NAME=<checkpoint or weights folder>")
    p.add_argument("--speed-step", type=float, default=1.8, help="m/s (half the commanded accelerate − brake)")
    p.add_argument("--curvature-step", type=float, default=0.01, help="1/m")
    p.add_argument("--out", type=Path, required=True)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    results = {}
    for spec in args.model:
        name, sep, path = spec.partition("=")
        if not sep or not name or not Path(path).exists():
            raise SystemExit(f"--model {spec!r}: expected NAME=<existing checkpoint or weights folder>")
        results[name] = resolution(load(Path(path)), args.speed_step, args.curvature_step)
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"speed_step": args.speed_step, "curvature_step": args.curvature_step, "models": results}
    atomic_write_text(args.out / "resolution.json", json.dumps(report, indent=2))
    atomic_write_text(args.out / "resolution.md", markdown(results, args.speed_step, args.curvature_step))
    print(markdown(results, args.speed_step, args.curvature_step))
    return report


if __name__ == "__main__":
    main()
