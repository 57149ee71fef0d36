"""`make reproduce`: the GAIA-1 reference recipe from scratch, ending in the shipped weights (docs/reference.md).

    python -m gaia_app.tasks.reproduce [--out outputs/reference] [--weights gaia_app/weights/gaia1] [--dry-run]
                                       [--until STEP] [--gpu]

Steps, each a train.py / generate.py command that resumes or skips finished work when run again:
  tokenizer        train.py experiment=gaia1/reference/tokenizer
  tokenize         generate.py mode=tokenize: 1024 synthetic clips of 3.2 s, half of them leaving their policy for
                   a random open-loop command, tokenized at 6.25 Hz (+ 128 clips of the held-out val world)
  world_model      train.py experiment=gaia1/reference/world_model
  tokenize_finetune  generate.py mode=tokenize: 1024 more clips (world seed 5), every one leaving its policy for an
                   open-loop command, a tenth of them at night (+ 128 held-out clips of that mix)
  world_model_finetune  train.py experiment=gaia1/reference/world_model_finetune from the world_model step's weights
  --gpu only (`make reproduce GPU=1`; version 5 of the shipped weights came from it, on one H200):
  tokenize_gpu     generate.py mode=tokenize on the GPU: the fine-tune's 1024 clips (world seed 5) again, into a cache
  tokenize_gpu_more  and 2366 clips of world seed 6 beside them
  world_model_gpu  train.py experiment=gaia1/reference/world_model_finetune_gpu from the world_model_finetune
                   step's weights
  tokenize_less_snow  generate.py mode=tokenize (CPU): 1024 driven clips of world seed 8 with snow in 8 % of them
  world_model_less_snow  train.py experiment=gaia1/reference/world_model_less_snow from the world_model_gpu step's
                   weights (version 6 came from it); the steps below then score and export this world model
  cross_entropy    validation cross-entropy per conditioning mode vs the copy-previous-frame and unigram baselines
  probes           benchmarks/probe_quality.py: controllability probes for the recipe's size and protocol, and
                   their model-free check (ceiling vs reference, scene accuracy on real frames)
  controllability  generate.py mode=controllability with those probes: 32 held-out contexts × 4 commands, prompts
  video_decoder    train.py experiment=gaia1/reference/video_decoder on the tokens of the step-1 tokenizer
  export           generate.py mode=export into the weights folder (float16 safetensors + YAML + probes), the video
                   decoder with its measured decoding setting (the conditional mean over 16 draws)
Then MANIFEST.md beside the weights folder (gaia_app/weights/MANIFEST.md) records, per step, the exact command, its
wall time, the commit and the machine, with the cross-entropy and controllability tables.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

from gaia_app.utils.run_dir import atomic_write_text

ROOT = Path(__file__).resolve().parents[2]
# the recipe's protocol: 4 context frames and 8 generated ones (1.25 s) fill the world model's 12-step window; the
# probes are trained (and checked without any model) for exactly that protocol. Classifier-free guidance (GAIA-1
# §5.1: a hyper-parameter to tune per use) at scale 1.5 for action-steered rollouts and 3 for text-prompted ones:
# picked among 1.5, 3 and 6 on the validation world (context.seed=2000, docs/reference.md), never on the evaluation
# world 1000 that the table reports
PROTOCOL = ["context.frames=4", "seconds=1.25", "guidance.scale=1.5", "guidance.text_scale=3"]
# how the shipped video decoder decodes by default (docs/video_decoder.md: the one setting that beats frame-by-frame
# decoding at the recipe's budget)
DECODING = ["decoder_sampler=one_step_mean", "decoder_steps=16"]
PROBES = ["--context-frames=4", "--seconds=1.25", "--probe-clips=768", "--probe-steps=4000"]
# clips simulated and rendered at the world model's 6.25 Hz directly: a quarter of the rendering of 25 Hz clips.
# Open-loop accelerations drawn symmetric in [-5, 5] m/s² (the default [-4.5, 2.5] makes speeding up rarer and
# weaker than braking, and the v2 weights read "accelerate" as slower than "keep", docs/reference.md)
TOKENS = ["data=synthetic", "data.source.num_clips=1024", "data.val_source.num_clips=128", "data.source.fps=6.25",
          "data.source.clip_len=20", "data.source.driven_share=0.5", "data.source.open_loop_acceleration=[-5,5]",
          "fps=6.25"]
# the fine-tune's clips (conf/experiment/gaia1/reference/world_model_finetune.yaml says why): every clip driven, a
# tenth at night, another world seed
FINETUNE_TOKENS = [*(t for t in TOKENS if not t.startswith("data.source.driven_share")), "data.source.driven_share=1.0",
                   "data.source.time_of_day_mix={day:0.7,dusk:0.2,night:0.1}", "seed=5"]
# the GPU fine-tune's cache (conf/experiment/gaia1/reference/world_model_finetune_gpu.yaml): those clips again and 2366
# of world seed 6, train split only (its held-out windows come from the cache itself)
GPU_TOKENS = [*(t for t in FINETUNE_TOKENS if not t.startswith("data.val_source")), "device=cuda", "workers=14",
              "splits=[train]"]
# the last fine-tune's clips (conf/experiment/gaia1/reference/world_model_less_snow.yaml): half the default share of
# snow, so that unprompted rollouts draw snow about as rarely as the floor asks; rendered on the CPU
LESS_SNOW_TOKENS = [*(t for t in FINETUNE_TOKENS if not t.startswith(("data.val_source", "seed="))), "seed=8",
                    "data.source.weather_mix={clear:0.62,rain:0.15,fog:0.15,snow:0.08}", "splits=[train]"]


def steps(out: Path, weights: Path, gpu: bool = False) -> list[tuple[str, list[str]]]:
    """(name, argv) of every step, in order; `gpu` adds the GPU fine-tune, whose world model the later steps use."""
    tokenizer, pretrained = out / "tokenizer/checkpoints/last.ckpt", out / "world_model/checkpoints/last.ckpt"
    finetuned = out / "world_model_finetune/checkpoints/last.ckpt"
    world_model = out / "world_model_less_snow/checkpoints/last.ckpt" if gpu else finetuned
    ckpts = [f"tokenizer_ckpt={tokenizer}", f"world_model_ckpt={world_model}"]
    decoder = out / "video_decoder/checkpoints/last.ckpt"
    probes = out / "probes/probes"
    py = sys.executable
    return [
        ("tokenizer", [py, "train.py", "experiment=gaia1/reference/tokenizer", f"hydra.run.dir={out / 'tokenizer'}",
                       "ckpt_path=last"]),
        ("tokenize", [py, "generate.py", "mode=tokenize", f"ckpt={tokenizer}", *TOKENS, f"out_dir={out / 'tokens'}",
                      f"hydra.run.dir={out / 'tokenize'}"]),
        ("world_model", [py, "train.py", "experiment=gaia1/reference/world_model", f"data.path={out / 'tokens/train'}",
                         f"hydra.run.dir={out / 'world_model'}", "ckpt_path=last"]),
        ("tokenize_finetune", [py, "generate.py", "mode=tokenize", f"ckpt={tokenizer}", *FINETUNE_TOKENS,
                               f"out_dir={out / 'tokens_finetune'}", f"hydra.run.dir={out / 'tokenize_finetune'}"]),
        ("world_model_finetune", [py, "train.py", "experiment=gaia1/reference/world_model_finetune",
                                  f"data.path={out / 'tokens_finetune/train'}", f"model.init_from={pretrained}",
                                  f"hydra.run.dir={out / 'world_model_finetune'}", "ckpt_path=last"]),
        *(gpu_steps(out, tokenizer, finetuned) if gpu else []),
        ("cross_entropy", [py, "-m", "gaia_app.protocols.world_model_report", f"--ckpt={world_model}",
                           f"--tokens={out / 'tokens_finetune'}", f"--out={out / 'cross_entropy'}"]),
        ("probes", [py, "benchmarks/probe_quality.py", f"--out={out / 'probes'}", *PROBES]),
        ("controllability", [py, "generate.py", "mode=controllability", *ckpts, *PROTOCOL,
                             f"controllability.probes={probes}", f"hydra.run.dir={out / 'controllability'}"]),
        ("video_decoder", [py, "train.py", "experiment=gaia1/reference/video_decoder",
                           f"model.tokenizer_ckpt={tokenizer}", f"hydra.run.dir={out / 'video_decoder'}",
                           "ckpt_path=last"]),
        ("export", [py, "generate.py", "mode=export", *ckpts, f"decoder_ckpt={decoder}", *DECODING,
                    f"controllability.probes={probes}",
                    f"out_dir={weights}", f"hydra.run.dir={out / 'export'}"]),
    ]


def gpu_steps(out: Path, tokenizer: Path, finetuned: Path) -> list[tuple[str, list[str]]]:
    """The optional GPU fine-tune (its token cache of two worlds in one folder, then the training run) and the CPU
    fine-tune on less snow that follows it."""
    py, cache, less_snow = sys.executable, out / "tokens_gpu", out / "tokens_less_snow"
    tokenize = [py, "generate.py", "mode=tokenize", f"ckpt={tokenizer}", *GPU_TOKENS, f"out_dir={cache}"]
    more = [*(t for t in tokenize if not t.startswith(("seed=", "data.source.num_clips="))), "seed=6",
            "data.source.num_clips=2366"]
    return [("tokenize_gpu", [*tokenize, f"hydra.run.dir={out / 'tokenize_gpu'}"]),
            ("tokenize_gpu_more", [*more, f"hydra.run.dir={out / 'tokenize_gpu_more'}"]),
            ("world_model_gpu", [py, "train.py", "experiment=gaia1/reference/world_model_finetune_gpu",
                                 f"data.path={cache / 'train'}", f"model.init_from={finetuned}",
                                 f"hydra.run.dir={out / 'world_model_gpu'}", "ckpt_path=last"]),
            ("tokenize_less_snow", [py, "generate.py", "mode=tokenize", f"ckpt={tokenizer}", *LESS_SNOW_TOKENS,
                                    f"out_dir={less_snow}", f"hydra.run.dir={out / 'tokenize_less_snow'}"]),
            ("world_model_less_snow", [py, "train.py", "experiment=gaia1/reference/world_model_less_snow",
                                       f"data.path={less_snow / 'train'}",
                                       f"model.init_from={out / 'world_model_gpu/checkpoints/last.ckpt'}",
                                       f"hydra.run.dir={out / 'world_model_less_snow'}", "ckpt_path=last"])]


def commit() -> str:
    """HEAD of the working tree, marked `-dirty` when it has uncommitted changes."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    head = git("rev-parse", "--short", "HEAD") or "unknown"
    # the weights the export step has just written are its output, not an uncommitted change to the recipe
    changed = git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)gaia_app/weights")
    return head + ("-dirty" if changed else "")


