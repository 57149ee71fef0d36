r"""Futures with moving agents: persistence, interaction and multiple futures of the lead vehicle (issue 49 item 3).

    python benchmarks/agent_futures.py --weights gaia1 --json outputs/agent_futures/gaia1.json

On --contexts held-out contexts of a synthetic world used for nothing else (--world-seed) that have a vehicle in the
ego lane within 30 m at the last context frame, under the shipped weights' protocol (4 context frames, 1.25 s of
future at 6.25 Hz, guidance scale 1.5, frames decoded by the tokenizer like the controllability table), the four
commands of that table with shared sampling noise; the synthetic world re-simulates each scene under the same
commands (gaia_app/protocols/agent_futures.py has the protocol, gaia_app/eval/lead_gap.py the reader). The
reader is the shipped agent probe (gaia_app/weights/probes). Targets: persistence ≥ 0.8 and "closer under
accelerate than brake" ≥ 0.8 for the model row; the multiple-futures spread wider than the round trips'.

Writes the JSON (--json), the markdown table (beside it) and the gallery strip of the first context (GAIA-1 Fig. 5:
the real continuation on top, then --futures futures under its own actions) as PNG and .rrd into --out.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import rerun as rr
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from gaia_app.eval.agent_iou import load_agent_probe
from gaia_app.pipelines.gaia1_inputs import future_frames
from gaia_app.protocols.agent_futures import agent_futures, markdown
from gaia_app.protocols.loading import load_pipeline
from gaia_app.utils.run_dir import atomic_write_text
from gaia_app.viz.gallery import write_png
from gaia_app.viz.media import image_grid, log_images

CONF = Path(__file__).resolve().parents[1] / "conf"
# the shipped weights' protocol (gaia_app/weights/MANIFEST.md, controllability)
PROTOCOL = ["context.frames=4", "seconds=1.25", "guidance.scale=1.5", "guidance.text_scale=3"]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--weights", default="gaia1", help="a GAIA-1 weights folder or shipped name")
    p.add_argument("--contexts", type=int, default=32, help="held-out contexts with a lead vehicle")
    p.add_argument("--world-seed", type=int, default=4950, help="the held-out world (used for nothing else)")
    p.add_argument("--scan", type=int, default=400, help="clips of the world searched for contexts")
    p.add_argument("--futures", type=int, default=8, help="futures per context for the spread")
    p.add_argument("--spread-contexts", type=int, default=4, help="contexts whose futures give the spread")
    p.add_argument("--probe", default="probes", help="weights folder of the agent probe")
    p.add_argument("--seed", type=int, default=0, help="sampling seed")
    p.add_argument("--json", type=Path, default=None, help="write the results here (and the table beside it)")
    p.add_argument("--out", type=Path, default=Path("outputs/agent_futures"), help="where the gallery goes")
    p.add_argument("overrides", nargs="*", help="Hydra overrides of generate.yaml (after --)")
    args = p.parse_args(argv)
    for name in ("contexts", "futures", "spread_contexts"):
        if getattr(args, name) < 2:
            p.error(f"--{name.replace('_', '-')}: at least 2 for an interval, got {getattr(args, name)}")
    return args


def gallery(videos: dict[str, torch.Tensor], out: Path) -> Path:
    """The real continuation above the futures of one context, frames left to right; PNG and .rrd."""
    rows = torch.cat([videos["real"], videos["futures"]])  # (1 + k, t, 3, H, W)
    grid = image_grid(rows.flatten(0, 1), ncols=rows.shape[1])
    png = out / "futures_strip.png"
    write_png(png, grid)
    recording = rr.RecordingStream("gaia_app_agent_futures")
    recording.save(str(out / "agent_futures.rrd"))
    log_images(recording, "futures/strip", rows.flatten(0, 1), ncols=rows.shape[1])
    recording.flush()
    return png


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("generate", [*PROTOCOL, f"weights={args.weights}", *args.overrides])
    pipeline = load_pipeline(cfg, video_decoder=False)
    probe, info = load_agent_probe(args.probe)
    if tuple(info["image_size"]) != tuple(pipeline.image_size):
        raise ValueError(f"--probe {args.probe} reads {tuple(info['image_size'])} frames, the weights make "
                         f"{tuple(pipeline.image_size)}")
    frames = future_frames(cfg.seconds, pipeline.rate, at_least=2)
    started = time.perf_counter()
    results, videos = agent_futures(pipeline, probe, args.world_seed, args.contexts, int(cfg.context.frames), frames,
                                    torch.Generator().manual_seed(args.seed), args.futures, args.spread_contexts,
                                    args.scan)
    results |= {"weights": args.weights, "seed": args.seed, "seconds": round(time.perf_counter() - started, 1)}
    args.out.mkdir(parents=True, exist_ok=True)
    results["gallery"] = str(gallery(videos, args.out))
    table = markdown(results)
    print(table)
    if args.json:
        atomic_write_text(args.json, json.dumps(results, indent=2))
        atomic_write_text(args.json.with_suffix(".md"), table)
    return results


if __name__ == "__main__":
    main()
