"""Closed-loop driving in the neural simulator: a speed-keeping controller drives GAIA-1 for `--seconds`.

    python -m gaia_app.tasks.drive --weights gaia1 --seconds 10 --target-speed 12 --out outputs/drive
    python -m gaia_app.tasks.drive --viewer         # also stream live to a Rerun viewer listening on 127.0.0.1
    # stream to a headless viewer, capture it:
    python -m gaia_app.tasks.drive --screenshot docs/gallery/simulator_live.png

The controller sees only the generated frames. After every step the shipped inverse-dynamics probe (the one the
controllability table measures with) reads the ego speed from the last pair of frames. Its readings are noisy
(about ±2.5 m/s from step to step on the shipped weights), so they are not used as the state directly: a Kalman
filter (`SpeedFilter`) predicts the speed by adding each change of the speed command (a model of the plant: the
world model drives what it is told to), then corrects the prediction by the reading with a gain that settles near
0.1 (`--process-noise`, `--probe-noise`). An integral controller (`SpeedKeeper`) moves the speed command by
`--gain` × (target − estimate) per step, at most `--max-accel` m/s² (the world model was trained on changes of
about 0.4 m/s per step); the curvature command holds `--curvature`. The world model renders each step with
classifier-free guidance ×`--guidance` (1.5, the shipped protocol's scale) on the actions (GAIA-1 §5.1): unguided,
its speed follows the command too weakly for the loop to hold a target (docs/simulator.md). `--controller` picks
another policy for comparison: `previous` (the proportional law on the raw probe reading this module used before),
`open-loop` (the same integral law on the commands alone: a ramp to the target, the probe ignored) or `none` (the
context's speed held). `--seeds` runs every policy on several sampler seeds side by side (tasks/drive_seeds.py).

Frames, the estimated and commanded speed, the trajectory (speed and curvature integrated at the world model's
rate) go to Rerun: always drive.rrd in --out and, with --viewer, live to a viewer this command starts on
127.0.0.1 (gaia_app/viz/viewer.py; the SDK's own spawn would listen on every interface). With --screenshot the
stream goes live to a headless viewer instead (Mesa's software Vulkan is enough without a GPU,
gaia_app/viz/screenshot.py) and its view at the end of the episode is written as a PNG. The episode's numbers go
to drive.json.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass, field
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
from gaia_app.utils.threads import apply_thread_policy
from gaia_app.viz.screenshot import capture_live, spawn_headless
from gaia_app.viz.viewer import (
    LOOPBACK,
    ViewerUnavailable,
    port_open,
    spawn_viewer,
    speaks_grpc,
    stop_viewer,
)
from gaia_app.weights.folders import shipped_folder


def estimated_speed(probe: torch.nn.Module, previous: np.ndarray, frame: np.ndarray) -> float:
    """The probe's speed (m/s) between two observations (H, W, 3) uint8."""
    pair = torch.stack([to_float(torch.from_numpy(f).permute(2, 0, 1)) for f in (previous, frame)])[None]
    return float(probed_actions(probe, pair, 1)[0, 0, 0])


CONTROLLERS = ("filtered", "previous", "open-loop", "none")
BASELINE = "none"  # the uncontrolled policy every --seeds comparison is scored against


@dataclass
class SpeedFilter:
    """Kalman filter of the ego speed (m/s) with the speed command's change as its input.

    Plant model: from one step to the next the rendered speed changes by the change of the command, plus process
    noise of std `process_noise` (m/s per step: what the world model does on its own); the probe reads the speed
    with noise of std `probe_noise`. Predict: x ← x + Δu, P ← P + q²; correct: K = P / (P + r²), x ← x + K (z − x),
    P ← (1 − K) P. With q ≪ r the gain settles near q / r, so a reading moves the estimate by a small share of its
    error: the probe corrects the slow drift between command and picture, and its step-to-step noise is averaged
    out instead of being fed back into the command."""

    process_noise: float = 0.3
    probe_noise: float = 2.5
    estimate: float = 0.0
    variance: float = 0.0

    def start(self, speed: float) -> None:
        """Start from a known speed (the context's) as uncertain as one probe reading."""
        self.estimate, self.variance = float(speed), self.probe_noise**2

    def update(self, command_change: float, reading: float) -> float:
        """One step: the command changed by `command_change` (m/s), the probe read `reading` → the estimate."""
        self.estimate += command_change
        self.variance += self.process_noise**2
        gain = self.variance / (self.variance + self.probe_noise**2)
        self.estimate += gain * (reading - self.estimate)
        self.variance *= 1.0 - gain
        return self.estimate


