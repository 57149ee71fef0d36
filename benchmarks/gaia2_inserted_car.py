r"""GAIA-2: is a car inserted with `model.add_agents` drawn as a car, and does a braking one close in?
(road-users issue)

    python benchmarks/gaia2_inserted_car.py [--weights gaia2] [--contexts 16] [--json OUT] [-- generate.yaml overrides]

On --contexts held-out 3-camera scenes of world --world-seed (used for nothing else), each rolled out as the demo does
(`make demo`: 3 chunks, guidance ×3 on the agent boxes, one future) twice with a car inserted --distance m ahead in
the ego lane: once holding its distance (velocity 0 relative to the ego, "hold") and once closing in at --closing m/s
("brake", a lead car braking harder than the ego). The shipped agent probe (gaia_app/weights/probes) reads the front
camera's generated frames:
- read as a car: the share of generated frames in which the probe marks at least READ_SHARE of the inserted car's
  projected box (target ≥ 70 %). For scale, the same share for the real lead vehicles within 30 m of world 4949
  (their boxes from the world's instance masks), the probe's ceiling;
- closing in: the probe's marked pixels inside the car's boxes, last generated frame ÷ first, for hold and for brake,
  and the share of scenes in which brake grows more than hold (the projected boxes' own growth is the reference).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from tqdm import tqdm

from gaia_app.data.agent_regions import box_mask
from gaia_app.data.clip import AgentBoxes
from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.eval.agent_fidelity import box_mask as pixel_box
from gaia_app.eval.agent_fidelity import fidelity_frames
from gaia_app.eval.agent_iou import load_agent_probe, predicted_agents
from gaia_app.eval.intervals import mean_interval, ratio_interval, share_interval
from gaia_app.pipelines.gaia2_edits import with_added_agents
from gaia_app.protocols.gaia2_context import commanded, latent_steps, sample, source_clip
from gaia_app.protocols.loading import load_gaia2
from gaia_app.utils.run_dir import atomic_write_text

CONF = Path(__file__).resolve().parents[1] / "conf"
READ_SHARE = 0.25
"""A car is read when the probe marks at least this share of its box (a real car fills ~60–80 % of its box)."""


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--weights", default="gaia2")
    p.add_argument("--contexts", type=int, default=16)
    p.add_argument("--world-seed", type=int, default=4960)
    p.add_argument("--distance", type=float, default=15.0, help="metres from the ego's rear axle to the car's centre")
    p.add_argument("--closing", type=float, default=3.0, help="m/s at which the braking car closes in")
    p.add_argument("--real-clips", type=int, default=64, help="clips of world 4949 for the real lead vehicles' row")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("overrides", nargs="*", help="Hydra overrides of generate.yaml (after --)")
    return p.parse_args(argv)


def demo_config(weights: str, seed: int, overrides: list[str]):
    """generate.yaml as `make demo` runs GAIA-2 (3 chunks, one future, guidance ×3), on world `seed`."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("generate", ["model=gaia2", "data=synthetic_rig", "mode=rollout", f"weights={weights}",
                                    "model.chunks=3", "num_futures=1", "model.guidance.scale=3",
                                    f"context.seed={seed}", *overrides])


def inserted(distance: float, closing: float) -> list[dict[str, Any]]:
    return [{"category": "car", "centre": [distance, 0.0, 0.75], "size": [4.5, 1.9, 1.5], "velocity": [-closing, 0.0]}]


def car_boxes(clip: Any, track_id: int, first: int, height: int, width: int) -> np.ndarray:
    """(T - first, H, W) bool: the inserted car's box projected into the front camera on each generated frame."""
    out = []
    for boxes in clip.agents[first:]:
        keep = boxes.track_id == track_id
        one = AgentBoxes(boxes.centre[keep], boxes.size[keep], boxes.yaw[keep], boxes.category[keep],
                         boxes.track_id[keep])
        out.append(box_mask(one, clip.cameras[0], height, width))
    return np.stack(out)


def rollout(cfg, pipeline, index: int, specs: list[dict[str, Any]]) -> tuple[torch.Tensor, np.ndarray]:
    """Front-camera generated frames (t, 3, H, W) of scene `index` with the car of `specs`, and its boxes (t, H, W)."""
    cfg.context.index = index
    steps = latent_steps(cfg)
    first = cfg.model.context_steps * pipeline.temporal
    clip = commanded(cfg, source_clip(cfg, pipeline, steps), first, pipeline.metadata.fields)
    own = max((int(a.track_id.max()) for a in clip.agents or [] if len(a)), default=0)
    clip = with_added_agents(clip, specs, first)
    frames = pipeline.decode(sample(cfg, pipeline, clip).latents)[0, 0, first:].clamp(-1, 1).float().cpu()
    boxes = car_boxes(clip, own + 1, first, *frames.shape[-2:])
    return frames[: len(boxes)], boxes[: len(frames)]


