r"""Issue 49 on one GPU: the GAIA-1 world model on the D = 4 tokenizer's 448 tokens per frame, in one run of ≤ 9 min.

    python benchmarks/gpu_road_users.py --out $OUT/ru --tokenizer gaia_app/weights/gaia1_road_users
    python benchmarks/gpu_road_users.py --out $OUT/ru          # also trains the tokenizer (≈ 5 more minutes)
    python benchmarks/gpu_road_users.py --out $OUT/ru --tokenizer <…> --minilm .gpu/minilm.tar.xz   # + the paper arm
    python benchmarks/gpu_road_users.py --out /tmp/ru --dry-run   # tiny sizes on a CPU: checks that every stage runs

The D = 4 tokenizer keeps road users (agent_iou_ratio 0.835 against the shipped 0.444, docs/tokenizer.md), but a world
model on its 448 tokens per frame costs 8.5× per training step (docs/benchmarks.md, "Tokens per frame"): hours on a
2-core CPU. This script trains that world model on one GPU. Stages, each a train.py / generate.py subprocess with its
own wall-clock budget (a stage past it is stopped; a training stage also stops itself through +trainer.max_time and
keeps its last checkpoint):
  tokenizer       only without --tokenizer: the study's two runs, experiment=gaia1/reference/tokenizer_agents_d4
                  (1 500 steps) then tokenizer_agents_d4_long (2 500 more), 14 workers rendering frames
  tokenize        generate.py mode=tokenize on CUDA with 14 render workers: the reference recipe's clips (1 024, half
                  of them leaving their policy for an open-loop command, + 128 held out) and the fine-tune's 1 024
                  driven clips of world seed 5 (a tenth at night), into one cache
  world_model     experiment=gaia1/road_users/world_model_d4_gpu on that cache, stopped by its time budget; with
                  --minilm, the paper-faithful study's paper arm (issue 50) trains beside it on the same GPU and cache,
                  experiment=gaia1/paper_faithful/world_model_d4_gpu (stage paper_d4), the same wall clock for both.
                  --minilm is benchmarks/pack_minilm.py's archive (the GPU machine has no MiniLM package) or a MiniLM
                  directory; the paper arm is left out, with the reason, when the new cache's captions use word
                  pieces the archive does not keep.
Brought back under --out (at most 8 files): weight-only float16 copies of the tokenizer and world-model checkpoints
(`tokenizer_d4.ckpt`, `world_model_d4.ckpt`, `paper_d4.ckpt`: what tokenizer_ckpt= / world_model_ckpt= /
model.init_from= read; the paper arm's text encoder reads the MiniLM package again), each stage's log tail, and
road_users.json (every stage's status, seconds, steps and command), rewritten after each stage.
On the lease machine (no hydra-core, omegaconf, antlr4, gymnasium, rerun-sdk, PyAV or MiniLM package): the first four
travel as wheels in an ignored .whl/ folder, the last three as benchmarks/gpu_stubs and --minilm, the tokenizer as a
carried copy (docs/benchmarks.md, "Sixth lease", has the whole call).
Then on the CPU: `generate.py mode=export` into a weights folder and `benchmarks/agent_futures.py --weights <folder>`
(docs/evaluation.md, "Futures with moving agents").
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
import tarfile
import time
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.pack_minilm import KEPT, covers  # noqa: E402
from gaia_app.utils.run_dir import atomic_path, atomic_write_text  # noqa: E402
from gaia_app.weights.checkpoints import read_checkpoint  # noqa: E402
from gaia_app.weights.nets import NETS_RECORD  # noqa: E402

# seconds per stage; the world model gets what is left of --budget-s after the stages before it
BUDGETS = {"tokenizer": 320, "tokenize": 170}
# the clips of the reference recipe (gaia_app/tasks/reproduce.py TOKENS and FINETUNE_TOKENS), rendered at 6.25 Hz
CLIPS = ["data=synthetic", "data.source.fps=6.25", "data.source.clip_len=20",
         "data.source.open_loop_acceleration=[-5,5]", "fps=6.25"]
POLICY_MIX = ["data.source.num_clips=1024", "data.val_source.num_clips=128", "data.source.driven_share=0.5"]
DRIVEN_MIX = ["data.source.num_clips=1024", "data.source.driven_share=1.0",
              "data.source.time_of_day_mix={day:0.7,dusk:0.2,night:0.1}", "seed=5", "splits=[train]"]
# what --dry-run shrinks (tiny sizes, a few steps, no CUDA)
DRY = {"steps": ["trainer.max_steps=2", "trainer.val_check_interval=2", "trainer.limit_val_batches=1",
                 "data.num_workers=0"],
       "clips": ["data.source.num_clips=2", "data.val_source.num_clips=1"]}
STAGE_MARGIN_S = 45  # start-up and checkpoint writing after +trainer.max_time stops the loop


class Report:
    """Stages so far, rewritten to DIR/<name> (road_users.json) after each."""

    def __init__(self, out: Path, meta: dict[str, Any], name: str = "road_users.json"):
        self.path, self.data = out / name, {"meta": meta, "stages": {}}
        out.mkdir(parents=True, exist_ok=True)

    def save(self, name: str, result: dict[str, Any]) -> None:
        self.data["stages"][name] = result
        atomic_write_text(self.path, json.dumps(self.data, indent=2, default=str))


def max_time(seconds: float) -> str:
    """Lightning's DD:HH:MM:SS for a training stage that must stop `STAGE_MARGIN_S` inside its budget."""
    left = max(int(seconds - STAGE_MARGIN_S), 30)
    return f"+trainer.max_time=00:{left // 3600:02d}:{left % 3600 // 60:02d}:{left % 60:02d}"