def machine() -> str:
    return f"{platform.system()} {platform.machine()}, {os.cpu_count()} CPU cores, Python {platform.python_version()}"


def shown(argv: list[str]) -> str:
    """The command as a user would type it (python, not the interpreter's path), quoted for a POSIX shell (braces
    and brackets of Hydra overrides would otherwise expand)."""
    return " ".join(["python", *map(shlex.quote, argv[1:])])


def manifest(records: list[dict], out: Path, weights: Path) -> str:
    """MANIFEST.md: the files, how each step made them, and the recipe's measured tables."""
    lines = ["# Shipped weights: GAIA-1 reference recipe", "",
             "Made by `make reproduce` (`python -m gaia_app.tasks.reproduce`), which ran these steps in order; "
             "docs/reference.md explains the recipe.", "",
             f"- machine: {records[0]['machine']}", "",
             "| file | bytes |", "|---|---|"]
    for path in sorted(p for p in weights.rglob("*") if p.is_file()):
        lines.append(f"| {path.relative_to(weights.parent)} | {path.stat().st_size} |")
    lines += ["", "| step | wall time | commit | command |", "|---|---|---|---|"]
    for r in records:
        note = f" ({r['note']})" if r.get("note") else ""
        lines.append(f"| {r['step']} | {r['wall_s'] / 60:.1f} min{note} | {r['commit']} | `{r['command']}` |")
    lines.append(f"| total | {sum(r['wall_s'] for r in records) / 60:.1f} min | | |")
    for name, title in (("cross_entropy/cross_entropy.md", "Held-out cross-entropy"),
                        ("controllability/controllability.md", "Controllability")):
        table = out / name
        if table.is_file():
            lines += ["", f"## {title}", "", table.read_text().strip()]
    return "\n".join(lines) + "\n"


