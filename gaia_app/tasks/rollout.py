"""`generate.py` rollout modes (GAIA-1 Fig. 1, §7): futures from the three GAIA-1 checkpoints.

Writes into the run dir: `future_<k>.mp4` per future, `grid.mp4` (the real clip, then every future, side by
side), `tokens.npy` (k, t, h, w), `conditioning.json` and `rollout.rrd`. Everything is written to a hidden
staging folder first and moved into place only when the whole rollout succeeded, so a failed run leaves
no partial outputs.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import torch
from omegaconf import DictConfig

from gaia_app.data.transforms import to_uint8
from gaia_app.data.video_io import write_video
from gaia_app.encoders.text import check_caption_fits
from gaia_app.pipelines.gaia1 import Gaia1Pipeline, Gaia1Rollout
from gaia_app.pipelines.gaia1_inputs import (
    ContextClip,
    build_conditioning,
    context_for,
    describe_actions,
    future_frames,
)
from gaia_app.protocols.loading import load_pipeline
from gaia_app.utils.run_dir import atomic_write_text
from gaia_app.viz.blueprints import rollout_blueprint
from gaia_app.viz.media import log_token_map, to_hwc_uint8, video_grid

CONTEXT_COLOUR, FUTURE_COLOUR = (40, 200, 80), (230, 60, 40)  # top stripe: context frame / generated frame


@contextmanager
def staging(run_dir: Path) -> Iterator[Path]:
    """A hidden folder whose files move into `run_dir` on success; removed, with its files, on error. A folder
    of an earlier run with the same name is replaced whole (os.replace cannot overwrite a non-empty folder)."""
    stage = run_dir / f".rollout-{uuid.uuid4().hex[:8]}"
    stage.mkdir(parents=True)
    try:
        yield stage
        for path in sorted(p for p in stage.iterdir() if not p.name.startswith(".replaced-")):
            target = run_dir / path.name
            if target.is_dir() and not target.is_symlink():
                os.replace(target, stage / f".replaced-{path.name}")  # removed with the stage below
            os.replace(path, target)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def mark(video: torch.Tensor, context_frames: int, upsample: int) -> np.ndarray:
    """(k, F, 3, H, W) → uint8 (k, F, 3, H, W) with a 2-pixel top stripe: green on context frames, red on generated."""
    out = to_uint8(video).numpy().copy()
    known = (context_frames - 1) * 2**upsample + 1 if context_frames else 0
    out[:, :known, :, :2] = np.array(CONTEXT_COLOUR, np.uint8)[:, None, None]
    out[:, known:, :, :2] = np.array(FUTURE_COLOUR, np.uint8)[:, None, None]
    return out


def real_cell(context: ContextClip | None, frames: int, fps: float, like: np.ndarray) -> np.ndarray:
    """The real clip at `fps` for the grid's first cell, (F, 3, H, W) uint8, holding its last frame past its end."""
    if context is None:
        return np.zeros_like(like)
    source = to_uint8(context.source).numpy()
    index = np.minimum(np.round(np.arange(frames) * context.source_fps / fps).astype(int), len(source) - 1)
    return source[index]


def write_videos(stage: Path, rollout: Gaia1Rollout, context: ContextClip | None, upsample: int) -> list[str]:
    """One mp4 per future and the grid mp4 (real clip first when there is one); returns the file names."""
    marked = mark(rollout.video, rollout.context_frames, upsample)
    names = []
    for k, video in enumerate(marked):
        names.append(f"future_{k}.mp4")
        write_video(stage / names[-1], video.transpose(0, 2, 3, 1), rollout.fps)
    cells = np.concatenate([real_cell(context, marked.shape[1], rollout.fps, marked[0])[None], marked])
    grid = video_grid(cells, ncols=len(cells), pad=2)
    write_video(stage / "grid.mp4", _even(grid.transpose(0, 2, 3, 1)), rollout.fps)
    return names + ["grid.mp4"]


