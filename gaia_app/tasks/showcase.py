"""`generate.py mode=showcase`: what `make demo` shows (docs/generate.md) — one context, steered futures, prompts.

From the shipped weights (weights=gaia1) or checkpoints, in one run:
- commands/: one held-out context, then `showcase.commands` (brake, accelerate, left, right) each for the same
  `seconds`; grid.mp4 (real continuation | the real continuation through the tokenizer | one future per command)
  and strip.png (one labelled row each, context frames marked green, generated red). The second row is the best
  any future can look: every future is decoded from tokens, and the small tokenizer redraws what its codebook
  lacks (houses come back as hedges, docs/generate.md), context frames included;
- prompts/: generation from text alone, no prompt against each of `showcase.prompts` (night, snow), all from the
  same sampling noise (`showcase.shared_noise`); grid.mp4 and strip.png;
- showcase.rrd: both, with the commanded speed and curvature of every future plotted.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import rerun as rr
import torch
from omegaconf import DictConfig

from gaia_app.data.synthetic.gallery import label
from gaia_app.data.video_io import write_video
from gaia_app.eval.controllability import probe_clips
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.gaia1_inputs import future_frames
from gaia_app.protocols.controllability import commanded_actions, rollout_frames, world_clips
from gaia_app.protocols.loading import load_pipeline
from gaia_app.tasks.rollout import mark, staging
from gaia_app.utils.run_dir import atomic_write_text
from gaia_app.viz.blueprints import showcase_blueprint
from gaia_app.viz.media import to_hwc_uint8, video_grid

STRIPE = 2  # pixels of the context / generated marker at the top of each frame
REAL_ROWS = ["real continuation", "real, through the tokenizer"]  # the rows above the futures, and their entities
REAL_ENTITIES = ["real", "real_tokenized"]


def marked(frames: torch.Tensor, context: int) -> np.ndarray:
    """(k, t, 3, H, W) in [-1, 1] → uint8 (k, t, H, W, 3), context frames marked green, generated red (rollout.mark)."""
    return mark(frames, context, upsample=0).transpose(0, 1, 3, 4, 2)


def strip(videos: np.ndarray, names: list[str], scale: int = 2) -> np.ndarray:
    """uint8 (k, t, H, W, 3) → one labelled row of t frames per video, upscaled `scale`× (nearest)."""
    rows = []
    for video, name in zip(videos, names):
        row = np.concatenate(list(video), axis=1)
        row = cv2.resize(row, (row.shape[1] * scale, row.shape[0] * scale), interpolation=cv2.INTER_NEAREST)
        label(row, name, (0, STRIPE * scale))
        rows.append(row)
    return np.concatenate(rows, axis=0)


def write_panel(folder: Path, videos: np.ndarray, names: list[str], fps: float) -> list[str]:
    """grid.mp4 (videos side by side) and strip.png of one panel; returns the file names."""
    folder.mkdir(parents=True, exist_ok=True)
    grid = video_grid(videos.transpose(0, 1, 4, 2, 3), ncols=len(videos), pad=2)
    grid = grid.transpose(0, 2, 3, 1)
    write_video(folder / "grid.mp4", grid[:, : grid.shape[1] // 2 * 2, : grid.shape[2] // 2 * 2], fps)
    image = strip(videos, names)
    cv2.imwrite(str(folder / "strip.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return [f"{folder.name}/grid.mp4", f"{folder.name}/strip.png"]


def command_panel(cfg: DictConfig, pipeline: Gaia1Pipeline, generator: torch.Generator) -> dict[str, Any]:
    """The held-out context clip, then one future per command (and the real continuation, raw and through the
    tokenizer and the renderer the futures use)."""
    rate, (height, width) = pipeline.rate, pipeline.image_size
    t0, frames = cfg.context.frames, future_frames(cfg.seconds, rate)
    clip = probe_clips(world_clips(cfg.context.seed, 1, height, width, t0 + frames, rate, start=cfg.context.index),
                       rate, t0 + frames)
    commands = [tuple(c) for c in cfg.showcase.commands]
    actions = commanded_actions(clip, t0, frames, rate, commands)  # (C, t, 2)
    context = clip.frames[:, :t0].repeat(len(commands), 1, 1, 1, 1)
    shared = torch.zeros(len(commands), dtype=torch.long) if cfg.showcase.shared_noise else None  # one context
    futures = rollout_frames(pipeline, context, frames, len(commands), None, actions, generator, shared)
    through = pipeline.render(pipeline.encode(clip.frames[0])[None], generator)[0]
    return {"real": torch.cat([clip.frames, through]), "futures": futures, "actions": actions, "context": t0,
            "names": REAL_ROWS + [f"{speed} / {curvature}" for speed, curvature in commands]}


def prompt_panel(cfg: DictConfig, pipeline: Gaia1Pipeline, generator: torch.Generator) -> dict[str, Any]:
    """Generation from nothing: no prompt, then each prompt of `showcase.prompts`, `seconds` long. With
    `showcase.shared_noise` every rollout starts from the same generator state, so it draws the same sampling noise
    (tokens and decoder) and the rows differ by their prompt alone, as the command panel's futures differ by command."""
    frames = future_frames(cfg.seconds, pipeline.rate)
    prompts = list(cfg.showcase.prompts)
    texts = [None] + [pipeline.encode_text_batch([[prompt] * frames]) for prompt in prompts]
    start = generator.get_state()
    videos = []
    for text in texts:
        if cfg.showcase.shared_noise:
            generator.set_state(start)
        videos.append(rollout_frames(pipeline, None, frames, 1, text, None, generator))
    return {"futures": torch.cat(videos), "names": ["no prompt"] + prompts}


