"""`generate.py model=gaia2 mode=scratch|rollout|inpaint|edit`: multi-camera futures from a GAIA-2 video tokenizer and
latent world model (GAIA-2 report, inference; docs/latent_world_model.md).

The clip (context.source: a synthetic rig clip rendered by `data`, a clip folder, or a clip of a latent cache) gives
the cameras and every condition; the user's speed / curvature / prompt / model.metadata replace its labels on the
generated frames, model.add_agents adds boxes to its agents there (e.g. a car cut in ahead), model.drop removes
whole conditions.

    scratch   model.steps latent steps from noise under the clip's conditions
    rollout   model.context_steps clean steps of the clip, then model.chunks chunks of steps − context_steps new
              steps, each chunk under its own conditions, each continuing from the last generated steps
    inpaint   regenerate a region of the clip's first model.steps steps (model.inpaint: the agents' boxes or a
              box on some cameras), keep the rest
    edit      noise the clip's latents to 1 − model.edit_strength and denoise them under the (edited) conditions

Writes into the run dir (staged, so a failed run leaves nothing partial): sample_<k>.mp4 (cameras side by side,
leftmost first, a green / red top stripe on given / generated frames), grid.mp4 (the tokenized real clip, then every
sample), latents.npy (k, v, t, C, h, w) in the tokenizer's units, conditioning.json and rollout.rrd (a tab per clip:
camera grid with the conditioning boxes, 3D frusta and agent boxes, actions and captions on `frame`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from gaia_app.data.clip import AGENT_CATEGORIES, Clip, ClipError
from gaia_app.data.collate import pad_agents
from gaia_app.data.latent_cache import LatentClip, find_latent_clips, read_latent_clip
from gaia_app.data.transforms import to_uint8
from gaia_app.data.video_io import write_video
from gaia_app.models.gaia2.conditioning import AgentBoxes3d, project_boxes
from gaia_app.pipelines.gaia1_inputs import folder_clip, future_actions
from gaia_app.pipelines.gaia2 import Gaia2Output, Gaia2Pipeline, check_metadata, with_labels
from gaia_app.pipelines.gaia2_edits import InpaintRegion, cut_steps, with_added_agents
from gaia_app.tasks.rollout import CONTEXT_COLOUR, FUTURE_COLOUR, staging
from gaia_app.utils.run_dir import atomic_write_text
from gaia_app.viz.blueprints import rig_tabs_blueprint
from gaia_app.viz.media import video_grid
from gaia_app.viz.world import log_world


def load_gaia2(cfg: DictConfig) -> Gaia2Pipeline:
    """The GAIA-2 nets of `cfg` (a weights folder, or the two training checkpoints) with its solver and guidance."""
    g = cfg.model
    solver = (instantiate(g.sampler), instantiate(g.guidance))
    resize_mode = cfg.data.get("resize_mode", "crop")
    if cfg.get("weights"):
        given = [key for key in ("tokenizer_ckpt", "world_model_ckpt") if cfg.get(key)]
        if given:
            raise ValueError(f"weights={cfg.weights} replaces {', '.join(given)}; give one or the other")
        pipeline = Gaia2Pipeline.from_weights(cfg.weights, *solver, cfg.device, resize_mode, cfg.fps)
        size = (pipeline.encoder.height, pipeline.encoder.width)
        if size != (cfg.data.height, cfg.data.width):
            raise ValueError(f"weights={cfg.weights}: its video tokenizer was trained on {size} frames, but "
                             f"data.height × data.width is {(cfg.data.height, cfg.data.width)}; set them to match")
        return pipeline
    for key in ("tokenizer_ckpt", "world_model_ckpt"):
        if not cfg.get(key):
            raise ValueError(f"model=gaia2 mode={cfg.mode} needs {key}=<checkpoint of a GAIA-2 "
                             f"{'video tokenizer' if key == 'tokenizer_ckpt' else 'latent world model'}> "
                             "(or weights=<folder written by model=gaia2 mode=export>)")
    return Gaia2Pipeline.from_checkpoints(cfg.tokenizer_ckpt, cfg.world_model_ckpt, cfg.data.height, cfg.data.width,
                                          *solver, cfg.device, resize_mode, cfg.fps)


def latent_steps(cfg: DictConfig) -> int:
    """Latent steps of the clip that the mode uses."""
    g = cfg.model
    if g.steps < 1 or not 0 < g.context_steps < g.steps:
        raise ValueError(f"model.steps={g.steps}, model.context_steps={g.context_steps}: "
                         "need 0 < context_steps < steps")
    if cfg.mode == "rollout":
        if g.chunks < 1:
            raise ValueError(f"model.chunks={g.chunks}: expected at least 1")
        return g.context_steps + g.chunks * (g.steps - g.context_steps)
    return g.steps


def source_clip(cfg: DictConfig, pipeline: Gaia2Pipeline, steps: int) -> LatentClip:
    """The clip of `cfg.context`, encoded, with at least `steps` latent steps."""
    c, frames = cfg.context, steps * pipeline.temporal
    if c.source == "latents":
        if not c.folder:
            raise ValueError("context.source=latents needs context.folder=<a latent cache split or clip folder>")
        folders = [Path(c.folder)] if (Path(c.folder) / "mean.npy").is_file() else find_latent_clips(c.folder)
        if not 0 <= c.index < len(folders):
            raise ClipError(f"context.index={c.index}: {c.folder} holds {len(folders)} latent clips")
        clip = read_latent_clip(folders[c.index])
    elif c.source == "synthetic":
        if "source" not in cfg.data or "cameras" not in cfg.data.source:
            raise ValueError("context.source=synthetic with model=gaia2 renders the rig of `data`: "
                             "use data=synthetic_rig")
        world = instantiate(cfg.data.source, num_clips=c.index + 1, seed=c.seed, clip_len=frames)
        clip = pipeline.encode(world[c.index])
    elif c.source == "folder":
        if not c.folder:
            raise ValueError("context.source=folder needs context.folder=<a clip folder or a root of them>")
        clip = pipeline.encode(folder_clip(c.folder, c.index))
    else:
        raise ValueError(f"context.source={c.source!r}: expected synthetic, folder or latents")
    if clip.mean.shape[1] < steps:
        raise ClipError(f"clip '{clip.clip_id}' has {clip.mean.shape[1]} latent steps "
                        f"({clip.mean.shape[1] * clip.temporal_downsampling} frames); mode={cfg.mode} needs {steps}")
    return cut_steps(clip, steps)


def commanded(cfg: DictConfig, clip: LatentClip, first_frame: int, fields: list[str]) -> LatentClip:
    """The clip with the user's actions, prompt and metadata on frames first_frame.. (absent settings: the clip's own).
    fields: the metadata fields of the world model."""
    metadata = OmegaConf.to_container(cfg.model.metadata) if cfg.model.metadata else {}
    check_metadata(metadata, fields)
    actions = None
    if cfg.speed is not None or cfg.curvature is not None:
        if clip.actions is None:
            raise ClipError(f"clip '{clip.clip_id}' has no actions; speed= / curvature= replace existing ones")
        n = clip.timestamps.shape[0] - first_frame
        start_speed = float(clip.actions[max(first_frame - 1, 0), 0])
        actions = future_actions(_plain(cfg.speed), _plain(cfg.curvature), n, clip.fps, start_speed)
    return with_labels(clip, first_frame, actions, cfg.prompt, metadata)


def _plain(value: Any) -> Any:
    return OmegaConf.to_container(value) if OmegaConf.is_config(value) else value


def first_generated_frame(cfg: DictConfig, pipeline: Gaia2Pipeline) -> int:
    """The first frame the mode generates: after the clean context steps of a rollout, else 0."""
    return cfg.model.context_steps * pipeline.temporal if cfg.mode == "rollout" else 0


def conditioned_clip(cfg: DictConfig, pipeline: Gaia2Pipeline) -> LatentClip:
    """The clip of `cfg.context` with the user's commands (speed, curvature, prompt, model.metadata) and
    model.add_agents on the generated frames."""
    first = first_generated_frame(cfg, pipeline)
    clip = commanded(cfg, source_clip(cfg, pipeline, latent_steps(cfg)), first, pipeline.metadata.fields)
    return with_added_agents(clip, _plain(cfg.model.add_agents) or [], first)


def inpaint_region(cfg: DictConfig) -> InpaintRegion:
    """model.inpaint as an InpaintRegion."""
    spec = cfg.model.inpaint
    cameras = None if spec.cameras is None else tuple(str(name) for name in spec.cameras)
    return InpaintRegion(str(spec.region), tuple(float(x) for x in spec.box), cameras)


def sample(cfg: DictConfig, pipeline: Gaia2Pipeline, clip: LatentClip) -> Gaia2Output:
    """cfg.num_futures samples of cfg.mode from `clip` (the pipeline call of the mode)."""
    g = cfg.model
    shared = {"num_futures": cfg.num_futures, "seed": int(cfg.seed), "drop": list(g.drop)}
    if cfg.mode == "rollout":
        return pipeline.rollout(clip, g.context_steps, g.steps, g.chunks, **shared)
    if cfg.mode == "scratch":
        return pipeline.scratch(clip, g.steps, **shared)
    if cfg.mode == "inpaint":
        return pipeline.inpaint(clip, g.steps, inpaint_region(cfg), **shared)
    return pipeline.edit(clip, g.steps, g.edit_strength, **shared)


def pixel_boxes(clip: LatentClip) -> list[dict[str, Any]]:
    """Per frame, the conditioning agents projected into every camera: {"boxes_2d": {camera: [{box (x0, y0, x1, y1)
    pixels, category, track_id}]}} (viz/world.py draws them over the views)."""
    frames = clip.timestamps.shape[0]
    if clip.agents is None or clip.cameras is None:
        return [{} for _ in range(frames)]
    padded = pad_agents([clip.agents])
    agents = AgentBoxes3d(padded["agents_centre"], padded["agents_size"], padded["agents_yaw"],
                          padded["agents_category"], padded["agents_mask"])
    intrinsics = torch.tensor(np.stack([c.intrinsics for c in clip.cameras]), dtype=torch.float32)[None]
    extrinsics = torch.tensor(np.stack([c.extrinsics for c in clip.cameras]), dtype=torch.float32)[None]
    boxes, _, visible = project_boxes(agents, intrinsics, extrinsics, clip.image_size)  # (1, T, v, N, 4)
    scale = torch.tensor([clip.image_size[1], clip.image_size[0]] * 2, dtype=torch.float32)
    out = []
    for t in range(frames):
        per_camera = {}
        for v, cam in enumerate(clip.cameras):
            keep = torch.nonzero(visible[0, t, v]).flatten().tolist()
            per_camera[cam.name] = [{"box": (boxes[0, t, v, n] * scale).tolist(),
                                     "category": AGENT_CATEGORIES[int(padded["agents_category"][0, t, n])],
                                     "track_id": int(padded["agents_track_id"][0, t, n])} for n in keep]
        out.append({"boxes_2d": per_camera})
    return out


def display_clip(clip: LatentClip, video: torch.Tensor, name: str, boxes: list[dict[str, Any]]) -> Clip:
    """Decoded frames (v, T, 3, H, W) in [-1, 1] with the labels that conditioned them, as a Clip for log_world
    (no logged ego pose: the path is integrated from the conditioning actions)."""
    return Clip(clip_id=name, frames=to_uint8(video.cpu()).numpy(), timestamps=clip.timestamps, actions=clip.actions,
                text=clip.text, agents=clip.agents, cameras=clip.cameras, meta=dict(clip.meta), frame_meta=boxes)


def left_to_right(clip: LatentClip) -> list[int]:
    """Camera indices ordered by where they look, leftmost first (yaw of the optical axis in the ego frame, z up),
    so side-by-side views read like the scene."""
    yaws = [math.atan2(float(c.extrinsics[1, 2]), float(c.extrinsics[0, 2])) for c in clip.cameras]
    return sorted(range(len(yaws)), key=lambda i: -yaws[i])


def stripe(video: np.ndarray, first_generated: int) -> np.ndarray:
    """(v, T, 3, H, W) uint8 → cameras side by side (T, H, v·W, 3) with a 2-pixel top stripe: green on given frames,
    red on generated ones."""
    out = video.copy()
    out[:, :first_generated, :, :2] = np.array(CONTEXT_COLOUR, np.uint8)[:, None, None]
    out[:, first_generated:, :, :2] = np.array(FUTURE_COLOUR, np.uint8)[:, None, None]
    return np.concatenate(list(out), axis=-1).transpose(0, 2, 3, 1)


def write_outputs(stage: Path, cfg: DictConfig, clip: LatentClip, real: torch.Tensor, samples: torch.Tensor,
                  first_generated: int) -> list[str]:
    """mp4s and rollout.rrd of the decoded real clip (v, T, 3, H, W) and samples (k, v, T, 3, H, W)."""
    fps = clip.fps or 12.5
    order = left_to_right(clip)
    rows = [to_uint8(real.cpu()).numpy()[order]] + [to_uint8(s.cpu()).numpy()[order] for s in samples]
    names = []
    for k, video in enumerate(rows[1:]):
        names.append(f"sample_{k}.mp4")
        write_video(stage / names[-1], _even(stripe(video, first_generated)), fps)
    cells = np.stack([stripe(video, first_generated if k else video.shape[1]).transpose(0, 3, 1, 2)
                      for k, video in enumerate(rows)])
    write_video(stage / "grid.mp4", _even(video_grid(cells, ncols=1, pad=2).transpose(0, 2, 3, 1)), fps)
    log_generation(stage / "rollout.rrd", cfg, clip, real, samples, first_generated)
    return names + ["grid.mp4", "rollout.rrd"]


def log_generation(path: Path, cfg: DictConfig, clip: LatentClip, real: torch.Tensor, samples: torch.Tensor,
                   first_generated: int) -> None:
    """A tab per clip (tokenized real clip, each sample): camera grid with the conditioning boxes, 3D frusta and
    agent boxes, actions, captions, phase and metadata on the `frame` timeline."""
    rec = rr.RecordingStream("gaia_app", recording_id=f"gaia2-{path.parent.name}")
    rec.save(str(path))
    roots = ["/real"] + [f"/sample_{k}" for k in range(len(samples))]
    rec.send_blueprint(rig_tabs_blueprint([clip.cameras[i].name for i in left_to_right(clip)], roots))
    boxes = pixel_boxes(clip)
    metadata = ", ".join(f"{k}={v}" for k, v in sorted(clip.meta.items()) if isinstance(v, (str, int, float, bool)))
    for root, video in zip(roots, [real, *samples]):
        log_world(rec, display_clip(clip, video, root.strip("/"), boxes), root=root, send_blueprint=False,
                  series_root=root)
        for t in range(video.shape[1]):
            rec.set_time("frame", sequence=t)
            if t == 0:
                rec.log(f"{root}/text", rr.TextLog(f"metadata: {metadata}"))
            if t in (0, first_generated) and root != "/real":
                rec.log(f"{root}/text", rr.TextLog("given" if t < first_generated else "generated",
                                                   level=rr.TextLogLevel.INFO))
        rec.disable_timeline("frame")
    rec.flush()
    rec.disconnect()


def _even(frames: np.ndarray) -> np.ndarray:
    """Crop (t, h, w, 3) to even height and width (H.264 needs them)."""
    return frames[:, : frames.shape[1] // 2 * 2, : frames.shape[2] // 2 * 2]


def describe(cfg: DictConfig, clip: LatentClip, pipeline: Gaia2Pipeline, first_generated: int) -> dict[str, Any]:
    """conditioning.json: the clip, the conditions the samples were generated under, solver and guidance."""
    g = cfg.model
    fields = pipeline.metadata.fields
    return {"model": "gaia2", "mode": cfg.mode, "clip": clip.clip_id, "context": OmegaConf.to_container(cfg.context),
            "cameras": [c.name for c in clip.cameras], "latent_steps": int(clip.mean.shape[1]),
            "frames": int(clip.timestamps.shape[0]), "fps": clip.fps, "first_generated_frame": first_generated,
            "metadata": {k: clip.meta.get(k) for k in fields}, "prompt": cfg.prompt,
            "actions": None if clip.actions is None else np.round(clip.actions, 4).tolist(),
            "commanded": {"speed": _plain(cfg.speed), "curvature": _plain(cfg.curvature)},
            "dropped": list(g.drop), "added_agents": _plain(g.add_agents), "sampler": OmegaConf.to_container(g.sampler),
            "guidance": OmegaConf.to_container(g.guidance),
            **({"inpaint": OmegaConf.to_container(g.inpaint)} if cfg.mode == "inpaint" else {}),
            **({"edit_strength": g.edit_strength} if cfg.mode == "edit" else {})}


def gaia2_generate(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Run cfg.mode with the GAIA-2 checkpoints and write its outputs (module docstring); returns the results."""
    pipeline = load_gaia2(cfg)
    out = sample(cfg, pipeline, conditioned_clip(cfg, pipeline))
    clip, first_generated = out.clip, out.first_generated_frame
    real = pipeline.decode(pipeline.window(clip, 0, clip.mean.shape[1])[0])[0]
    samples = pipeline.decode_samples(out.latents)
    with staging(run_dir) as stage:
        files = write_outputs(stage, cfg, clip, real, samples, first_generated)
        np.save(stage / "latents.npy", (out.latents / pipeline.scale).cpu().numpy().astype(np.float16))
        atomic_write_text(stage / "conditioning.json",
                          json.dumps(describe(cfg, clip, pipeline, first_generated), indent=2, default=str))
    return {"model": "gaia2", "mode": cfg.mode, "clip": clip.clip_id, "samples": cfg.num_futures,
            "latent_steps": int(clip.mean.shape[1]), "frames": int(samples.shape[2]), "cameras": int(samples.shape[1]),
            "fps": clip.fps, "first_generated_frame": first_generated,
            "seconds_per_sample": round(out.seconds_per_sample, 3), "evaluated_tokens": out.evaluated_tokens,
            "files": files + ["latents.npy", "conditioning.json"]}
