"""GAIA-2 end to end: a trained video tokenizer and latent world model, from clips to generated multi-camera video
(GAIA-2 report, inference).

Legend: b batch, v cameras, T frames, t latent steps (τ frames each), C h w latent channels and grid.

Conditions travel as the labels of a `LatentClip` (data/latent_cache.py): a user's commanded actions, prompt or
metadata edit the clip's labels (`with_labels`), and `window` turns any span of latent steps into scaled latents
and `WorldConditions` exactly as training saw them (data/latent_windows.latent_window).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lightning.fabric.utilities.apply_func import move_data_to_device

from gaia_app.data.clip import Clip, ClipError
from gaia_app.data.latent_cache import LatentClip
from gaia_app.data.latent_windows import collate_latent_windows, latent_window
from gaia_app.data.metadata import BUCKETS, VOCABULARIES, MetadataEncoder
from gaia_app.diffusion.flow_matching import FlowSampler
from gaia_app.models.gaia2.conditioning import WorldConditions, batch_conditions, batch_text_vector
from gaia_app.models.gaia2.latent_world_model import LatentWorldModel
from gaia_app.models.gaia2.video_tokenizer import VideoTokenizer
from gaia_app.pipelines.gaia2_edits import InpaintRegion, cut_steps
from gaia_app.pipelines.gaia2_video_tokenizer import VideoTokenizerPipeline
from gaia_app.pipelines.gaia2_world_model import Guidance, LatentWorldModelPipeline
from gaia_app.weights.folders import load_nets, shipped_folder
from gaia_app.weights.nets import checkpoint_nets


def check_metadata(overrides: Mapping[str, Any], fields: Sequence[str]) -> None:
    """Metadata overrides must name a field of the model and a value of its vocabulary (or a number for buckets)."""
    for name, value in overrides.items():
        if name not in fields:
            raise ValueError(f"model.metadata.{name}: the world model conditions on {list(fields)}")
        if name in BUCKETS:
            if not isinstance(value, (int, float)):
                raise ValueError(f"model.metadata.{name}={value!r}: expected a number")
        elif str(value) not in VOCABULARIES[name]:
            raise ValueError(f"model.metadata.{name}={value!r}: expected one of {list(VOCABULARIES[name])}")


def with_labels(clip: LatentClip, first_frame: int = 0, actions: np.ndarray | None = None, prompt: str | None = None,
                metadata: Mapping[str, Any] | None = None) -> LatentClip:
    """`clip` with its labels from frame `first_frame` on replaced: actions (n, 2) per frame (speed m/s, curvature 1/m),
    every caption by `prompt`, clip metadata fields by `metadata`. Nothing else changes."""
    frames = clip.mean.shape[1] * clip.temporal_downsampling
    out = replace(clip, meta={**clip.meta, **(metadata or {})})
    if actions is not None:
        if clip.actions is None:
            raise ClipError(f"latent clip '{clip.clip_id}' has no actions to command: its world model window "
                            "would mix labelled and unlabelled steps")
        if actions.shape != (frames - first_frame, 2):
            raise ValueError(f"commanded actions {actions.shape}: expected ({frames - first_frame}, 2), one per frame")
        out.actions = np.concatenate([clip.actions[:first_frame], actions]).astype(np.float32)
    if prompt is not None:
        out.text = list(clip.text or [None] * frames)[:first_frame] + [prompt] * (frames - first_frame)
    return out


GAIA2_MODES = ("scratch", "rollout", "inpaint", "edit")


@dataclass
class Gaia2Output:
    """What one GAIA-2 generation call returns.

    latents: (k, v, t, C, h, w) k samples in the world model's scaled units (`Gaia2Pipeline.decode` turns them into
    frames); clip: the latent clip whose labels conditioned them (cut to the t steps); first_generated_frame: the
    first frame not given (0 unless the call continues a context); seconds_per_sample: sampling wall time;
    evaluated_tokens: world-model token evaluations so far (the pipeline's counter).
    """

    latents: torch.Tensor
    clip: LatentClip
    first_generated_frame: int
    seconds_per_sample: float
    evaluated_tokens: int


class Gaia2Pipeline:
    """A GAIA-2 video tokenizer and latent world model with the solver and guidance of one run.

    Built from bare nets: training checkpoints (`from_checkpoints`) or a weights folder (`from_weights`, written by
    `generate.py model=gaia2 mode=export`); no LightningModule is built.

    Args:
        tokenizer: VideoTokenizer (encodes clips, decodes latents).
        world_model: LatentWorldModel.
        height, width: the tokenizer's input size (clips are resized and cropped to it).
        sampler, guidance: flow ODE solver and classifier-free guidance (pipelines/gaia2_world_model.py).
        fps: clips are resampled to this rate by timestamps before encoding (None: their own rate).
        text_encoder: the world model's caption encoder ([[caption]] per sample → (b, 1, m, e)), or None.
        latent_scale: the world model's scale of tokenizer latents (about 1 / their standard deviation).
    """

    def __init__(self, tokenizer: VideoTokenizer, world_model: LatentWorldModel, height: int, width: int,
                 sampler: FlowSampler | None = None, guidance: Guidance | None = None, resize_mode: str = "crop",
                 fps: float | None = None, text_encoder: torch.nn.Module | None = None, latent_scale: float = 1.0):
        self.tokenizer = tokenizer.eval()
        self.text_encoder = text_encoder
        self.encoder = VideoTokenizerPipeline(self.tokenizer, height, width, resize_mode, fps)
        self.world = LatentWorldModelPipeline(world_model.eval(), sampler, guidance)
        self.metadata = MetadataEncoder(list(world_model.conditioner.metadata_fields))
        self.scale = float(latent_scale)

    @classmethod
    def from_checkpoints(cls, tokenizer_ckpt: str | Path, world_model_ckpt: str | Path, height: int, width: int,
                         sampler: FlowSampler | None = None, guidance: Guidance | None = None, device: str = "cpu",
                         resize_mode: str = "crop", fps: float | None = None) -> Gaia2Pipeline:
        """From the training checkpoints of a video tokenizer and a latent world model (read weights-only)."""
        tokenizer = checkpoint_nets(tokenizer_ckpt, "video_tokenizer", "tokenizer_ckpt", device)[0]["net"]
        nets, config, _ = checkpoint_nets(world_model_ckpt, "latent_world_model", "world_model_ckpt", device)
        return cls(tokenizer, nets["net"], height, width, sampler, guidance, resize_mode, fps,
                   nets.get("text_encoder"), float(config.get("latent_scale", 1.0)))

    @classmethod
    def from_weights(cls, folder: str | Path, sampler: FlowSampler | None = None, guidance: Guidance | None = None,
                     device: str = "cpu", resize_mode: str = "crop", fps: float | None = None) -> Gaia2Pipeline:
        """From a weights folder (video_tokenizer.* and latent_world_model.*, safetensors + YAML); the input size
        and latent scale come from the folder's info."""
        folder = shipped_folder(folder)
        tokenizer, info = load_nets(folder, "video_tokenizer", device)
        world, world_info = load_nets(folder, "latent_world_model", device)
        height, width = (int(v) for v in info["image_size"])
        return cls(tokenizer["net"], world["net"], height, width, sampler, guidance, resize_mode, fps,
                   world.get("text_encoder"), float(world_info["latent_scale"]))

    @property
    def temporal(self) -> int:
        """Frames per latent step (τ)."""
        return self.tokenizer.temporal

    @property
    def device(self) -> torch.device:
        return self.encoder.device

    def encode(self, clip: Clip) -> LatentClip:
        """A multi-camera clip with its rig → its posterior and labels (whole latent steps)."""
        if clip.cameras is None:
            raise ClipError(f"clip '{clip.clip_id}' has no cameras (intrinsics/extrinsics): GAIA-2 needs the rig")
        return self.encoder.encode(clip)

    def window(self, clip: LatentClip, start: int, steps: int) -> tuple[torch.Tensor, WorldConditions]:
        """Latent steps start..start+steps-1 → scaled posterior means (1, v, t, C, h, w) and their conditions."""
        batch = collate_latent_windows([latent_window(clip, start, steps, self.metadata)])
        batch = move_data_to_device(batch, self.device)
        with torch.no_grad():
            cond = batch_conditions(batch, self.text_vector(batch))
        return batch["mean"] * self.scale, cond

    def text_vector(self, batch: dict[str, Any]) -> torch.Tensor | None:
        """(b, e) pooled caption features of a latent-window batch, or None without captions or text encoder."""
        return batch_text_vector(self.text_encoder, batch)

    @torch.no_grad()
    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        """Scaled latents (b, v, t, C, h, w) → frames (b, v, t·τ, 3, H, W) in [-1, 1]."""
        return self.tokenizer.decode(latents / self.scale).clamp(-1, 1)

    def decode_samples(self, latents: torch.Tensor) -> torch.Tensor:
        """Scaled latents (k, v, t, C, h, w) → frames (k, v, t·τ, 3, H, W), one sample at a time (bounded memory)."""
        return torch.cat([self.decode(x[None]) for x in latents])

    # one call per mode (GAIA-2 report, inference); `drop` removes whole conditions (e.g. ["action"]), the k samples
    # draw from one generator seeded by `seed`, one after the other

    def scratch(self, clip: LatentClip, steps: int, num_futures: int = 1, seed: int = 0,
                drop: Sequence[str] = ()) -> Gaia2Output:
        """`steps` latent steps from noise under the conditions of the clip's first `steps` steps."""
        real, cond = self.conditioned_window(clip, steps, drop)
        return self.sampled(clip, steps, 0, num_futures, seed,
                            lambda generator: self.world.from_scratch(tuple(real.shape), cond, generator))

    def rollout(self, clip: LatentClip, context_steps: int, steps: int, chunks: int, num_futures: int = 1,
                seed: int = 0, drop: Sequence[str] = ()) -> Gaia2Output:
        """`context_steps` clean steps of the clip, then `chunks` chunks of steps − context_steps new steps, each
        under the conditions of its own window of the clip, each continuing from the last generated steps."""
        if not 0 < context_steps < steps or chunks < 1:
            raise ValueError(f"rollout: context_steps={context_steps}, steps={steps}, chunks={chunks}: "
                             "need 0 < context_steps < steps and chunks ≥ 1")
        new = steps - context_steps
        total = context_steps + chunks * new
        self.check_length(clip, total)
        context, _ = self.window(clip, 0, context_steps)
        windows = [self.window(clip, j * new, steps)[1].without(*drop) for j in range(chunks)]
        return self.sampled(clip, total, context_steps * self.temporal, num_futures, seed,
                            lambda generator: self.world.rollout(context, windows, new, generator))

    def inpaint(self, clip: LatentClip, steps: int, region: InpaintRegion, num_futures: int = 1, seed: int = 0,
                drop: Sequence[str] = ()) -> Gaia2Output:
        """Regenerate `region` of the clip's first `steps` steps and keep the rest."""
        real, cond = self.conditioned_window(clip, steps, drop)
        mask = region.mask(clip, cond, tuple(real.shape), self.world.model.patch).to(real.device)
        return self.sampled(clip, steps, 0, num_futures, seed,
                            lambda generator: self.world.inpaint(real, mask, cond, generator))

    def edit(self, clip: LatentClip, steps: int, strength: float, num_futures: int = 1, seed: int = 0,
             drop: Sequence[str] = ()) -> Gaia2Output:
        """Noise the clip's first `steps` latent steps to 1 − strength and denoise them under its (edited)
        conditions (SDEdit-style)."""
        if not 0 < strength <= 1:
            raise ValueError(f"model.edit_strength={strength}: expected 0 < strength ≤ 1")
        real, cond = self.conditioned_window(clip, steps, drop)
        return self.sampled(clip, steps, 0, num_futures, seed,
                            lambda generator: self.world.edit(real, cond, strength, generator))

    def check_length(self, clip: LatentClip, steps: int) -> None:
        if steps < 1 or clip.mean.shape[1] < steps:
            raise ClipError(f"clip '{clip.clip_id}' has {clip.mean.shape[1]} latent steps "
                            f"({clip.mean.shape[1] * clip.temporal_downsampling} frames); the call needs {steps}")

    def conditioned_window(self, clip: LatentClip, steps: int,
                           drop: Sequence[str]) -> tuple[torch.Tensor, WorldConditions]:
        """The clip's first `steps` scaled latents (1, v, t, C, h, w) and their conditions without `drop`."""
        self.check_length(clip, steps)
        real, cond = self.window(clip, 0, steps)
        return real, cond.without(*drop)

    def sampled(self, clip: LatentClip, steps: int, first_generated: int, num_futures: int, seed: int,
                run: Callable[[torch.Generator], torch.Tensor]) -> Gaia2Output:
        """`num_futures` samples of `run`, one after the other from one generator seeded by `seed`."""
        if num_futures < 1:
            raise ValueError(f"num_futures={num_futures}: expected at least 1")
        generator = torch.Generator(device=self.device).manual_seed(int(seed))
        start = time.perf_counter()
        latents = torch.cat([run(generator) for _ in range(num_futures)])
        seconds = (time.perf_counter() - start) / num_futures
        return Gaia2Output(latents, clip_steps(clip, steps), first_generated, seconds, self.world.counter.tokens)


def clip_steps(clip: LatentClip, steps: int) -> LatentClip:
    """The clip cut to its first `steps` latent steps (unchanged when it has exactly that many)."""
    return clip if clip.mean.shape[1] == steps else cut_steps(clip, steps)