def run_stage(report: Report, out: Path, name: str, commands: list[list[str]], budget: float) -> bool:
    """Run a stage's commands in turn within `budget` seconds of wall clock; their log's tail goes to DIR/<name>.log."""
    start, log, status = time.monotonic(), out / f"{name}.log", "ok"
    with open(log, "w") as sink:
        for argv in commands:
            left = budget - (time.monotonic() - start)
            try:
                done = subprocess.run([sys.executable, *argv], cwd=ROOT, stdout=sink, stderr=subprocess.STDOUT,
                                      timeout=max(left, 1))
            except subprocess.TimeoutExpired:
                status = "timeout"
                break
            if done.returncode:
                status = f"exit {done.returncode}"
                break
    return finish_stage(report, log, name, status, start, budget, commands)


def finish_stage(report: Report, log: Path, name: str, status: str, start: float, budget: float,
                 commands: list[list[str]]) -> bool:
    """Keep the log's tail and record the stage (status, seconds, budget, commands); True when it ran through."""
    keep_tail(log)
    report.save(name, {"status": status, "seconds": round(time.monotonic() - start, 1), "budget_s": round(budget),
                       "commands": [" ".join(["python", *argv]) for argv in commands]})
    return status == "ok"


def keep_tail(log: Path, chars: int = 20_000) -> None:
    """Progress bars make long logs: keep the last `chars` characters, one line per carriage return."""
    text = log.read_text(errors="replace").replace("\r", "\n")
    log.write_text(text[-chars:])


def slim_checkpoint(source: Path, target: Path) -> dict[str, Any]:
    """A weight-only float16 copy of a training checkpoint (state_dict, hyper-parameters, the nets' record, the step):
    what inference and model.init_from read, small enough to bring back from the GPU machine."""
    checkpoint = read_checkpoint(source)
    state = {k: v.half() if v.is_floating_point() else v for k, v in checkpoint["state_dict"].items()}
    slim = {"state_dict": state, **{k: checkpoint[k] for k in ("hyper_parameters", NETS_RECORD, "global_step", "epoch")
                                    if k in checkpoint}}
    portable_text_encoder(slim)
    with atomic_path(target) as tmp:
        torch.save(slim, tmp)
    return {"file": target.name, "megabytes": round(target.stat().st_size / 2**20, 2),
            "global_step": checkpoint.get("global_step")}


