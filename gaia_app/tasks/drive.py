"""Closed-loop driving in the neural simulator: a speed-keeping controller drives GAIA-1 for `--seconds`.

    python -m gaia_app.tasks.drive --weights gaia1 --seconds 10 --target-speed 12 --out outputs/drive
    python -m gaia_app.tasks.drive --viewer         # also stream live to a Rerun viewer listening on 127.0.0.1
    python -m gaia_app.tasks.drive --screenshot docs/gallery/simulator_live.png   # stream to a headless viewer, capture it

The controller sees only the generated frames: the shipped inverse-dynamics probe (the one the controllability
table measures with) estimates the ego speed from each new pair of frames, a proportional controller turns the
error against `--target-speed` into the next speed command (gain `--gain` per step, at most ±`--max-accel` m/s²),
and the curvature command holds `--curvature`. Frames, the estimated and commanded speed, the trajectory (speed
and curvature integrated at the world model's rate) go to Rerun: always drive.rrd in --out and, with --viewer, live
to a viewer this command starts on 127.0.0.1 (gaia_app/viz/viewer.py; the SDK's own spawn would listen on every
interface). With --screenshot the stream goes live to a headless viewer instead (Mesa's software Vulkan is enough
without a GPU, gaia_app/viz/screenshot.py) and its view at the end of the episode is written as a PNG. The episode's
numbers go to drive.json.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import torch
from tqdm import tqdm

from gaia_app.data.transforms import to_float
from gaia_app.eval.controllability import load_probes, probed_actions
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.simulator import DrivingSimulator
from gaia_app.utils.run_dir import atomic_write_text
from gaia_app.utils.shipped import shipped_folder
from gaia_app.viz.screenshot import capture_live, spawn_headless
from gaia_app.viz.viewer import (
    LOOPBACK,
    ViewerUnavailable,
    port_open,
    spawn_viewer,
    stop_viewer,
)


def estimated_speed(probe: torch.nn.Module, previous: np.ndarray, frame: np.ndarray) -> float:
    """The probe's speed (m/s) between two observations (H, W, 3) uint8."""
    pair = torch.stack([to_float(torch.from_numpy(f).permute(2, 0, 1)) for f in (previous, frame)])[None]
    return float(probed_actions(probe, pair, 1)[0, 0, 0])


def speed_command(current: float, target: float, gain: float, max_step: float) -> float:
    """Proportional control of the commanded speed: the next command moves towards the target by gain × error,
    at most max_step (m/s per step), never below 0."""
    return max(0.0, current + float(np.clip(gain * (target - current), -max_step, max_step)))


def pose_step(pose: np.ndarray, speed: float, curvature: float, dt: float) -> np.ndarray:
    """(x, y, heading) after driving dt seconds at speed and curvature (an arc; ego frame of the first step)."""
    x, y, heading = pose
    distance = speed * dt
    turn = curvature * distance
    if abs(turn) < 1e-9:
        return np.array([x + distance * math.cos(heading), y + distance * math.sin(heading), heading])
    radius = 1.0 / curvature
    return np.array([x + radius * (math.sin(heading + turn) - math.sin(heading)),
                     y - radius * (math.cos(heading + turn) - math.cos(heading)), heading + turn])


def log_step(rec: rr.RecordingStream, step: int, time_s: float, frame: np.ndarray, estimate: float | None,
             command: list[float], trail: list[np.ndarray]) -> None:
    rec.set_time("step", sequence=step)
    rec.set_time("time", duration=time_s)
    rec.log("/camera", rr.Image(frame))
    rec.log("/speed/commanded", rr.Scalars(command[0]))
    if estimate is not None:
        rec.log("/speed/estimated", rr.Scalars(estimate))
    rec.log("/curvature/commanded", rr.Scalars(command[1]))
    rec.log("/trajectory", rr.LineStrips3D([[[p[0], p[1], 0.0] for p in trail]]))


def drive_blueprint() -> rrb.Blueprint:
    """The camera beside the commanded and estimated speed, the curvature command and the trajectory."""
    series = rrb.Vertical(rrb.TimeSeriesView(origin="/speed", name="speed (m/s): commanded, estimated from pixels"),
                          rrb.TimeSeriesView(origin="/curvature", name="curvature command (1/m)"),
                          rrb.Spatial3DView(origin="/trajectory", name="trajectory (commands integrated)"))
    return rrb.Blueprint(rrb.Horizontal(rrb.Spatial2DView(origin="/camera", name="camera (generated)"), series,
                                        column_shares=[3, 2]), collapse_panels=True)


