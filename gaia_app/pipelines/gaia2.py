"""GAIA-2 end to end: a trained video tokenizer and latent world model, from clips to generated multi-camera video
(GAIA-2 report, inference).

Legend: b batch, v cameras, T frames, t latent steps (τ frames each), C h w latent channels and grid.

Conditions travel as the labels of a `LatentClip` (data/latent_cache.py): a user's commanded actions, prompt or
metadata edit the clip's labels (`with_labels`), and `window` turns any span of latent steps into scaled latents
and `WorldConditions` exactly as training saw them (data/latent_windows.latent_window).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
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
from gaia_app.lit.checkpoint import load_module
from gaia_app.lit.gaia2_video_tokenizer import VideoTokenizerModule
from gaia_app.lit.gaia2_world_model import LatentWorldModelModule, batch_conditions
from gaia_app.models.gaia2.conditioning import WorldConditions
from gaia_app.pipelines.gaia2_video_tokenizer import VideoTokenizerPipeline
from gaia_app.pipelines.gaia2_world_model import Guidance, LatentWorldModelPipeline


def load_checkpoint(path: str | Path, kind: type, key: str, device: str) -> Any:
    """The module in `path`, checked to be a `kind` (the error names the config key)."""
    module = load_module(path, map_location=device)
    if not isinstance(module, kind):
        raise TypeError(f"{key}={path} holds a {type(module).__name__}; GAIA-2 generation needs a {kind.__name__}")
    return module.eval()


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


class Gaia2Pipeline:
    """A GAIA-2 video tokenizer and latent world model with the solver and guidance of one run.

    Args:
        tokenizer: VideoTokenizerModule (encodes clips, decodes latents).
        world_model: LatentWorldModelModule (its `latent_scale` maps tokenizer latents to the model's).
        height, width: the tokenizer's input size (clips are resized and cropped to it).
        sampler, guidance: flow ODE solver and classifier-free guidance (pipelines/gaia2_world_model.py).
        fps: clips are resampled to this rate by timestamps before encoding (None: their own rate).
    """

    def __init__(self, tokenizer: VideoTokenizerModule, world_model: LatentWorldModelModule, height: int, width: int,
                 sampler: FlowSampler | None = None, guidance: Guidance | None = None, resize_mode: str = "crop",
                 fps: float | None = None):
        self.tokenizer = tokenizer.tokenizer.eval()
        self.module = world_model
        self.encoder = VideoTokenizerPipeline(self.tokenizer, height, width, resize_mode, fps)
        self.world = LatentWorldModelPipeline(world_model.model, sampler, guidance)
        self.metadata = MetadataEncoder(list(world_model.model.conditioner.metadata_fields))
        self.scale = float(world_model.latent_scale)

    @classmethod
    def from_checkpoints(cls, tokenizer_ckpt: str | Path, world_model_ckpt: str | Path, height: int, width: int,
                         sampler: FlowSampler | None = None, guidance: Guidance | None = None, device: str = "cpu",
                         resize_mode: str = "crop", fps: float | None = None) -> Gaia2Pipeline:
        tokenizer = load_checkpoint(tokenizer_ckpt, VideoTokenizerModule, "tokenizer_ckpt", device)
        world_model = load_checkpoint(world_model_ckpt, LatentWorldModelModule, "world_model_ckpt", device)
        return cls(tokenizer, world_model, height, width, sampler, guidance, resize_mode, fps)

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
            cond = batch_conditions(batch, self.module.text_vector(batch))
        return batch["mean"] * self.scale, cond

    @torch.no_grad()
    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        """Scaled latents (b, v, t, C, h, w) → frames (b, v, t·τ, 3, H, W) in [-1, 1]."""
        return self.tokenizer.decode(latents / self.scale).clamp(-1, 1)