def speed_command(command: float, estimate: float, target: float, gain: float, max_step: float) -> float:
    """Integral control of the commanded speed: the command moves by gain × (target − estimate), at most max_step
    (m/s per step), never below 0. The command keeps what earlier corrections added, so a persistent offset between
    command and picture is worked off."""
    return max(0.0, command + float(np.clip(gain * (target - estimate), -max_step, max_step)))


def previous_command(reading: float, target: float, gain: float, max_step: float) -> float:
    """The law this module used before the filter: the raw reading moved towards the target (for comparison)."""
    return max(0.0, reading + float(np.clip(gain * (target - reading), -max_step, max_step)))


@dataclass
class SpeedKeeper:
    """Chooses each step's speed command from the probe's reading (module docstring). controller: one of
    CONTROLLERS; max_step: m/s per step."""

    target: float
    gain: float
    max_step: float
    controller: str = "filtered"
    filter: SpeedFilter = field(default_factory=SpeedFilter)
    command: float = 0.0
    applied: float = 0.0  # the command the newest frame was rendered under

    def __post_init__(self) -> None:
        if self.controller not in CONTROLLERS:
            raise ValueError(f"controller={self.controller!r}: expected one of {CONTROLLERS}")

    def start(self, speed: float) -> None:
        """A new episode from the context's speed (m/s): that speed is the first command."""
        self.command = self.applied = float(speed)
        self.filter.start(speed)

    def next(self, reading: float) -> float:
        """The probe's reading of the frame just rendered under `self.command` → the speed estimate; `self.command`
        becomes the next step's command."""
        change, self.applied = self.command - self.applied, self.command
        estimate = self.filter.update(change, reading)  # the filter follows every policy's commands
        if self.controller == "filtered":
            self.command = speed_command(self.command, estimate, self.target, self.gain, self.max_step)
        elif self.controller == "open-loop":  # the plant model alone: as if each command were met
            self.command = speed_command(self.command, self.command, self.target, self.gain, self.max_step)
        elif self.controller == "previous":
            self.command = previous_command(reading, self.target, self.gain, self.max_step)
        return estimate


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


def log_step(rec: rr.RecordingStream, step: int, time_s: float, frame: np.ndarray, reading: float | None,
             estimate: float | None, command: list[float], trail: list[np.ndarray]) -> None:
    rec.set_time("step", sequence=step)
    rec.set_time("time", duration=time_s)
    rec.log("/camera", rr.Image(frame))
    rec.log("/speed/commanded", rr.Scalars(command[0]))
    if reading is not None:
        rec.log("/speed/probed", rr.Scalars(reading))
        rec.log("/speed/estimated", rr.Scalars(estimate))
    rec.log("/curvature/commanded", rr.Scalars(command[1]))
    rec.log("/trajectory", rr.LineStrips3D([[[p[0], p[1], 0.0] for p in trail]]))


def drive_blueprint() -> rrb.Blueprint:
    """The camera beside the commanded and estimated speed, the curvature command and the trajectory."""
    series = rrb.Vertical(rrb.TimeSeriesView(origin="/speed", name="speed (m/s): commanded, probed, filtered"),
                          rrb.TimeSeriesView(origin="/curvature", name="curvature command (1/m)"),
                          rrb.Spatial3DView(origin="/trajectory", name="trajectory (commands integrated)"))
    return rrb.Blueprint(rrb.Horizontal(rrb.Spatial2DView(origin="/camera", name="camera (generated)"), series,
                                        column_shares=[3, 2]), collapse_panels=True)


def drive(env: DrivingSimulator, probe: torch.nn.Module, rec: rr.RecordingStream | None, steps: int,
          keeper: SpeedKeeper, curvature: float, seed: int, progress: bool = True,
          options: dict[str, Any] | None = None) -> dict[str, Any]:
    """Run one closed-loop episode (logged to `rec` unless None); returns its per-step record. options: the
    simulator's reset options (`episode_options`: context clip, guidance scale), None for its defaults."""
    frame, info = env.reset(seed=seed, options=options)
    dt = 1.0 / env.pipeline.rate
    keeper.start(float(env.actions[-1][0]))
    pose, trail, record = np.zeros(3), [np.zeros(3)], []
    if rec is not None:
        log_step(rec, 0, 0.0, frame, None, None, [keeper.command, curvature], trail)
    for step in tqdm(range(1, steps + 1), desc="drive", unit="step", disable=not progress):
        action = [keeper.command, curvature]
        previous = frame
        frame, _, _, truncated, info = env.step(action)
        reading = estimated_speed(probe, previous, frame)
        estimate = keeper.next(reading)
        pose = pose_step(pose, action[0], curvature, dt)
        trail.append(pose)
        if rec is not None:
            log_step(rec, step, info["time_s"], frame, reading, estimate, action, trail)
        record.append({"step": step, "time_s": info["time_s"], "command": action, "probed_speed": reading,
                       "estimated_speed": estimate})
        if truncated:
            break
    return {"steps": record, "target_speed": keeper.target, "controller": keeper.controller, "seed": seed,
            "context": {k: v for k, v in (options or {}).items() if k in ("world_seed", "index")},
            **speed_errors(record, keeper.target), "final_pose": pose.tolist()}


