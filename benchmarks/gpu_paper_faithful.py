r"""Issue 50 on one GPU: the paper-faithful study's smaller budgets on the D = 4 tokens, trained and scored in one run.

    python benchmarks/gpu_paper_faithful.py --out $OUT/pf --tokenizer gaia_app/weights/gaia1_road_users \
        --minilm .gpu/minilm.tar.xz --score paper_full=.gpu/paper_d4.ckpt \
        --score shortcuts_full=.gpu/world_model_d4.ckpt
    python benchmarks/gpu_paper_faithful.py --out /tmp/pf --tokenizer <…> --minilm <…> --dry-run   # tiny, on a CPU

The sixth lease trained both arms of the study for about 7 000 steps of 16 windows (44× the CPU budget's FLOPs,
docs/paper_faithful.md); a curve needs the same arms at smaller budgets on the same cache, and scoring a 448-token
world model on the CPU takes about an hour per arm. Stages (benchmarks/gpu_road_users.py's machinery):
  tokenize   the reference recipe's clips with the D = 4 tokenizer on CUDA (as gpu_road_users.py)
  ladder     both arms (experiment=gaia1/paper_faithful/world_model_d4_gpu and gaia1/road_users/world_model_d4_gpu)
             at each --fractions of FULL_STEPS, all side by side, each with its cosine over its own steps
  export     a weights folder per trained arm and per --score checkpoint (the D = 4 tokenizer, the shipped probes)
  score      generate.py mode=controllability on CUDA for every folder side by side: world 5050, the protocol of
             the study's tables (32 contexts, 4 context frames, 1.25 s, guidance 1.5, text guidance 3)
Brought back under --out (at most 8 files): paper_faithful.json (every stage's status, seconds, command) and
ladder.tar (the weight-only float16 checkpoints, each arm's controllability.json / .md and the logs' tails),
rewritten after every stage, so a run stopped at its limit still returns what it finished. The lease machine needs
what gpu_road_users.py needs (wheels, benchmarks/gpu_stubs, the MiniLM archive; docs/benchmarks.md, "Sixth lease").
"""

from __future__ import annotations

import argparse
import datetime
import sys
import tarfile
import time
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.gpu_road_users import (  # noqa: E402
    Report,
    paper_arm,
    run_side_by_side,
    run_stage,
    slim_checkpoint,
    tokenize_commands,
    tokenizer_setting,
    world_model_command,
)
from gaia_app.utils.run_dir import atomic_path  # noqa: E402

FULL_STEPS = 7000  # the sixth lease's arms: 7 083 (shortcuts) and 6 583 (paper) steps of 16 windows
ARMS = {"paper": "gaia1/paper_faithful/world_model_d4_gpu", "shortcuts": "gaia1/road_users/world_model_d4_gpu"}
# the study's controllability protocol (docs/paper_faithful.md), world 5050 scored once per arm
PROTOCOL = ["mode=controllability", "context.frames=4", "seconds=1.25", "guidance.scale=1.5", "guidance.text_scale=3",
            "controllability.contexts=32", "context.seed=5050"]
DRY_PROTOCOL = ["controllability.contexts=2", "seconds=0.32", "controllability.text_repeats=1",
                "controllability.floor_repeats=2", "controllability.real_clips=2"]
BUDGETS = {"tokenize": 170, "export": 60}
PROBES = ROOT / "gaia_app/weights/gaia1/probes"


def ladder_arms(cache: Path, work: Path, seconds: float, dry: bool, minilm: Path | None,
                fractions: list[float]) -> dict[str, list[str]]:
    """{run name: train.py command}: each arm at each fraction of FULL_STEPS, its schedule over its own steps (the
    paper arm only with a MiniLM directory)."""
    arms = {}
    for fraction in fractions:
        steps = max(round(fraction * FULL_STEPS), 1)
        for arm, experiment in ARMS.items():
            if arm == "paper" and minilm is None:
                continue
            extra = [] if dry else [f"trainer.max_steps={steps}", f"model.sched.decay_steps={steps}",
                                    f"trainer.val_check_interval={steps}"]
            if arm == "paper":
                extra.append(f"model.text_encoder.path={minilm}")
            name = f"{arm}_{steps}"
            arms[name] = world_model_command(experiment, cache, work / name, seconds, dry, tuple(extra))
    return arms


def export_command(tokenizer: Path, checkpoint: Path, folder: Path) -> list[str]:
    return ["generate.py", "mode=export", tokenizer_setting(tokenizer, "tokenizer_ckpt"),
            f"world_model_ckpt={checkpoint}", f"controllability.probes={PROBES}", f"out_dir={folder}",
            f"hydra.run.dir={folder}_export"]