def _even(frames: np.ndarray) -> np.ndarray:
    """Crop (t, h, w, 3) to even height and width (H.264 needs them)."""
    return frames[:, : frames.shape[1] // 2 * 2, : frames.shape[2] // 2 * 2]


def log_rollout(path: Path, rollout: Gaia1Rollout, context: ContextClip | None, conditions: dict[str, Any],
                codebook: torch.Tensor, guidance_scales: torch.Tensor | None, upsample: int) -> None:
    """Context vs generated frames on the `frame` timeline (output rate), token maps, actions, prompts,
    guidance scale and per-frame perplexity at the world model's steps."""
    rec = rr.RecordingStream("gaia_app", recording_id=f"rollout-{path.parent.name}")
    rec.save(str(path))
    rec.send_blueprint(rollout_blueprint(rollout.video.shape[0], context is not None,
                                         conditions.get("actions") is not None, guidance_scales is not None))
    step = 2**upsample
    real = real_cell(context, rollout.video.shape[1], rollout.fps, to_uint8(rollout.video[0]).numpy())
    for i in range(rollout.video.shape[1]):
        rec.set_time("frame", sequence=i)
        if context is not None:
            rec.log("/real", rr.Image(to_hwc_uint8(real[i], channels_first=True)))
        for k in range(rollout.video.shape[0]):
            rec.log(f"/future_{k}/video", rr.Image(to_hwc_uint8(rollout.video[k, i])))
    actions, captions = conditions.get("actions"), conditions.get("captions")
    for t in range(rollout.tokens.shape[1]):
        rec.set_time("frame", sequence=t * step)
        rec.log("/phase", rr.TextLog("context" if t < rollout.context_frames else "generated"))
        if actions is not None:
            rec.log("/actions/speed", rr.Scalars(float(actions[t][0])))
            rec.log("/actions/curvature", rr.Scalars(float(actions[t][1])))
        if captions is not None and captions[t] is not None:
            rec.log("/prompt", rr.TextLog(captions[t]))
        if guidance_scales is not None and t >= rollout.context_frames:
            rec.log("/guidance/scale", rr.Scalars(float(guidance_scales[t - rollout.context_frames].mean())))
        for k in range(rollout.tokens.shape[0]):
            log_token_map(rec, f"/future_{k}/tokens", rollout.tokens[k, t], codebook)
            if t >= rollout.context_frames:
                rec.log(f"/future_{k}/perplexity", rr.Scalars(math.exp(float(rollout.log_ppl[k, t]))))
    rec.flush()
    rec.disconnect()


def rollout(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Run one rollout of `cfg.mode` and write its outputs (module docstring); returns the results."""
    pipeline = load_pipeline(cfg)
    for setting in ("prompt", "negative_prompt"):
        check_caption_fits(pipeline.text_encoder, cfg.get(setting), setting)
    frames = future_frames(cfg.seconds, pipeline.rate)
    context = context_for(cfg.mode, cfg.context.source, cfg.context.seed, cfg.context.index, cfg.context.folder,
                          cfg.context.frames, frames, pipeline.rate, *pipeline.image_size)
    t0 = cfg.context.frames if context is not None else 0
    conditioning, commanded = build_conditioning(cfg.mode, context, t0, frames, pipeline.rate, cfg.prompt,
                                                 cfg.negative_prompt, cfg.speed, cfg.curvature)
    generator = torch.Generator(device=pipeline.device).manual_seed(int(cfg.seed))
    out = pipeline(None if context is None else context.frames[:t0], frames, conditioning, cfg.num_futures, generator)
    conditions = {"mode": cfg.mode,
                  "context": None if context is None else {"clip": context.name, "meta": context.meta},
                  "captions": None if conditioning.captions is None else list(conditioning.captions),
                  "negative_prompt": cfg.negative_prompt,
                  "actions": describe_actions(None if conditioning.actions is None else conditioning.actions.tolist()),
                  "commanded_actions": describe_actions(commanded),
                  "guidance": _guidance(pipeline, frames, conditioning.captions is not None)}
    scales = _guidance_scales(pipeline, frames, conditioning.captions is not None)
    with staging(run_dir) as stage:
        files = write_videos(stage, out, context, pipeline.upsample)
        np.save(stage / "tokens.npy", out.tokens.numpy())
        atomic_write_text(stage / "conditioning.json", json.dumps(conditions, indent=2, default=str))
        log_rollout(stage / "rollout.rrd", out, context, conditions, _codebook(pipeline), scales, pipeline.upsample)
    generated = out.log_ppl[:, t0:]
    return {"mode": cfg.mode, "futures": cfg.num_futures, "context_frames": t0, "generated_frames": frames,
            "video_frames": int(out.video.shape[1]), "fps": out.fps,
            "files": files + ["tokens.npy", "conditioning.json", "rollout.rrd"],
            "mean_frame_perplexity": float(generated.exp().mean())}


def _codebook(pipeline: Gaia1Pipeline) -> torch.Tensor:
    """(K, e) code vectors, for the PCA colouring of token maps."""
    return pipeline.tokenizer.code_vectors().cpu()


def _guidance_scales(pipeline: Gaia1Pipeline, frames: int, prompted: bool) -> torch.Tensor | None:
    """(f, n) scales of this rollout's generated tokens (text_scale when it is prompted with text)."""
    guidance = pipeline.rollouts.guidance
    return None if guidance is None else guidance.for_rollout(prompted).scales(frames, pipeline.world_model.n)


def _guidance(pipeline: Gaia1Pipeline, frames: int, prompted: bool) -> dict[str, Any] | None:
    scales = _guidance_scales(pipeline, frames, prompted)
    if scales is None:
        return None
    return {"config": repr(pipeline.rollouts.guidance),
            "per_frame_mean_scale": [round(float(s), 4) for s in scales.mean(1)]}