def speed_errors(record: list[dict[str, Any]], target: float, window_s: float = 5.0) -> dict[str, float]:
    """Over the steps of the last `window_s` seconds: mean |probed − target| (the score), |mean probed − target|
    (the part a controller can remove; the probe's step-to-step noise stays) and mean |command − target|."""
    last = [r for r in record if r["time_s"] > record[-1]["time_s"] - window_s]
    probed = np.array([r["probed_speed"] for r in last])
    commands = np.array([r["command"][0] for r in last])
    return {"probed_speed_error": float(np.abs(probed - target).mean()),
            "probed_mean_offset": float(abs(probed.mean() - target)),
            "command_error": float(np.abs(commands - target).mean()), "window_steps": len(last)}


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", default="gaia1", help="a weights folder (shipped name or path) with probes/")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--target-speed", type=float, default=12.0, help="m/s")
    parser.add_argument("--curvature", type=float, default=0.0, help="1/m, held (positive: left)")
    parser.add_argument("--controller", choices=CONTROLLERS, default="filtered")
    parser.add_argument("--gain", type=float, default=0.5, help="share of the estimated speed error added to the "
                        "command per step (previous: corrected per step)")
    parser.add_argument("--max-accel", type=float, default=3.0, help="m/s² at most between commands")
    parser.add_argument("--process-noise", type=float, default=0.3, help="filter: m/s per step the world drifts")
    parser.add_argument("--probe-noise", type=float, default=2.5, help="filter: m/s std of one probe reading")
    parser.add_argument("--guidance", type=float, default=1.5,
                        help="classifier-free guidance scale on the actions (GAIA-1 §5.1; 1.5: the scale the shipped "
                             "weights' controllability is measured with; 0: unguided, the conditional "
                             "stream alone at half the cost per step)")
    parser.add_argument("--world-seed", type=int, default=1000, help="the synthetic world of the context clip")
    parser.add_argument("--clip", type=int, default=0, help="the context clip's index in that world")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--seeds", help="evaluate every controller side by side on these sampler seeds, e.g. "
                        "101-116 or 1,2,3 (tasks/drive_seeds.py); no recording")
    parser.add_argument("--clips", help="with --seeds: the context clips, the k-th seed's episodes start from the "
                                         "k-th (cycled), e.g. 0-7 (default: --clip for every seed)")
    parser.add_argument("--controllers", help="with --seeds: the controllers to compare, e.g. filtered,none "
                                              "(default: all; none, the baseline, must be among them)")
    parser.add_argument("--out", type=Path, default=Path("outputs/drive"))
    parser.add_argument("--viewer", action="store_true", help="stream live to a Rerun viewer on 127.0.0.1")
    parser.add_argument("--viewer-port", type=int, default=9876)
    parser.add_argument("--screenshot", type=Path, help="stream to a headless viewer and save its final view (PNG)")
    args = parser.parse_args(argv)
    for name in ("seconds", "max_accel", "process_noise", "probe_noise"):
        if not math.isfinite(getattr(args, name)) or getattr(args, name) <= 0:
            parser.error(f"--{name.replace('_', '-')}={getattr(args, name)}: expected a finite number > 0")
    if not math.isfinite(args.guidance) or args.guidance < 0:
        parser.error(f"--guidance={args.guidance}: expected a finite scale >= 0")
    for name in ("world_seed", "clip"):
        if getattr(args, name) < 0:
            parser.error(f"--{name.replace('_', '-')}={getattr(args, name)}: expected an integer >= 0")
    if not 0 <= args.gain <= 1:
        parser.error(f"--gain={args.gain}: expected a share in [0, 1]")
    if not 0 <= args.target_speed <= 70:
        parser.error(f"--target-speed={args.target_speed}: expected m/s in [0, 70] (the simulator's speed range)")
    read_seed_options(parser, args)
    return args


def parse_seeds(text: str, option: str = "--seeds") -> list[int]:
    """"101-116" or "1,2,3" (or both: "1-3,7") → the seeds (or clips), each an integer ≥ 0; ValueError naming
    `option`."""
    seeds: list[int] = []
    try:
        for part in text.split(","):
            low, _, high = part.strip().partition("-")
            seeds += list(range(int(low), int(high or low) + 1))
    except ValueError:
        raise ValueError(f"{option}={text!r}: expected integers and ranges such as 101-116 or 1,2,3") from None
    if not seeds or min(seeds) < 0 or len(set(seeds)) != len(seeds):
        raise ValueError(f"{option}={text!r}: expected distinct integers ≥ 0")
    return seeds


