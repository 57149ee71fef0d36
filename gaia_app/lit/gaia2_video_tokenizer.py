"""Training of the GAIA-2 video tokenizer (GAIA-2 report, tokenizer), in two stages chosen by `model.stage`.

Batch: {"video": (b, v, T, 3, H, W) float in [-1, 1], …} from ClipDataModule (other keys unused).

Stage "reconstruction" trains the whole tokenizer on
    λ_L1·L1 + λ_L2·L2 + λ_perc·perceptual + λ_DINO·(1 − cos(P·μ, DINOv2)) + λ_KL·KL(q ‖ N(0, I))
with μ the posterior mean and P the trained 1×1 projection (the "DINOv2 distillation of latents").
Stage "gan" freezes the encoder (so a latent cache made after stage 1 stays valid) and fine-tunes the
decoder on the reconstruction terms plus λ_GAN·w·GAN against a 3-D convolutional discriminator, w
VQGAN's adaptive weight. It starts from a stage-1 checkpoint (`model.init_from`).

The report gives the loss terms, not their weights; the defaults below are choices (docs/video_tokenizer.md).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from einops import rearrange
from torch import nn

from gaia_app.encoders import distillation_loss
from gaia_app.eval.metrics import psnr, ssim
from gaia_app.lit.adversarial import AdversarialModule, pixel_terms
from gaia_app.lit.checkpoint import load_net_weights
from gaia_app.models.gaia2.conditioning import AgentBoxes3d, box_raster, project_boxes
from gaia_app.models.gaia2.video_tokenizer import (
    VideoTokenizer,
    VideoTokenizerOutput,
    kl_bits_per_pixel,
    widen_latent_channels,
)

STAGES = ("reconstruction", "gan")
WIDENINGS = (None, "unread", "read")
OFF_WARNINGS = {
    "perceptual": "model.perceptual=none (or model.weights.perceptual=0): the perceptual loss "
                  "(GAIA-2 report, tokenizer) is off",
    "dino": "model.dino=none (or model.weights.dino=0): the DINOv2 distillation of the latents "
            "(GAIA-2 report, tokenizer) is off",
    "gan": "model.stage=gan without a discriminator (model.discriminator=null or model.weights.gan=0): "
           "the decoder is fine-tuned on reconstruction terms only",
}


@dataclass(frozen=True)
class VideoLossWeights:
    """λ of each loss term (GAIA-2 report, tokenizer names the terms, not their weights). A zero weight switches a
    term off."""

    l1: float = 1.0
    l2: float = 1.0
    perceptual: float = 0.1
    dino: float = 0.1
    kl: float = 1.0e-4
    gan: float = 0.1
    agents: float = 0.0
    """Not in GAIA-2: the L1/L2 terms weigh pixels inside the agents' projected boxes 1 + `agents` times."""


