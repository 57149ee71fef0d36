r"""Evaluate GAIA-1 and GAIA-2 checkpoints against held-out synthetic data and print one table.

    python benchmarks/evaluate_models.py --out outputs/evaluation \
        --gaia1 tokenizer_ckpt=G1TOK world_model_ckpt=G1WM [decoder_ckpt=G1DEC] \
        --gaia2 tokenizer_ckpt=G2TOK world_model_ckpt=G2WM \
        [--both evaluate.metrics=[psnr,ssim,fvmd,agent_iou]]

Runs `generate.py mode=evaluate` (GAIA-1: front camera, 6.25 Hz) and `generate.py model=gaia2 mode=evaluate
data=synthetic_rig` (GAIA-2: 3 cameras, 12.5 Hz) into <out>/gaia1 and <out>/gaia2, each on clips of the synthetic
world `context.seed` that neither model trained on, then prints their fidelity rows (model, tokenized ceiling,
held-frame floor) as one table with the metrics both computed (the same code scores both). Overrides after
--gaia1 / --gaia2 go to that run only, after --both to both. The GAIA-2 run also writes its agent-control and
action-adherence tables (<out>/gaia2/gaia2_evaluation.md).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from gaia_app.eval.report import combined_table

ROOT = Path(__file__).resolve().parents[1]


def run(out: Path, overrides: list[str]) -> None:
    command = [sys.executable, str(ROOT / "generate.py"), "mode=evaluate", f"hydra.run.dir={out}",
               "extras.print_config=false", *overrides]
    subprocess.run(command, check=True, cwd=ROOT)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--gaia1", nargs="+", required=True, metavar="OVERRIDE")
    parser.add_argument("--gaia2", nargs="+", required=True, metavar="OVERRIDE")
    parser.add_argument("--both", nargs="*", default=[], metavar="OVERRIDE")
    args = parser.parse_args()
    runs = {"GAIA-1": args.out / "gaia1", "GAIA-2": args.out / "gaia2"}
    run(runs["GAIA-1"], [*args.both, *args.gaia1])
    rig = [] if any(o.startswith("data=") for o in args.gaia2) else ["data=synthetic_rig"]
    run(runs["GAIA-2"], ["model=gaia2", *rig, *args.both, *args.gaia2])
    text = combined_table(runs)
    (args.out / "evaluation.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