def real_lead_reading(probe, count: int = 64) -> dict[str, Any]:
    """The probe's reading of real lead vehicles within 30 m (world 4949, 12.5 Hz): share of frames read."""
    world = SyntheticClipDataset(num_clips=count, seed=4949, height=64, width=112, clip_len=15, render_rate=12.5)
    held = fidelity_frames([world.sample(i) for i in tqdm(range(count), desc="real lead vehicles")], 12.5, 8)
    predicted = predicted_agents(probe, held.frames)
    read = frames = 0
    for p, lead in zip(predicted.flatten(0, 1).numpy(), held.lead.flatten(0, 1).numpy()):
        if lead.any():
            box = pixel_box(np.where(lead, 0, -1))
            frames += 1
            read += (p & box).sum() >= READ_SHARE * box.sum()
    return share_interval(int(read), frames).as_dict() if frames else {}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    cfg = demo_config(args.weights, args.world_seed, args.overrides)
    pipeline = load_gaia2(cfg)
    probe, _ = load_agent_probe()
    started = time.perf_counter()
    rows: dict[str, list] = {"read": [], "frames": [], "growth_hold": [], "growth_brake": [], "box_growth_brake": []}
    for index in tqdm(range(args.contexts), desc="scenes"):
        for name, closing in (("hold", 0.0), ("brake", args.closing)):
            frames, boxes = rollout(cfg, pipeline, index, inserted(args.distance, closing))
            marked = (predicted_agents(probe, frames[None])[0].numpy() & boxes).sum(axis=(1, 2))
            area = boxes.sum(axis=(1, 2))
            seen = area > 0
            rows["read"].append(int((marked[seen] >= READ_SHARE * area[seen]).sum()))
            rows["frames"].append(int(seen.sum()))
            rows[f"growth_{name}"].append(float((marked[-1] + 1) / (marked[0] + 1)))
            if name == "brake":
                rows["box_growth_brake"].append(float(area[-1] / max(area[0], 1)))
    growth = np.array(rows["growth_brake"]) > np.array(rows["growth_hold"])
    result = {"weights": args.weights, "contexts": args.contexts, "world_seed": args.world_seed,
              "distance": args.distance,
              "closing": args.closing, "read_share": READ_SHARE,
              "read_as_car": ratio_interval(rows["read"], rows["frames"]).as_dict(),
              "real_lead_read": real_lead_reading(probe, args.real_clips),
              "growth_hold": mean_interval(rows["growth_hold"]).as_dict(),
              "growth_brake": mean_interval(rows["growth_brake"]).as_dict(),
              "box_growth_brake": mean_interval(rows["box_growth_brake"]).as_dict(),
              "brake_grows_more": share_interval(int(growth.sum()), len(growth)).as_dict(),
              "seconds": time.perf_counter() - started, "per_scene": rows}
    print(markdown(result))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.json, json.dumps(result, indent=2) + "\n")
    return result


def markdown(r: dict[str, Any]) -> str:
    def est(d: dict[str, float], k: int = 2) -> str:
        return f"{d['mean']:.{k}f} [{d['low']:.{k}f}, {d['high']:.{k}f}]" if d else "n/a"

    return "\n".join([
        f"GAIA-2 inserted car ({r['contexts']} scenes of world {r['world_seed']}, {r['distance']:g} m ahead; "
        f"{r['seconds']:.0f} s)", "",
        "| | value |", "|---|---|",
        f"| generated frames where the probe reads the inserted car "
        f"(≥ {r['read_share']:.0%} of its box; target ≥ 70 %) "
        f"| {est(r['read_as_car'])} |",
        f"| real lead vehicles within 30 m read the same way (the probe's ceiling) | {est(r['real_lead_read'])} |",
        f"| probed car pixels, last ÷ first generated frame: hold | {est(r['growth_hold'])} |",
        f"| the same, braking car closing in at {r['closing']:g} m/s | {est(r['growth_brake'])} |",
        f"| its projected box, last ÷ first (the reference) | {est(r['box_growth_brake'])} |",
        f"| scenes where the braking car grows more than the holding one | {est(r['brake_grows_more'])} |",
    ]) + "\n"


if __name__ == "__main__":
    main()
