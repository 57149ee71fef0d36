"""GAIA-1 end to end (GAIA-1 Fig. 1, §5): context video → tokens → world-model futures → video.

Legend:
    k futures, t0 context frames, f generated frames, t = t0 + f, all at the world model's rate
    (6.25 Hz in GAIA-1, §2.3); h × w token grid, n = h·w; H × W images in [-1, 1].

The three trained components stay separate checkpoints (tokenizer, world model, video decoder);
`Gaia1Pipeline.from_checkpoints` loads them, checks they agree on the token layout, and the pipeline
then runs every rollout mode of GAIA-1 §7: with or without video context, with text, actions, both or
neither, guided by classifier-free guidance or a negative prompt, several futures in one batch.
Without a video decoder each frame is decoded on its own by the tokenizer, at the world model's rate.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from einops import rearrange

from gaia_app.diffusion.ar_sampling import AutoregressiveSampler
from gaia_app.diffusion.guidance import ClassifierFreeGuidance
from gaia_app.diffusion.noise_schedule import CosineNoiseSchedule
from gaia_app.diffusion.samplers import DDIMSampler, ImageVideoBlend, OneStepMeanSampler
from gaia_app.eval.token_perplexity import fit_window, token_log_perplexity
from gaia_app.models.gaia1.world_model import STREAMS, Conditions, WorldModel
from gaia_app.models.tokenizer_protocol import DiscreteTokenizer
from gaia_app.pipelines.gaia1_video_decoder import VideoDecodingPipeline
from gaia_app.pipelines.gaia1_world_model import WorldModelRolloutPipeline

Captions = Sequence[str | None]


@dataclass
class Conditioning:
    """What one rollout is conditioned on, step by step over all t = t0 + f steps.

    captions: t captions (None where a step has none) or None (no text); actions: (t, 2) speed (m/s) and
    curvature (1/m), or None; negative: t captions of a negative prompt (GAIA-1 §5.1) or None.
    """

    captions: Captions | None = None
    actions: torch.Tensor | None = None
    negative: Captions | None = None

    def check(self, steps: int) -> None:
        """Every given stream must cover exactly `steps` steps; the message names the stream."""
        for name, value in (("captions", self.captions), ("negative", self.negative)):
            if value is not None and len(value) != steps:
                raise ValueError(f"conditioning.{name}: {len(value)} captions for {steps} steps (context + future)")
        if self.actions is not None and tuple(self.actions.shape) != (steps, 2):
            raise ValueError(f"conditioning.actions: shape {tuple(self.actions.shape)}, expected ({steps}, 2) "
                             "(speed, curvature per context + future step)")


@dataclass
class Gaia1Rollout:
    """tokens (k, t, h, w) int64; frames (k, t, 3, H, W) at the world model's rate; video (k, F, 3, H, W) at
    `fps` (F = 4t − 3 at 25 Hz after two decoder doublings, else F = t); log_ppl (k, t) mean nats per token of
    each frame under the world model (NaN for context frames); context_frames: t0."""

    tokens: torch.Tensor
    frames: torch.Tensor
    video: torch.Tensor
    fps: float
    log_ppl: torch.Tensor
    context_frames: int


class Gaia1Pipeline:
    """Tokenizer + world model + (optional) video decoder: rollouts from context frames and conditions.

    Args:
        tokenizer: the trained image tokenizer (encodes context frames; frame-by-frame decoding).
        world_model: the trained world model. text_encoder: captions → (b, t, m, e), or None.
        sampler: the token sampler (top-k by default, GAIA-1 §5.1). guidance: eq. 3 guidance or None.
        decoder: the video decoding pipeline (§5.2) or None. upsample: decoder frame-rate doublings (0-2).
        image_size: (H, W) of the tokenizer's images. rate: the world model's frame rate in Hz.
    """

    def __init__(self, tokenizer: DiscreteTokenizer, world_model: WorldModel, image_size: tuple[int, int],
                 text_encoder: Callable | None = None, sampler: AutoregressiveSampler | None = None,
                 guidance: ClassifierFreeGuidance | None = None, decoder: VideoDecodingPipeline | None = None,
                 upsample: int = 2, rate: float = 6.25):
        self.tokenizer, self.world_model, self.text_encoder = tokenizer, world_model, text_encoder
        self.decoder, self.upsample, self.rate = decoder, upsample if decoder is not None else 0, rate
        self.image_size = tuple(image_size)
        self.token_grid = tuple(s // tokenizer.downsampling for s in self.image_size)
        self.rollouts = WorldModelRolloutPipeline(world_model, sampler or AutoregressiveSampler(), guidance, STREAMS)
        self.check_layout()

    @classmethod
    def from_checkpoints(cls, tokenizer: str | Path, world_model: str | Path, decoder: str | Path | None = None,
                         image_size: tuple[int, int] | None = None, device: str = "cpu",
                         decoder_steps: int | None = None, decoder_blend: ImageVideoBlend | None = None,
                         decoder_sampler: str | None = None, **kwargs) -> Gaia1Pipeline:
        """Load the three components' nets (weights/nets.py: weights-only, checked configs, no
        LightningModule); `image_size` defaults to the decoder's (required without one).

        decoder_steps: steps of the decoder run's own sampler (DDIM, §5.2: 50), None for its default.
        decoder_blend: eq. 4 image/video blend of the decoder's steps (§5.2: p = 0.25, w = 0.5), None for none.
        decoder_sampler: "ddim" (the decoder run's own sampler, DDIM in every preset; also for None) or
            "one_step_mean" (the conditional mean over decoder_steps noise draws, the fast option;
            `make_decoder_sampler`) or "antithetic_mean" (that mean over pairs of opposite draws).
        kwargs: the constructor's sampler, guidance, upsample and rate.
        """
        from gaia_app.weights.nets import checkpoint_nets

        tok = checkpoint_nets(tokenizer, "tokenizer", "tokenizer_ckpt", device)[0]["net"]
        wm = checkpoint_nets(world_model, "world_model", "world_model_ckpt", device)[0]
        video = None
        if decoder is not None:
            nets, config, _ = checkpoint_nets(decoder, "video_decoder", "decoder_ckpt", device)
            net = nets["net"]
            image_size = image_size or tuple(net.image_size)
            video = VideoDecodingPipeline(net, *decoder_sampling(config, decoder_steps, decoder_sampler or "ddim"),
                                          blend=decoder_blend, progress=True,
                                          render_tokens=_renderer(tok) if net.render_tokens else None)
        if image_size is None:
            raise ValueError("image_size=(H, W) is needed when no decoder checkpoint gives it")
        return cls(tok, wm["net"], image_size, wm.get("text_encoder"), decoder=video, **kwargs)

    @classmethod
    def from_weights(cls, folder: str | Path, device: str = "cpu", video_decoder: bool = True,
                     decoder_steps: int | None = None, decoder_blend: ImageVideoBlend | None = None, upsample: int = 2,
                     decoder_sampler: str | None = None, **kwargs) -> Gaia1Pipeline:
        """Tokenizer and world model from a shipped weights folder (gaia_app/weights/folders.py), e.g.
        gaia_app/weights/gaia1, and its video decoder when it has one and `video_decoder` (else frames are decoded
        one by one by the tokenizer at the world model's rate). decoder_sampler, decoder_steps: None for the setting
        the decoder was exported with (video_decoder.yaml info.sampler, info.steps); decoder_blend, upsample: as in
        from_checkpoints. kwargs: sampler, guidance."""
        from gaia_app.weights.folders import load_nets, weight_files

        tokenizer, tokenizer_info = load_nets(folder, "tokenizer", device)
        world_model, world_info = load_nets(folder, "world_model", device)
        if "image_size" not in tokenizer_info or "rate" not in world_info:
            raise ValueError(f"{folder}: tokenizer.yaml needs info.image_size and world_model.yaml info.rate")
        video = None
        if video_decoder and weight_files(folder, "video_decoder")[0].exists():
            nets, info = load_nets(folder, "video_decoder", device)
            schedule = CosineNoiseSchedule(int(info["timesteps"]))
            sampler = make_decoder_sampler(decoder_sampler or str(info.get("sampler", "ddim")), schedule,
                                           decoder_steps or int(info["steps"]))
            video = VideoDecodingPipeline(nets["net"], schedule, sampler, int(info["frames"]),
                                          int(info["context_frames"]), blend=decoder_blend, progress=True,
                                          render_tokens=(_renderer(tokenizer["net"]) if nets["net"].render_tokens
                                                         else None))
        return cls(tokenizer["net"], world_model["net"], tuple(tokenizer_info["image_size"]),
                   world_model.get("text_encoder"), decoder=video, upsample=upsample, rate=float(world_info["rate"]),
                   **kwargs)

    def check_layout(self) -> None:
        """Tokenizer, world model and decoder must agree on the token grid and the vocabulary."""
        h, w = self.token_grid
        if self.world_model.n != h * w or self.world_model.vocab_size != self.tokenizer.codebook_size:
            raise ValueError(f"world model expects {self.world_model.n} tokens per frame "
                             f"from {self.world_model.vocab_size} "
                             f"codes; the tokenizer makes {h}×{w} = {h * w} at {self.image_size} from "
                             f"{self.tokenizer.codebook_size} codes")
        if self.decoder is not None:
            net = self.decoder.net
            if tuple(net.token_grid) != (h, w) or tuple(net.image_size) != self.image_size:
                raise ValueError(f"video decoder works on {tuple(net.token_grid)} tokens at {tuple(net.image_size)}; "
                                 f"the tokenizer makes {(h, w)} at {self.image_size}")

    @property
    def device(self) -> torch.device:
        return next(self.world_model.parameters()).device

    @property
    def fps(self) -> float:
        return self.rate * 2**self.upsample

    # ---- stages -------------------------------------------------------------------------------------

    @torch.no_grad()
    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        """Context frames (t0, 3, H, W) in [-1, 1] → tokens (t0, h, w)."""
        if tuple(frames.shape[-2:]) != self.image_size or frames.ndim != 4:
            raise ValueError(f"context frames: expected (t0, 3, {self.image_size[0]}, {self.image_size[1]}), "
                             f"got {tuple(frames.shape)}")
        return self.tokenizer.encode(frames.to(self.device))

    def encode_text(self, captions: Captions | None, futures: int) -> torch.Tensor | None:
        """t captions → (k, t, m, e) text features (the same for every future), or None."""
        return None if captions is None else self.encode_text_batch([captions] * futures)

    def encode_text_batch(self, captions: Sequence[Captions]) -> torch.Tensor:
        """b lists of t captions → (b, t, m, e) text features."""
        if self.text_encoder is None:
            raise ValueError("a text prompt was given but this world model was trained without a text encoder")
        return self.text_encoder([list(c) for c in captions]).to(self.device)

    @torch.no_grad()
    def sample_tokens(self, context: torch.Tensor, frames: int, conditioning: Conditioning, num_futures: int,
                      generator: torch.Generator | None = None) -> tuple[torch.Tensor, Conditions]:
        """context (t0, h, w) → tokens (k, t0 + f, h, w) and the conditions they were sampled with."""
        conditioning.check(context.shape[0] + frames)
        text = self.encode_text(conditioning.captions, 1)
        negative = self.encode_text(conditioning.negative, 1)
        actions = None if conditioning.actions is None else conditioning.actions[None]
        return self.sample_batch(context[None], frames, text, actions, negative, num_futures, generator)

    @torch.no_grad()
    def sample_batch(self, context: torch.Tensor, frames: int, text: torch.Tensor | None = None,
                     actions: torch.Tensor | None = None, negative: torch.Tensor | None = None, num_futures: int = 1,
                     generator: torch.Generator | None = None, lead: int = 0,
                     noise_groups: torch.Tensor | None = None) -> tuple[torch.Tensor, Conditions]:
        """b contexts at once: tokens (b, t0, h, w); text, negative (b, lead + t, m, e) encoded; actions
        (b, lead + t, 2) → tokens (b·k, t, h, w), each context's futures adjacent, and their conditions (t steps).
        lead: steps of the streams before the context that only inform the conditions; noise_groups (b,) int64:
        rows that share their sampling noise, e.g. one context under several commands (WorldModelRolloutPipeline)."""
        steps = lead + context.shape[1] + frames
        actions = None if actions is None else actions.float().to(self.device)
        flat = rearrange(context, "b t h w -> b t (h w)").to(self.device)
        groups = None if noise_groups is None else noise_groups.to(self.device)
        out = self.rollouts(flat, frames, text, actions, negative, num_futures, generator, lead, groups)
        cond = self.rollouts.conditions(out.tokens.shape[0], steps, *(
            None if x is None else x.repeat_interleave(num_futures, 0) for x in (text, actions))).steps(lead, steps)
        h, w = self.token_grid
        return rearrange(out.tokens, "k t (h w) -> k t h w", h=h, w=w), cond

    @torch.no_grad()
    def frame_log_perplexity(self, tokens: torch.Tensor, cond: Conditions, context_frames: int) -> torch.Tensor:
        """(k, t) mean nats/token of each generated frame given its window (NaN for context frames)."""
        flat = rearrange(tokens, "k t h w -> k t (h w)")
        out = torch.full(flat.shape[:2], math.nan)
        if flat.shape[1] <= self.world_model.frames:  # one window: one causal forward scores every frame alike
            logits = self.world_model(flat, cond.steps(0, flat.shape[1])).float()  # (k, t, n, V)
            nats = -logits.log_softmax(-1).gather(-1, flat[..., None])[..., 0]
            out[:, context_frames:] = nats[:, context_frames:].mean(-1).cpu()
            return out
        for t in range(context_frames, flat.shape[1]):
            context, window = fit_window(self.world_model, flat[:, :t], cond.steps(0, t + 1))
            out[:, t] = token_log_perplexity(self.world_model, context, flat[:, t], window).mean(-1).cpu()
        return out

    def tokenizer_frames(self, tokens: torch.Tensor) -> torch.Tensor:
        """tokens (k, t, h, w) → the tokenizer's frame-by-frame decoding (k, t, 3, H, W) in [-1, 1], on the CPU."""
        return _renderer(self.tokenizer)(tokens.to(self.device)).cpu()

    @torch.no_grad()
    def render(self, tokens: torch.Tensor,
               generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """tokens (k, t, h, w) → frames at the world model's rate (k, t, 3, H, W) and the output video."""
        if self.decoder is None:
            frames = self.tokenizer_frames(tokens)
            return frames, frames
        video = self.decoder(tokens, self.upsample, generator)
        out = {0: video.base, 1: video.double, 2: video.quadruple}[self.upsample]
        return video.base.cpu(), out.cpu()

    def __call__(self, context: torch.Tensor | None, frames: int, conditioning: Conditioning | None = None,
                 num_futures: int = 1, generator: torch.Generator | None = None) -> Gaia1Rollout:
        """context: (t0, 3, H, W) in [-1, 1] or None (generation from nothing) → `num_futures` futures of `frames`."""
        if frames < 1 or num_futures < 1:
            raise ValueError(f"frames ({frames}) and num_futures ({num_futures}) must be ≥ 1")
        h, w = self.token_grid
        tokens = self.encode(context) if context is not None else torch.zeros(0, h, w, dtype=torch.long)
        tokens, cond = self.sample_tokens(tokens, frames, conditioning or Conditioning(), num_futures, generator)
        t0 = tokens.shape[1] - frames
        log_ppl = self.frame_log_perplexity(tokens, cond, t0)
        base, video = self.render(tokens, generator)
        return Gaia1Rollout(tokens.cpu(), base, video, self.fps, log_ppl, t0)


DECODER_SAMPLERS = ("ddim", "one_step_mean", "antithetic_mean")


def make_decoder_sampler(kind: str, schedule: CosineNoiseSchedule, steps: int,
                         stored: Callable | None = None) -> Callable:
    """The video decoder's sampler: "ddim" with `steps` steps (the run's stored sampler factory when given, GAIA-1
    §5.2), "one_step_mean", the conditional mean over `steps` noise draws (docs/video_decoder.md), or
    "antithetic_mean", the same mean over `steps` / 2 pairs of opposite draws (x_T, −x_T)."""
    if kind in ("one_step_mean", "antithetic_mean"):
        return OneStepMeanSampler(schedule, draws=steps, antithetic=kind == "antithetic_mean")
    if kind == "ddim":
        return stored(schedule, steps=steps) if stored is not None else DDIMSampler(schedule, steps=steps)
    raise ValueError(f"decoder_sampler: expected one of {DECODER_SAMPLERS}, got {kind!r}")


def decoder_sampling(config: dict, steps: int | None,
                     kind: str = "ddim") -> tuple[CosineNoiseSchedule, Callable, int, int]:
    """(noise schedule, sampler, frames T', context frames) of a video decoder's stored config (model.schedule,
    model.sampler with `steps` if given, model.frames, model.context_frames), as VideoDecoderModule builds them;
    kind "one_step_mean" replaces the sampler (`make_decoder_sampler`, `steps` draws, 8 if None)."""
    from gaia_app.weights.targets import DIFFUSION_TARGETS, instantiate_checked

    where = "the video decoder checkpoint's model config"
    schedule = instantiate_checked(config["schedule"], f"{where}: schedule", DIFFUSION_TARGETS)() \
        if config.get("schedule") else CosineNoiseSchedule()
    if not config.get("sampler"):
        raise ValueError(f"{where} has no sampler")
    stored = instantiate_checked(config["sampler"], f"{where}: sampler", DIFFUSION_TARGETS)
    if kind == "ddim" and not steps:
        sampler = stored(schedule)
    else:
        sampler = make_decoder_sampler(kind, schedule, steps or 8, stored)
    return schedule, sampler, int(config.get("frames", 7)), int(config.get("context_frames", 2))


def _renderer(tokenizer: DiscreteTokenizer) -> Callable[[torch.Tensor], torch.Tensor]:
    """tokens (b, t, h, w) → the tokenizer's frame-by-frame decoding (b, t, 3, H, W) in [-1, 1]."""

    @torch.no_grad()
    def render(tokens: torch.Tensor) -> torch.Tensor:
        frames = tokenizer.decode(rearrange(tokens, "b t h w -> (b t) h w")).clamp(-1, 1)
        return rearrange(frames, "(b t) c h w -> b t c h w", b=tokens.shape[0])

    return render
