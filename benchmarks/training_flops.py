r"""Training compute of GAIA-1 world models, for the paper-faithful study's budgets (issue 50, GAIA-1 §6).

    python benchmarks/training_flops.py \
        --run cpu_paper=outputs/paper_faithful/weights_world_model_cpu:5000x4 \
        --run gpu_paper=outputs/gpu_d4/paper_d4:6583x16 [--json OUT]

Each run is NAME=<weights folder>:<steps>x<windows per step>. The FLOPs of one training window are those of
benchmarks/bench_gpu_world_model.py (6·N per position, N the non-embedding parameters, plus causal attention
6·L·S·d per position, S the window's positions), read off the folder's net: its width, depth, frames and positions per
step (text, image and action tokens). Printed: a Markdown table with each run's positions per window, N, total
training FLOPs and its ratio to the first run.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_gpu_world_model import model_flops_per_step  # noqa: E402
from gaia_app.eval.scaling import non_embedding_parameters  # noqa: E402
from gaia_app.models.gaia1.world_model import WorldModel  # noqa: E402
from gaia_app.weights.folders import load_nets  # noqa: E402

RUN = re.compile(r"^(?P<name>[\w.-]+)=(?P<folder>.+):(?P<steps>\d+)x(?P<batch>\d+)$")


def parse_run(text: str) -> dict[str, Any]:
    """NAME=FOLDER:STEPSxBATCH → {name, folder, steps, batch}; anything else is refused with the expected form."""
    match = RUN.match(text)
    if match is None:
        raise argparse.ArgumentTypeError(f"--run {text!r}: expected NAME=<weights folder>:<steps>x<windows per step>, "
                                         "e.g. gpu=outputs/gpu_d4/paper_d4:6583x16")
    return {"name": match["name"], "folder": match["folder"], "steps": int(match["steps"]),
            "batch": int(match["batch"])}


def run_flops(run: dict[str, Any]) -> dict[str, Any]:
    """Positions per window, non-embedding parameters and total training FLOPs of one run."""
    net = load_nets(run["folder"], "world_model")[0]["net"]
    windows = run["steps"] * run["batch"]
    return {**run, "positions": net.frames * net.step_len, "windows": windows,
            "non_embedding_parameters": non_embedding_parameters(net, WorldModel.block_types),
            "flops": model_flops_per_step(net, 1) * windows}


def table(rows: list[dict[str, Any]]) -> str:
    base = rows[0]["flops"]
    lines = ["| run | positions per window | N (non-embedding) | windows | training FLOPs | × first |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r['name']} | {r['positions']} | {r['non_embedding_parameters'] / 1e6:.2f}M | {r['windows']} | "
              f"{r['flops']:.3g} | {r['flops'] / base:.1f} |" for r in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", type=parse_run, action="append", required=True, help="NAME=FOLDER:STEPSxBATCH")
    p.add_argument("--json", type=Path, default=None, help="also write the rows as JSON here")
    args = p.parse_args(argv)
    rows = [run_flops(run) for run in args.run]
    print(table(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return rows


if __name__ == "__main__":
    main()