def tokenizer_commands(work: Path, dry: bool) -> list[list[str]]:
    """The two tokenizer runs of the study (docs/tokenizer.md), the second starting from the first: one stage, one
    log."""
    first, second = work / "tokenizer_d4", work / "tokenizer_d4_long"
    common = ["trainer=cpu" if dry else "trainer=gpu", "trainer.precision=32-true",
              *(DRY["steps"] if dry else ["data.num_workers=14"]), "logger=csv"]
    return [["train.py", "experiment=gaia1/reference/tokenizer_agents_d4", *common, f"hydra.run.dir={first}"],
            ["train.py", "experiment=gaia1/reference/tokenizer_agents_d4_long", *common,
             f"model.init_from={first / 'checkpoints/last.ckpt'}", f"hydra.run.dir={second}"]]


def tokenizer_setting(tokenizer: Path, checkpoint_key: str = "ckpt") -> str:
    """How generate.py reads the tokenizer: a weights folder (e.g. gaia_app/weights/gaia1_road_users, written by
    `mode=export export_parts=tokenizer`) as weights=, a training checkpoint as `checkpoint_key`=."""
    return f"weights={tokenizer}" if tokenizer.is_dir() else f"{checkpoint_key}={tokenizer}"


def tokenize_commands(tokenizer: Path, cache: Path, dry: bool) -> list[list[str]]:
    """Both clip mixes into one cache (segments are named by clip, so the mixes sit side by side)."""
    device = ["device=cpu", "workers=0"] if dry else ["device=cuda", "workers=14"]
    commands = []
    for i, mix in enumerate((POLICY_MIX, DRIVEN_MIX)):
        if dry:
            mix = [*(t for t in mix if not t.startswith(("data.source.num_clips", "data.val_source"))), *DRY["clips"]]
        commands.append(["generate.py", "mode=tokenize", tokenizer_setting(tokenizer), *CLIPS, *mix, *device,
                         f"out_dir={cache}", f"hydra.run.dir={cache}_run{i}"])
    return commands


def world_model_command(experiment: str, cache: Path, run: Path, seconds: float, dry: bool,
                        extra: tuple[str, ...] = ()) -> list[str]:
    steps = ["trainer=cpu", *DRY["steps"], "data.batch_size=1"] if dry else [max_time(seconds)]
    return ["train.py", f"experiment={experiment}", f"data.path={cache / 'train'}", *steps, *extra, "logger=csv",
            f"hydra.run.dir={run}"]


def run_side_by_side(report: Report, out: Path, arms: dict[str, list[str]], budget: float) -> dict[str, bool]:
    """Start every arm's command at once (one GPU, its own log DIR/<arm>.log) and wait for all within `budget` s."""
    start, running = time.monotonic(), {}
    for name, argv in arms.items():
        sink = open(out / f"{name}.log", "w")
        running[name] = (subprocess.Popen([sys.executable, *argv], cwd=ROOT, stdout=sink, stderr=subprocess.STDOUT),
                         sink)
    done = {}
    for name, (process, sink) in running.items():
        try:
            code = process.wait(timeout=max(budget - (time.monotonic() - start), 1))
            status = "ok" if code == 0 else f"exit {code}"
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
            status = "timeout"
        sink.close()
        done[name] = finish_stage(report, out / f"{name}.log", name, status, start, budget, [arms[name]])
    return done


def unpack_minilm(source: Path, work: Path) -> Path:
    """A MiniLM directory from pack_minilm.py's archive (unpacked under `work`), or `source` itself if a directory."""
    if source.is_dir():
        return source
    target = work / "minilm"
    target.mkdir(parents=True, exist_ok=True)
    with tarfile.open(source) as archive:
        archive.extractall(target, filter="data")
    return target