class VideoTokenizerModule(AdversarialModule):
    """GAIA-2 tokenizer objective; generator/discriminator plumbing in AdversarialModule.

    Args:
        net, optim, sched: see GaiaModule.
        stage: "reconstruction" (stage 1, everything trains, no GAN) or "gan" (stage 2, decoder only + GAN).
        init_from: checkpoint (or weights folder such as "gaia2") whose tokenizer weights initialise the net when a
            fresh fit starts (stage 2 starts from stage 1; a fine-tune from the shipped weights); None: random init.
            Only `net.*` weights are read; the optimiser starts afresh.
        widen_latents: init_from has fewer latent channels than model.net (not in GAIA-2; widen_latent_channels):
            "unread" (the decoder's columns for the new channels start at zero) or "read" (at their own init); None:
            shapes must match.
        discriminator: PatchDiscriminator3d factory (used in stage "gan" only), or None.
        perceptual: factory of the frozen perceptual network (applied frame by frame), or none.
        dino: factory of the frozen DINOv2 teacher (`load_vision_teacher` partial), or none.
        weights: λ per term (VideoLossWeights fields).
        sample_posterior: decode a posterior sample (True, VAE training) or its mean.
        gan_start_step, adaptive_weight_max, gradient_clip_val: see AdversarialModule.
    """

    component = "video_tokenizer"

    def __init__(
        self,
        net: Callable[[], VideoTokenizer],
        optim: Callable,
        sched: Callable | None = None,
        stage: str = "reconstruction",
        init_from: str | None = None,
        widen_latents: str | None = None,
        discriminator: Callable[[], nn.Module] | None = None,
        perceptual: Callable[[], nn.Module] | str | None = None,
        dino: Callable[[], nn.Module] | str | None = None,
        weights: Mapping[str, float] | None = None,
        sample_posterior: bool = True,
        gan_start_step: int = 0,
        adaptive_weight_max: float = 1e4,
        gradient_clip_val: float | None = 1.0,
    ):
        if stage not in STAGES:
            raise ValueError(f"model.stage={stage!r}: expected one of {STAGES}")
        if widen_latents not in WIDENINGS:
            raise ValueError(f"model.widen_latents={widen_latents!r}: expected one of {WIDENINGS}")
        self.stage = stage
        self.weights = VideoLossWeights(**dict(weights or {}))
        super().__init__(net, optim, sched, discriminator if stage == "gan" else None,
                         {"perceptual": perceptual, "dino": dino}, gan_start_step, adaptive_weight_max,
                         gradient_clip_val)
        self.off_warnings = {k: v for k, v in OFF_WARNINGS.items() if k != "gan" or stage == "gan"}
        self.init_from, self.widen_latents = init_from, widen_latents
        self.sample_posterior = sample_posterior

    @property
    def tokenizer(self) -> VideoTokenizer:
        self.configure_model()
        return self.net  # type: ignore[return-value]

    def configure_model(self) -> None:
        """Build the nets once; in stage "gan" freeze the encoder side."""
        super().configure_model()
        if self.stage == "gan":
            for frozen in (self.net.encoder, self.net.distill_head):
                if frozen is not None:
                    frozen.requires_grad_(False)

    def on_fit_start(self) -> None:
        # a resumed run (ckpt_path) already holds its own weights; init_from only starts a fresh one, and
        # only when fitting, so load_module() of a stage-2 checkpoint never needs the stage-1 file
        if self.init_from and self.trainer.ckpt_path is None:
            self.load_init_weights()

    def load_init_weights(self) -> None:
        """Copy the tokenizer weights of `init_from` into the net (in place: optimiser state stays bound)."""
        load_tokenizer_weights(self.tokenizer, self.init_from, self.widen_latents)

    def generator_parameters(self) -> Iterable[nn.Parameter]:
        """Stage 1: the whole tokenizer; stage 2: the decoder only (GAIA-2 report, tokenizer: the GAN fine-tunes the
        decoder)."""
        params = self.net.decoder.parameters() if self.stage == "gan" else self.net.parameters()
        return [p for p in params if p.requires_grad]

    # ---- losses --------------------------------------------------------------------------

    def run_tokenizer(self, video: torch.Tensor) -> VideoTokenizerOutput:
        """Forward pass; in stage "gan" the frozen encoder runs without building a graph."""
        if self.stage != "gan":
            return self.tokenizer(video, sample=self.sample_posterior)
        with torch.no_grad():
            posterior = self.tokenizer.encode(video)
            latents = posterior.sample() if self.sample_posterior else posterior.mode()
        return VideoTokenizerOutput(self.tokenizer.decode(latents), posterior, latents)

    def pixel_weights(self, video: torch.Tensor, batch: dict[str, Any] | None) -> torch.Tensor | None:
        """(b, v, T, 1, H, W) weights 1 + λ_agents inside the agents' boxes projected through the rig, 1 elsewhere,
        scaled to mean 1; None when `weights.agents` is 0. The boxes come from the batch's "agents_*" (b, T, N)
        and "intrinsics"/"extrinsics" (b, v, 3, 3)/(b, v, 4, 4), as the world model reads them."""
        if self.weights.agents == 0:
            return None
        needed = ("agents_centre", "agents_size", "agents_yaw", "agents_category", "agents_mask", "intrinsics",
                  "extrinsics")
        if batch is None or any(key not in batch for key in needed):
            raise ValueError("model.weights.agents > 0 needs agent boxes and camera specs in the batch (clips with "
                             "agents and cameras, e.g. data=synthetic_rig)")
        agents = AgentBoxes3d(*(batch[f"agents_{k}"] for k in ("centre", "size", "yaw", "category", "mask")))
        boxes, _, visible = project_boxes(agents, batch["intrinsics"], batch["extrinsics"], tuple(video.shape[-2:]))
        inside = rearrange(box_raster(boxes, visible, tuple(video.shape[-2:])), "b T v H W -> b v T 1 H W")
        weight = 1 + self.weights.agents * inside.to(video.dtype)
        return weight / weight.mean()

    def reconstruction_terms(self, video: torch.Tensor, out: VideoTokenizerOutput,
                             batch: dict[str, Any] | None = None) -> dict[str, torch.Tensor]:
        """Weighted L1, L2 and perceptual (frame by frame) terms (GAIA-2 report, tokenizer); with `weights.agents`
        the L1/L2 pixels inside agent boxes count 1 + λ_agents times."""
        w, recon = self.weights, out.reconstruction
        pixels = self.pixel_weights(video, batch)
        terms = pixel_terms(recon, video, w.l1, w.l2, pixels)
        if (perceptual := self.frozen_network("perceptual", video.device)) is not None:
            frames = "b v T c H W -> (b v T) c H W"
            terms["perceptual"] = w.perceptual * perceptual(rearrange(recon, frames), rearrange(video, frames)).mean()
        return terms

    def latent_terms(self, video: torch.Tensor, out: VideoTokenizerOutput) -> dict[str, torch.Tensor]:
        """Weighted KL to N(0, I) and DINOv2 distillation of the posterior mean (GAIA-2 report, tokenizer); stage 1
        only."""
        if self.stage == "gan":
            return {}
        terms = {"kl": self.weights.kl * out.posterior.kl().mean()}
        if (teacher := self.frozen_network("dino", video.device)) is not None:
            student = self.tokenizer.distill(out.posterior.mean)  # (b·v·t, f, h, w)
            target = teacher(self.step_frames(video))  # (b·v·t, f, gh, gw), no grad
            if student.shape[1] != target.shape[1]:
                raise ValueError(f"model.dino gives {target.shape[1]}-dim features but model.net.distill_dim="
                                 f"{student.shape[1]}: set model.net.distill_dim={target.shape[1]}")
            terms["dino"] = self.weights.dino * distillation_loss(student, target)
        return terms

    def step_frames(self, video: torch.Tensor) -> torch.Tensor:
        """The middle frame of each latent step, (b·v·t, 3, H, W): what the DINOv2 teacher sees. One frame
        per step, not all τ, keeps the teacher's cost at 1/τ; neighbouring frames barely differ in content."""
        tau = self.tokenizer.temporal
        middle = video[:, :, tau // 2 :: tau]
        return rearrange(middle, "b v t c H W -> (b v t) c H W")

    def losses(self, video: torch.Tensor, out: VideoTokenizerOutput, batch: dict[str, Any] | None = None
               ) -> dict[str, torch.Tensor]:
        """Weighted loss terms without the GAN term (as validated), and their total under 'loss'."""
        return self.generator_terms(video, out, with_gan=False, batch=batch)

    def generator_terms(self, video: torch.Tensor, out: VideoTokenizerOutput, with_gan: bool,
                        batch: dict[str, Any] | None = None) -> dict[str, torch.Tensor]:
        """`losses` plus, when `with_gan`, λ_GAN·w·GAN with w from the decoder's last-layer gradients.
        batch: the agents and cameras for `weights.agents`."""
        reconstruction = self.reconstruction_terms(video, out, batch)
        terms = {**reconstruction, **self.latent_terms(video, out)}
        loss = sum(terms.values())
        if with_gan:
            self.add_gan_term(terms, sum(reconstruction.values()), as_clips(out.reconstruction),
                              self.tokenizer.last_layer)
            loss = loss + terms["gan"]
        terms["loss"] = loss
        return terms

    # ---- optimisation --------------------------------------------------------------------

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> dict[str, torch.Tensor]:
        video = batch["video"]

        def generate(with_gan: bool) -> tuple[dict[str, torch.Tensor], VideoTokenizerOutput]:
            out = self.run_tokenizer(video)
            return self.generator_terms(video, out, with_gan, batch), out

        terms, _ = self.adversarial_step(generate, lambda out: (as_clips(video), as_clips(out.reconstruction)))
        return {k: v.detach() for k, v in terms.items()}

    # ---- validation and media ------------------------------------------------------------

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        video = batch["video"]
        out = self.tokenizer(video, sample=False)
        terms = self.losses(video, out, batch)
        recon = out.reconstruction.clamp(-1, 1)
        frames = "b v T c H W -> (b v T) c H W"
        n = len(video)
        self.log_dict({f"val/{k}": v for k, v in terms.items()}, batch_size=n)
        self.log("val/psnr", psnr(rearrange(recon, frames), rearrange(video, frames)).mean(), prog_bar=True,
                 batch_size=n)
        self.log("val/ssim", ssim(rearrange(recon, frames), rearrange(video, frames)).mean(), batch_size=n)
        self.log("val/kl_bits_per_pixel", kl_bits_per_pixel(out.posterior, video.shape[2], *video.shape[-2:]),
                 batch_size=n)

    @torch.no_grad()
    def evaluation_pair(self, batch: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        """(input clips, reconstructions from the posterior mean), both (b·v, T, 3, H, W): cameras are
        separate videos for gaia_app.lit.evaluation.EvaluationCallback (PSNR/SSIM/LPIPS/FVMD/FID/FDD)."""
        video = batch["video"]
        recon = self.tokenizer(video, sample=False).reconstruction.clamp(-1, 1)
        fold = "b v T c H W -> (b v) T c H W"
        return rearrange(video, fold), rearrange(recon, fold)

    @torch.no_grad()
    def media(self, batch: dict[str, Any]) -> dict[str, Any]:
        """What the Rerun media callback shows: per camera, input above reconstruction (one column per
        camera, played over the frames), and the latent channels of the first clip as a grey-level mosaic."""
        video = batch["video"][:1]
        out = self.tokenizer(video, sample=False)
        stacked = torch.cat([video, out.reconstruction.clamp(-1, 1)], dim=-2)  # input on top: (1, v, T, 3, 2H, W)
        return {"val/input_over_reconstruction": stacked,
                "val/latent_channels": latent_mosaic(out.posterior.mean[0, 0])}


def as_clips(video: torch.Tensor) -> torch.Tensor:
    """(b, v, T, 3, H, W) → (b·v, 3, T, H, W), the 3-D discriminator's layout (cameras judged separately)."""
    return rearrange(video, "b v T c H W -> (b v) c T H W")


def latent_mosaic(latents: torch.Tensor, columns: int = 8) -> torch.Tensor:
    """latents (t, C, h, w) → (t, 1, rows·h, columns·w) in [-1, 1]: each channel standardised to ±3σ and
    tiled, one mosaic per latent step (zero-padded to whole rows)."""
    t, c = latents.shape[:2]
    columns = min(columns, c)
    rows = -(-c // columns)
    x = latents.float()
    x = (x - x.mean(dim=(-2, -1), keepdim=True)) / (3 * x.std(dim=(-2, -1), keepdim=True) + 1e-6)
    x = torch.cat([x, x.new_zeros(t, rows * columns - c, *x.shape[-2:])], dim=1).clamp(-1, 1)
    return rearrange(x, "t (r q) h w -> t 1 (r h) (q w)", q=columns)


def load_tokenizer_weights(net: VideoTokenizer, path: str | Path, widen_latents: str | None = None) -> None:
    """Copy the `net.*` weights of a VideoTokenizerModule checkpoint, or of a weights folder's video_tokenizer (e.g.
    "gaia2", the shipped one), into `net` (strict: same architecture, except that weights without the decoder's
    refiner start a net that has one, and with `widen_latents` weights with fewer latent channels start a net with
    more: models.gaia2.video_tokenizer.widen_latent_channels)."""
    load_net_weights(net, path, "a stage-1 tokenizer checkpoint (a VideoTokenizerModule checkpoint)",
                     component="video_tokenizer", fresh=net.fresh_modules,
                     transform=(lambda weights: widen_latent_channels(weights, net, widen_latents == "read"))
                     if widen_latents else None)
