"""Training of the GAIA-1 video decoder: multi-task v-prediction diffusion on token-conditioned clips
(GAIA-1 §2.4, §4.3, Fig. 4).

Batch: {"video": (b, v, T, 3, H, W) in [-1, 1], ...} from the ClipDataModule at the source rate (25 Hz);
each step picks a frame step (1, 2 or 4: 25, 12.5 or 6.25 Hz, §4.3) and a T'-frame window, tokenises
it with the frozen image tokenizer, draws one task (image, video, forward/backward autoregressive,
interpolation; equal probability) and drops each conditioning token with p = 0.15.

Loss (eq. 2 with §4.3's weights): 0.1·L1 + 1.0·L2 between the predicted and true v, on the frames
the task generates. An exponential moving average of the weights (0.999) is kept in `self.ema` and
is what validation, media and generation use.

The tokenizer comes from its own checkpoint (`tokenizer_ckpt`) and is kept out of the module tree: it
is frozen, never optimised, and not duplicated into this module's checkpoints.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from einops import rearrange, repeat
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from gaia_app.diffusion.noise_schedule import CosineNoiseSchedule, v_target
from gaia_app.diffusion.video_sampling import sample_window
from gaia_app.lit.base import GaiaModule, decay_groups
from gaia_app.lit.checkpoint import load_module
from gaia_app.models.gaia1.decoder_tasks import TASKS, DecoderTask, TaskSampler, drop_tokens, make_task
from gaia_app.models.gaia1.video_decoder import VideoDecoder
from gaia_app.models.tokenizer_protocol import DiscreteTokenizer
from gaia_app.weights.folders import load_nets, shipped_folder


def load_tokenizer(source: str) -> DiscreteTokenizer:
    """The GAIA-1 image tokenizer of a training checkpoint (`.ckpt`), or of a shipped weights folder (a folder
    with tokenizer.safetensors, or a name under gaia_app/weights such as "gaia1"), so that a decoder can be trained
    on the tokens of the shipped reference weights."""
    if Path(source).is_file():
        return load_module(source).tokenizer
    return load_nets(shipped_folder(source), "tokenizer")[0]["net"]


class VideoDecoderModule(GaiaModule):
    """GAIA-1 video decoder with its multi-task objective and EMA weights.

    Args:
        net, optim, sched: see GaiaModule (§4.3: AdamW 5e-5, wd 0.01, betas 0.9/0.99; warm-up, cosine to 1e-6).
        tokenizer_ckpt: checkpoint of the trained GAIA-1 image tokenizer that makes the conditioning tokens.
        schedule: factory of the noise schedule (cosine β, §4.3). sampler: factory taking the schedule
            (DDIM 50 steps, §5.2), used for media and by generation.
        tasks: {task: weight} (§4.3: all equal). frames: T'. context_frames: context of the AR tasks.
        frame_steps: source-frame steps a window may use (25 Hz source: 1, 2, 4 → 25, 12.5, 6.25 Hz).
        token_dropout: p of dropping each conditioning token. l1_weight, l2_weight: loss weights.
        ema_decay: decay of the weight average. media_steps: sampler steps for the Rerun media.
    """

    component = "video_decoder"
    net_prefixes = {"net": "ema.module."}  # generation samples with the EMA weights (GAIA-1 §4.3)

    def __init__(self, net: Callable[[], VideoDecoder], optim: Callable, sched: Callable | None = None,
                 tokenizer_ckpt: str | None = None, schedule: Callable[[], CosineNoiseSchedule] = CosineNoiseSchedule,
                 sampler: Callable | None = None, tasks: dict[str, float] | None = None, frames: int = 7,
                 context_frames: int = 2, frame_steps: Sequence[int] = (1, 2, 4), token_dropout: float = 0.15,
                 l1_weight: float = 0.1, l2_weight: float = 1.0, ema_decay: float = 0.999, media_steps: int = 20):
        super().__init__(net, optim, sched)
        self.tokenizer_ckpt = tokenizer_ckpt
        self.schedule = schedule()
        self.sampler_factory = sampler
        self.task_sampler = TaskSampler(dict(tasks or {name: 1.0 for name in TASKS}), frames, context_frames)
        self.frames, self.context_frames, self.frame_steps = frames, context_frames, tuple(frame_steps)
        self.token_dropout, self.l1_weight, self.l2_weight = token_dropout, l1_weight, l2_weight
        self.ema_decay, self.media_steps = ema_decay, media_steps
        self.ema: AveragedModel | None = None
        self.frozen: dict[str, DiscreteTokenizer] = {}  # a plain dict: not a submodule (see the module docstring)

    # ---- networks ---------------------------------------------------------------------------------

    def configure_model(self) -> None:
        """Build the decoder and its EMA copy once (idempotent)."""
        super().configure_model()
        if self.ema is None:
            self.ema = AveragedModel(self.net, multi_avg_fn=get_ema_multi_avg_fn(self.ema_decay), use_buffers=True)
            self.ema.requires_grad_(False)

    @property
    def decoder(self) -> VideoDecoder:
        self.configure_model()
        return self.net  # type: ignore[return-value]

    @property
    def ema_decoder(self) -> VideoDecoder:
        """The averaged weights: what validation and generation sample with."""
        self.configure_model()
        return self.ema.module  # type: ignore[union-attr, return-value]

    @property
    def tokenizer(self) -> DiscreteTokenizer:
        """The frozen image tokenizer, loaded from `tokenizer_ckpt` on first use."""
        if "tokenizer" not in self.frozen:
            if not self.tokenizer_ckpt:
                raise ValueError("the video decoder needs model.tokenizer_ckpt=<trained GAIA-1 tokenizer checkpoint, "
                                 "or a shipped weights folder such as gaia1>")
            self.frozen["tokenizer"] = load_tokenizer(self.tokenizer_ckpt).eval().requires_grad_(False)
        tokenizer = self.frozen["tokenizer"].to(self.device)
        self.frozen["tokenizer"] = tokenizer
        return tokenizer

    def sampler(self, steps: int | None = None) -> Callable:
        if self.sampler_factory is None:
            raise ValueError("model.sampler is not set")
        return self.sampler_factory(self.schedule, **({"steps": steps} if steps else {}))

    def configure_optimizers(self) -> Any:
        self.configure_model()
        optimizer = self.optim_factory(decay_groups(self.net))
        if not self.sched_factory:
            return optimizer
        return {"optimizer": optimizer,
                "lr_scheduler": {"scheduler": self.sched_factory(optimizer), "interval": "step"}}

    def optimizer_step(self, *args: Any, **kwargs: Any) -> None:
        """Step, then fold the new weights into the EMA (here rather than in on_train_batch_end, so a
        checkpoint written at the end of this step already holds this step's average)."""
        super().optimizer_step(*args, **kwargs)
        self.ema.update_parameters(self.net)  # type: ignore[union-attr]

    # ---- data ---------------------------------------------------------------------------------------

    def window(self, batch: dict[str, Any], step: int | None = None, offset: int | None = None) -> torch.Tensor:
        """T' frames every `step` source frames (random step and offset when None) → (b·v, T', 3, H, W)."""
        video = rearrange(batch["video"], "b v t c h w -> (b v) t c h w")
        steps = [s for s in self.frame_steps if (self.frames - 1) * s < video.shape[1]]
        if not steps:
            raise ValueError(f"clips of {video.shape[1]} frames are too short for {self.frames} frames at steps "
                             f"{self.frame_steps}: set data.clip_len ≥ {(self.frames - 1) * min(self.frame_steps) + 1}")
        step = step or steps[int(torch.randint(len(steps), ()))]
        span = (self.frames - 1) * step + 1
        offset = int(torch.randint(video.shape[1] - span + 1, ())) if offset is None else offset
        return video[:, offset : offset + span : step]

    @torch.no_grad()
    def tokenize(self, frames: torch.Tensor) -> torch.Tensor:
        """(b, t, 3, H, W) → tokens (b, t, h, w) with the frozen tokenizer."""
        tokens = self.tokenizer.encode(rearrange(frames, "b t c h w -> (b t) c h w"))
        return rearrange(tokens, "(b t) h w -> b t h w", b=frames.shape[0])

    @torch.no_grad()
    def render_tokens(self, tokens: torch.Tensor) -> torch.Tensor:
        """tokens (b, t, h, w) → the frozen tokenizer's frame-by-frame decoding (b, t, 3, H, W) in [-1, 1]."""
        frames = self.tokenizer.decode(rearrange(tokens, "b t h w -> (b t) h w")).clamp(-1, 1)
        return rearrange(frames, "(b t) c h w -> b t c h w", b=tokens.shape[0])

    def rendered(self, net: VideoDecoder, tokens: torch.Tensor) -> torch.Tensor | None:
        """`render_tokens(tokens)` for a decoder that takes it, else None."""
        return self.render_tokens(tokens) if net.render_tokens else None

    # ---- objective ----------------------------------------------------------------------------------

    def masks(self, task: DecoderTask, tokens: torch.Tensor, dropout: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """(token_mask (b, t, h, w), context_mask (b, t)) of a task for tokens (b, t, h, w)."""
        b = tokens.shape[0]
        token_mask = repeat(task.tokens.to(tokens.device), "t -> b t h w", b=b, h=tokens.shape[2], w=tokens.shape[3])
        if dropout and self.token_dropout > 0:
            token_mask = drop_tokens(token_mask, self.token_dropout)
        return token_mask, repeat(task.context.to(tokens.device), "t -> b t", b=b)

    def loss(self, net: VideoDecoder, x0: torch.Tensor, tokens: torch.Tensor, task: DecoderTask,
             dropout: bool) -> torch.Tensor:
        """0.1·L1 + 1.0·L2 on v over the task's generated frames (GAIA-1 eq. 2, §4.3). x0: (b, t, 3, H, W); a
        residual decoder diffuses (and is given as context) its residual over the rendered tokens instead."""
        b = x0.shape[0]
        token_mask, context_mask = self.masks(task, tokens, dropout)
        rendered = self.rendered(net, tokens)
        x0 = net.residual_frame(rendered, token_mask, x0).encode(x0)  # x0 itself unless net.residual
        step = self.schedule.sample_timesteps(b, x0.device)
        noise = torch.randn_like(x0)
        x_t = self.schedule.add_noise(x0, noise, step)
        alpha, sigma = self.schedule.alpha_sigma(step)
        pred = net(x_t, step, tokens, token_mask, x0, context_mask, temporal=task.temporal, rendered=rendered)
        target = task.target.to(x0.device)
        error = (pred - v_target(x0, noise, alpha, sigma))[:, target]
        return self.l1_weight * error.abs().mean() + self.l2_weight * error.pow(2).mean()

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        x0 = self.window(batch)
        task = self.task_sampler()
        loss = self.loss(self.decoder, x0, self.tokenize(x0), task, dropout=True)
        self.log("train/loss", loss, prog_bar=True)
        self.log(f"train/loss_{task.name}", loss)
        return loss

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        """Every task on every batch, with the EMA weights, at the slowest rate (the world model's)."""
        step = max(s for s in self.frame_steps if (self.frames - 1) * s < batch["video"].shape[2])
        x0 = self.window(batch, step=step, offset=0)
        tokens = self.tokenize(x0)
        losses = {name: self.loss(self.ema_decoder, x0, tokens, make_task(name, self.frames, self.context_frames),
                                  dropout=False) for name in TASKS}
        for name, value in losses.items():
            self.log(f"val/loss_{name}", value)
        self.log("val/loss", torch.stack(list(losses.values())).mean(), prog_bar=True)

    # ---- media --------------------------------------------------------------------------------------

    @torch.no_grad()
    def decode_tokens(self, tokens: torch.Tensor, callback: Callable | None = None) -> torch.Tensor:
        """Tokens (b, T′, h, w) → decoded window (b, T′, 3, H, W) with the EMA decoder, video task (every frame
        from tokens), `media_steps` sampler steps, a fixed seed."""
        ones = torch.ones(tokens.shape[:2], dtype=torch.bool, device=tokens.device)
        shape = (*tokens.shape[:2], 3, *self.ema_decoder.image_size)
        return sample_window(self.ema_decoder, self.schedule, self.sampler(self.media_steps), tokens, ones,
                             torch.zeros(shape, device=tokens.device), ~ones,
                             generator=torch.Generator(tokens.device).manual_seed(0), callback=callback,
                             rendered=self.rendered(self.ema_decoder, tokens))

    @torch.no_grad()
    def evaluation_pair(self, batch: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        """(ground-truth window, its decoding from the tokenizer's tokens), both (b, T′, 3, H, W), for
        gaia_app.lit.evaluation.EvaluationCallback (FVMD, FDD, PSNR/SSIM of the video decoder)."""
        x0 = self.window(batch, step=max(self.frame_steps), offset=0)
        return x0, self.decode_tokens(self.tokenize(x0))

    @torch.no_grad()
    def media(self, batch: dict[str, Any]) -> dict[str, Any]:
        """Ground truth, decoded video (EMA, video task), the tokenizer's frame-by-frame decoding and the
        denoising steps of the first frame, for the Rerun media callback."""
        x0 = self.window(batch, step=max(self.frame_steps), offset=0)[:2]
        tokens = self.tokenize(x0)
        steps: list[torch.Tensor] = []
        decoded = self.decode_tokens(tokens, callback=lambda i, t, x, x0_pred: steps.append(x0_pred[0, 0].clamp(-1, 1)))
        framewise = self.render_tokens(tokens)
        return {
            "val/decoder/ground_truth": x0,
            "val/decoder/decoded": decoded,
            "val/decoder/tokenizer_framewise": framewise,
            "val/decoder/denoising_steps": torch.stack(steps)[None],
            "val/decoder/tokens": tokens[:, 0],
        }