def run_step(name: str, command: list[str]) -> dict:
    """Run one step's command from the project root; its record (command, wall time, commit, machine)."""
    print(f"== {name}: {shown(command)}", flush=True)
    start = time.perf_counter()
    subprocess.run(command, cwd=ROOT, check=True)
    return {"step": name, "command": shown(command), "wall_s": time.perf_counter() - start, "commit": commit(),
            "machine": machine()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("outputs/reference"))
    parser.add_argument("--weights", type=Path, default=Path("gaia_app/weights/gaia1"))
    parser.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    parser.add_argument("--until", choices=[name for name, _ in steps(Path("."), Path("."), gpu=True)],
                        help="stop after this step (no MANIFEST.md); run again without it to go on")
    parser.add_argument("--gpu", action="store_true", help="add the GPU fine-tune (needs CUDA) and export its model")
    args = parser.parse_args(argv)
    records_path = args.out / "reproduce.json"
    done = {r["step"]: r for r in json.loads(records_path.read_text())} if records_path.is_file() else {}
    recipe = steps(args.out, args.weights, args.gpu)
    in_order = lambda: [done[name] for name, _ in recipe if name in done]  # noqa: E731
    for name, command in recipe:
        if args.dry_run:
            print(shown(command))
        elif name not in done:  # a step finished in an earlier invocation keeps its record
            done[name] = run_step(name, command)
            atomic_write_text(records_path, json.dumps(in_order(), indent=2))
        if name == args.until:
            print(f"stopped after {name} (--until); run again without it to go on")
            return
    if not args.dry_run:
        atomic_write_text(args.weights.parent / "MANIFEST.md", manifest(in_order(), args.out, args.weights))
        print(f"weights in {args.weights}, MANIFEST.md beside them")


if __name__ == "__main__":
    main()