def paper_arm(report: Report, minilm: Path | None, work: Path, cache: Path) -> Path | None:
    """The MiniLM directory the paper arm reads, or None (no --minilm, or the cache's captions are not covered: the
    reason goes into the report)."""
    if minilm is None:
        return None
    directory = unpack_minilm(minilm, work)
    covered, outside = covers(directory, cache) if (directory / KEPT).is_file() else (True, [])
    if not covered:
        report.save("paper_d4", {"status": "left out: captions use word pieces the MiniLM archive zeroed",
                                 "captions": outside})
        return None
    return directory


def world_model_arms(cache: Path, work: Path, seconds: float, dry: bool, minilm: Path | None) -> dict[str, list[str]]:
    """{stage: command}: the road-users world model, and the paper arm beside it when `minilm` is a directory."""
    arms = {"world_model": world_model_command("gaia1/road_users/world_model_d4_gpu", cache, work / "world_model_d4",
                                               seconds, dry)}
    if minilm is not None:
        arms["paper_d4"] = world_model_command("gaia1/paper_faithful/world_model_d4_gpu", cache, work / "paper_d4",
                                               seconds, dry, (f"model.text_encoder.path={minilm}",))
    return arms


def portable_text_encoder(checkpoint: dict[str, Any]) -> None:
    """Point a checkpoint's pretrained text encoder back at its package copy: the GPU machine's unpacked directory
    exists nowhere else, and the package holds the same network in float32."""
    encoder = ((checkpoint.get("hyper_parameters") or {}).get("model_cfg") or {}).get("text_encoder")
    if isinstance(encoder, dict) and encoder.get("path") is not None:
        encoder["path"] = None


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="what comes back: checkpoints, logs, road_users.json")
    p.add_argument("--tokenizer", type=Path, default=None,
                   help="a trained D = 4 tokenizer: a checkpoint or a weights folder (the shipped "
                        "gaia_app/weights/gaia1_road_users); else the two tokenizer runs train it first")
    p.add_argument("--work", type=Path, default=Path("/tmp/road_users"), help="runs and caches (not brought back)")
    p.add_argument("--minilm", type=Path, default=None,
                   help="pack_minilm.py's archive (or a MiniLM directory): also train the paper arm (issue 50)")
    p.add_argument("--budget-s", type=float, default=540.0, help="wall-clock seconds for every stage together")
    p.add_argument("--dry-run", action="store_true", help="tiny sizes on a CPU: a few steps and clips per stage")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    if not args.dry_run and not torch.cuda.is_available():
        raise SystemExit("gpu_road_users.py needs CUDA (or --dry-run for tiny sizes on a CPU)")
    start = time.monotonic()
    meta = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "torch": torch.__version__, "cuda": torch.version.cuda, "dry_run": args.dry_run,
            "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"}
    report = Report(args.out, meta)
    tokenizer = args.tokenizer
    if tokenizer is None:
        if not run_stage(report, args.out, "tokenizer", tokenizer_commands(args.work, args.dry_run),
                         BUDGETS["tokenizer"]):
            return report.data
        tokenizer = args.work / "tokenizer_d4_long/checkpoints/last.ckpt"
    report.save("tokenizer_checkpoint", {"folder": str(tokenizer)} if tokenizer.is_dir()
                else slim_checkpoint(tokenizer, args.out / "tokenizer_d4.ckpt"))
    cache = args.work / "tokens_d4"
    if not run_stage(report, args.out, "tokenize", tokenize_commands(tokenizer, cache, args.dry_run),
                     BUDGETS["tokenize"]):
        return report.data
    minilm = paper_arm(report, args.minilm, args.work, cache)
    left = max(args.budget_s - (time.monotonic() - start), 60)
    run_side_by_side(report, args.out, world_model_arms(cache, args.work, left, args.dry_run, minilm), left)
    for name in ("world_model_d4", "paper_d4"):
        last = args.work / name / "checkpoints/last.ckpt"
        if last.is_file():  # a stage stopped at its budget still keeps its last checkpoint
            report.save(f"{name}_checkpoint", slim_checkpoint(last, args.out / f"{name}.ckpt"))
    return report.data


if __name__ == "__main__":
    main()