def entity(name: str) -> str:
    """A Rerun entity name from a label ("keep / left" → "keep_left", "It is night." → "It_is_night")."""
    return re.sub(r"[^A-Za-z0-9]+", "_", name).strip("_")


def log_showcase(path: Path, commands: dict[str, Any], prompts: dict[str, Any], fps: float) -> None:
    """Every video on the `frame` timeline (the world model's steps) and each command's speed and curvature as plots."""
    rec = rr.RecordingStream("gaia_app", recording_id=f"showcase-{path.parent.name}")
    rec.save(str(path))
    steered = commands["names"][len(REAL_ROWS):]
    rec.send_blueprint(showcase_blueprint([entity(n) for n in steered], [entity(n) for n in prompts["names"]]))
    videos = {f"commands/{name}": video for name, video in zip(REAL_ENTITIES, commands["real"])}
    videos |= {f"commands/{name}": video for name, video in zip(steered, commands["futures"])}
    videos |= {f"prompts/{name}": video for name, video in zip(prompts["names"], prompts["futures"])}
    for t in range(max(len(v) for v in videos.values())):
        rec.set_time("frame", sequence=t)
        rec.set_time("time", duration=t / fps)
        for name, video in videos.items():
            if t < len(video):
                panel, title = name.split("/", 1)
                rec.log(f"{panel}/{entity(title)}", rr.Image(to_hwc_uint8(video[t])))
        for name, actions in zip(steered, commands["actions"]):
            if t < len(actions):
                key = entity(name)
                rec.log(f"actions/speed/{key}", rr.Scalars(float(actions[t, 0])))
                rec.log(f"actions/curvature/{key}", rr.Scalars(float(actions[t, 1])))
    rec.flush()
    rec.disconnect()


def showcase(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Run both panels and write their files (module docstring); returns what was written."""
    pipeline = load_pipeline(cfg)
    generator = torch.Generator(device=pipeline.device).manual_seed(int(cfg.seed))
    commands = command_panel(cfg, pipeline, generator)
    prompts = prompt_panel(cfg, pipeline, generator)
    t0 = commands["context"]
    with staging(run_dir) as stage:
        files = write_panel(stage / "commands", marked(torch.cat([commands["real"], commands["futures"]]), t0),
                            commands["names"], pipeline.rate)
        files += write_panel(stage / "prompts", marked(prompts["futures"], 0), prompts["names"], pipeline.rate)
        log_showcase(stage / "showcase.rrd", commands, prompts, pipeline.rate)
    summary = {"context_frames": t0, "generated_frames": int(commands["futures"].shape[1]) - t0,
               "fps": pipeline.rate, "commands": commands["names"][len(REAL_ROWS):], "prompts": prompts["names"][1:],
               "commanded_actions": commands["actions"].tolist(), "files": files + ["showcase.rrd"]}
    atomic_write_text(run_dir / "showcase.md", markdown(summary))
    return summary


def markdown(summary: dict[str, Any]) -> str:
    lines = [f"# Showcase: {summary['context_frames']} context frames, {summary['generated_frames']} generated at "
             f"{summary['fps']:g} Hz", "", "| future | commanded speed (m/s) per step | curvature (1/m) |",
             "|---|---|---|"]
    for name, actions in zip(summary["commands"], summary["commanded_actions"]):
        future = actions[summary["context_frames"]:]
        lines.append(f"| {name} | {', '.join(f'{a[0]:.1f}' for a in future)} | {future[0][1]:+.3f} |")
    lines += ["", f"Prompts (from text alone): {', '.join(summary['prompts'])} against no prompt.",
              "Files: " + ", ".join(summary["files"])]
    return "\n".join(lines) + "\n"