def parse_controllers(text: str | None) -> list[str]:
    """"filtered,none" → those controllers (None: all of CONTROLLERS); the baseline "none" must be among them."""
    names = list(CONTROLLERS) if text is None else [n.strip() for n in text.split(",")]
    if any(n not in CONTROLLERS for n in names) or BASELINE not in names or len(set(names)) != len(names):
        raise ValueError(f"--controllers={text!r}: expected distinct names among {CONTROLLERS}, {BASELINE!r} included")
    return names


def read_seed_options(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """--seeds, --clips and --controllers → lists on `args` (--controllers: all when not given), read before any
    weights load; --clips/--controllers need --seeds."""
    if args.seeds is None and (args.clips is not None or args.controllers is not None):
        parser.error("--clips and --controllers compare controllers over seeds: give --seeds too")
    try:
        if args.seeds is not None:
            args.seeds, args.controllers = parse_seeds(args.seeds), parse_controllers(args.controllers)
        if args.clips is not None:
            args.clips = parse_seeds(args.clips, "--clips")
    except ValueError as error:
        parser.error(str(error))


def make_keeper(args: argparse.Namespace, rate: float, controller: str | None = None) -> SpeedKeeper:
    """The speed controller the arguments describe (`controller` overrides --controller)."""
    return SpeedKeeper(args.target_speed, args.gain, args.max_accel / rate, controller or args.controller,
                       SpeedFilter(args.process_noise, args.probe_noise))


def episode_options(args: argparse.Namespace, clip: int | None = None) -> dict[str, Any]:
    """The simulator's reset options: clip `clip` (default --clip) of the synthetic world --world-seed as context,
    the actions guided at --guidance."""
    return {"context": "synthetic", "world_seed": args.world_seed, "index": args.clip if clip is None else clip,
            "guidance": args.guidance}


def load_world(weights: str) -> tuple[Gaia1Pipeline, torch.nn.Module]:
    """The pipeline (tokenizer observations) and the speed probe of a weights folder."""
    folder = shipped_folder(weights)
    pipeline = Gaia1Pipeline.from_weights(folder, video_decoder=False)
    dynamics, _, _ = load_probes(folder / "probes", tuple(pipeline.image_size), float(pipeline.rate))
    return pipeline, dynamics.eval()


def open_recording(args: argparse.Namespace) -> tuple[rr.RecordingStream, Any]:
    """drive.rrd in --out, plus the live or headless viewer asked for → (recording, headless viewer or None)."""
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
            elif not speaks_grpc(LOOPBACK, args.viewer_port):
                raise ViewerUnavailable(f"--viewer-port {args.viewer_port} is taken by a program that is not a Rerun "
                                        "viewer; choose another port")
            sinks.append(rr.GrpcSink(f"rerun+http://{LOOPBACK}:{args.viewer_port}/proxy"))
        except (ViewerUnavailable, OSError) as error:
            print(f"no live viewer ({error}); writing {args.out / 'drive.rrd'} only")
    rec.set_sinks(*sinks)
    rec.send_blueprint(drive_blueprint())
    return rec, headless


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    threads, why = apply_thread_policy(None)  # OMP_NUM_THREADS when set, else the free CPUs (utils/threads.py)
    print(f"CPU threads: {threads} ({why})")
    pipeline, probe = load_world(args.weights)
    steps = max(1, math.ceil(args.seconds * pipeline.rate))
    env = DrivingSimulator(pipeline, max_steps=steps)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.seeds:
        from gaia_app.tasks.drive_seeds import evaluate_seeds

        return evaluate_seeds(args, env, probe, steps)
    rec, headless = open_recording(args)
    try:
        results = drive(env, probe, rec, steps, make_keeper(args, pipeline.rate), args.curvature, args.seed,
                        options=episode_options(args))
        try:
            rec.flush()
        except RuntimeError as error:  # a live viewer that went away: the episode and drive.json still count
            print(f"the live viewer stopped receiving ({error}); drive.rrd may miss the last messages")
        if headless is not None:
            print(f"live view: {capture_live(*headless, args.screenshot)}")
    finally:  # capture_live stops the viewer; a failed episode must not leave it running
        if headless is not None:
            stop_viewer(headless[1])
    atomic_write_text(args.out / "drive.json", json.dumps(results, indent=2))
    print(f"mean |probed - target| speed over the last 5 s: {results['probed_speed_error']:.2f} m/s; "
          f"{args.out / 'drive.json'}, {args.out / 'drive.rrd'}")
    return results


if __name__ == "__main__":
    main()