def score_command(folder: Path, run: Path, dry: bool) -> list[str]:
    protocol = PROTOCOL
    if dry:  # each setting once: the dry run's replace the protocol's
        keys = {setting.split("=")[0] for setting in DRY_PROTOCOL}
        protocol = [s for s in PROTOCOL if s.split("=")[0] not in keys] + DRY_PROTOCOL
    return ["generate.py", *protocol, f"weights={folder}", "device=cpu" if dry else "device=cuda",
            f"hydra.run.dir={run}"]


def pack(out: Path, back: Path, work: Path, names: list[str]) -> None:
    """DIR/ladder.tar: the slim checkpoints and log tails gathered in `back` so far, and the controllability tables."""
    files = [back / name for n in names for name in (f"{n}.ckpt", f"{n}.log", f"score_{n}.log")]
    files += [work / f"score_{n}" / f"controllability.{kind}" for n in names for kind in ("json", "md")]
    files += [back / f"{stage}.log" for stage in ("tokenize", "export")]
    with atomic_path(out / "ladder.tar") as tmp, tarfile.open(tmp, "w") as archive:
        for file in files:
            if file.is_file():
                archive.add(file, arcname=file.name if file.parent == back else f"{file.parent.name}_{file.name}")


def parse_score(text: str) -> tuple[str, Path]:
    name, _, path = text.partition("=")
    if not name or not path:
        raise argparse.ArgumentTypeError(f"--score {text!r}: expected NAME=<world-model checkpoint>")
    return name, Path(path)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="what comes back: paper_faithful.json and ladder.tar")
    p.add_argument("--tokenizer", type=Path, required=True,
                   help="the D = 4 tokenizer: a checkpoint or a weights folder (gaia_app/weights/gaia1_road_users)")
    p.add_argument("--minilm", type=Path, default=None, help="pack_minilm.py's archive (without: no paper arm)")
    p.add_argument("--score", type=parse_score, action="append", default=[],
                   help="NAME=<world-model checkpoint> trained earlier, scored beside the new ones")
    # 1/32 and 1/4 of the sixth lease's steps: with it, three budgets spanning 32× (issue 50 asks ≥ 30×)
    p.add_argument("--fractions", type=float, nargs="+", default=[1 / 32, 1 / 4], help="of FULL_STEPS")
    p.add_argument("--work", type=Path, default=Path("/tmp/paper_faithful"), help="runs and caches (not brought back)")
    p.add_argument("--budget-s", type=float, default=540.0, help="wall-clock seconds for every stage together")
    p.add_argument("--dry-run", action="store_true", help="tiny sizes on a CPU: a few steps, clips and contexts")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    if not args.dry_run and not torch.cuda.is_available():
        raise SystemExit("gpu_paper_faithful.py needs CUDA (or --dry-run for tiny sizes on a CPU)")
    start = time.monotonic()

    def left() -> float:
        """Seconds of --budget-s not yet spent."""
        return args.budget_s - (time.monotonic() - start)

    report = Report(args.out, {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                               "torch": torch.__version__, "dry_run": args.dry_run}, "paper_faithful.json")
    cache, back = args.work / "tokens_d4", args.work / "back"  # back: what ladder.tar gathers (≤ 8 files return)
    back.mkdir(parents=True, exist_ok=True)
    if not run_stage(report, back, "tokenize", tokenize_commands(args.tokenizer, cache, args.dry_run),
                     BUDGETS["tokenize"]):
        return report.data
    minilm = paper_arm(report, args.minilm, args.work, cache)
    # training gets half of what is left, scoring the rest
    arms = ladder_arms(cache, args.work, left() / 2, args.dry_run, minilm, args.fractions)
    run_side_by_side(report, back, arms, max(left() / 2, 60))
    checkpoints = {name: args.work / name / "checkpoints/last.ckpt" for name in arms}
    checkpoints.update(dict(args.score))
    names = [name for name, path in checkpoints.items() if path.is_file()]
    for name in names:
        report.save(f"{name}_checkpoint", slim_checkpoint(checkpoints[name], back / f"{name}.ckpt"))
    pack(args.out, back, args.work, names)
    folders = {name: args.work / f"weights_{name}" for name in names}
    if run_stage(report, back, "export", [export_command(args.tokenizer, checkpoints[n], folders[n]) for n in names],
                 BUDGETS["export"]):
        scores = {f"score_{n}": score_command(folders[n], args.work / f"score_{n}", args.dry_run) for n in names}
        run_side_by_side(report, back, scores, max(left() - 15, 60))
    pack(args.out, back, args.work, names)
    return report.data


if __name__ == "__main__":
    main()