def drive(env: DrivingSimulator, probe: torch.nn.Module, rec: rr.RecordingStream, steps: int, target: float,
          curvature: float, gain: float, max_step: float, seed: int) -> dict[str, Any]:
    """Run one closed-loop episode; returns its per-step record."""
    frame, info = env.reset(seed=seed)
    dt = 1.0 / env.pipeline.rate
    command = float(env.actions[-1][0])
    pose, trail, record = np.zeros(3), [np.zeros(3)], []
    log_step(rec, 0, 0.0, frame, None, [command, curvature], trail)
    for step in tqdm(range(1, steps + 1), desc="drive", unit="step"):
        action = [command, curvature]
        previous = frame
        frame, _, _, truncated, info = env.step(action)
        estimate = estimated_speed(probe, previous, frame)
        pose = pose_step(pose, action[0], curvature, dt)
        trail.append(pose)
        log_step(rec, step, info["time_s"], frame, estimate, action, trail)
        record.append({"step": step, "time_s": info["time_s"], "command": action, "estimated_speed": estimate})
        command = speed_command(estimate, target, gain, max_step * dt)
        if truncated:
            break
    estimates = np.array([r["estimated_speed"] for r in record])
    return {"steps": record, "target_speed": target, "mean_abs_speed_error_last_half":
            float(np.abs(estimates[len(estimates) // 2:] - target).mean()), "final_pose": pose.tolist()}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", default="gaia1", help="a weights folder (shipped name or path) with probes/")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--target-speed", type=float, default=12.0, help="m/s")
    parser.add_argument("--curvature", type=float, default=0.0, help="1/m, held (positive: left)")
    parser.add_argument("--gain", type=float, default=0.5, help="share of the speed error corrected per step")
    parser.add_argument("--max-accel", type=float, default=3.0, help="m/s² at most between commands")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("outputs/drive"))
    parser.add_argument("--viewer", action="store_true", help="stream live to a Rerun viewer on 127.0.0.1")
    parser.add_argument("--viewer-port", type=int, default=9876)
    parser.add_argument("--screenshot", type=Path, help="stream to a headless viewer and save its final view (PNG)")
    args = parser.parse_args(argv)
    folder = shipped_folder(args.weights)
    pipeline = Gaia1Pipeline.from_weights(folder, video_decoder=False)
    dynamics, _, _ = load_probes(folder / "probes", tuple(pipeline.image_size), float(pipeline.rate))
    steps = max(1, math.ceil(args.seconds * pipeline.rate))
    env = DrivingSimulator(pipeline, max_steps=steps)
    args.out.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("gaia_app", recording_id=f"drive-{args.seed}")
    sinks: list[Any] = [rr.FileSink(str(args.out / "drive.rrd"))]
    headless = None
    if args.screenshot:
        headless = spawn_headless()  # ViewerUnavailable names the missing driver: asked for, so not skipped
        sinks.append(rr.GrpcSink(headless[0].url))
    if args.viewer and args.screenshot:
        print("--screenshot streams to its own headless viewer; --viewer is ignored")
    elif args.viewer:
        try:
            if not port_open(LOOPBACK, args.viewer_port):
                spawn_viewer(args.viewer_port, LOOPBACK)
            sinks.append(rr.GrpcSink(f"rerun+http://{LOOPBACK}:{args.viewer_port}/proxy"))
        except (ViewerUnavailable, OSError) as error:
            print(f"no live viewer ({error}); writing {args.out / 'drive.rrd'} only")
    rec.set_sinks(*sinks)
    rec.send_blueprint(drive_blueprint())
    try:
        results = drive(env, dynamics.eval(), rec, steps, args.target_speed, args.curvature, args.gain,
                        args.max_accel, args.seed)
        rec.flush()
        if headless is not None:
            print(f"live view: {capture_live(*headless, args.screenshot)}")
    finally:  # capture_live stops the viewer; a failed episode must not leave it running
        if headless is not None:
            stop_viewer(headless[1])
    atomic_write_text(args.out / "drive.json", json.dumps(results, indent=2))
    print(f"mean |estimated - target| speed over the last half: {results['mean_abs_speed_error_last_half']:.2f} m/s; "
          f"{args.out / 'drive.json'}, {args.out / 'drive.rrd'}")
    return results


if __name__ == "__main__":
    main()
