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
from omegaconf import DictConfig, OmegaConf

from gaia_app.data.clip import AGENT_CATEGORIES, Clip
from gaia_app.data.collate import pad_agents
from gaia_app.data.latent_cache import LatentClip
from gaia_app.data.transforms import to_uint8
from gaia_app.data.video_io import write_video
from gaia_app.models.gaia2.conditioning import AgentBoxes3d, project_boxes
from gaia_app.pipelines.gaia2 import Gaia2Pipeline
from gaia_app.protocols.gaia2_context import conditioned_clip, plain, sample
from gaia_app.protocols.loading import load_gaia2
from gaia_app.tasks.rollout import CONTEXT_COLOUR, FUTURE_COLOUR, staging
from gaia_app.utils.run_dir import atomic_write_text
from gaia_app.viz.blueprints import rig_tabs_blueprint
from gaia_app.viz.media import video_grid
from gaia_app.viz.world import log_world


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
            "commanded": {"speed": plain(cfg.speed), "curvature": plain(cfg.curvature)},
            "dropped": list(g.drop), "added_agents": plain(g.add_agents), "sampler": OmegaConf.to_container(g.sampler),
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
