"""Training of the GAIA-1 image tokenizer (GAIA-1 §2.2, §4.1).

Batch: {"image": (b, 3, H, W) float in [-1, 1]}.

The generator is the tokenizer (encoder, quantiser, decoder and DINO projection). Its loss is
    λ_L1·L1 + λ_L2·L2 + λ_perc·perceptual + λ_GAN·w·GAN + λ_cb·(codebook + commitment) + λ_DINO·(1 − cos)
with w VQGAN's adaptive weight. Optimisation is manual, with two optimisers: every batch takes one
generator step and, from `gan_start_step` on, one discriminator step on the hinge loss.

The generator/discriminator plumbing and the frozen loss networks (perceptual VGG, DINO teacher, kept
out of the state dict) are shared with the GAIA-2 video tokenizer: gaia_app/lit/adversarial.py.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from gaia_app.encoders import distillation_loss
from gaia_app.eval.metrics import codebook_perplexity, psnr, ssim
from gaia_app.lit.adversarial import AdversarialModule, pixel_terms
from gaia_app.lit.checkpoint import load_net_weights
from gaia_app.models.gaia1.tokenizer import ImageTokenizer, TokenizerOutput

OFF_WARNINGS = {
    "perceptual": "model.perceptual=none (or model.weights.perceptual=0): the perceptual loss (GAIA-1 §2.2) is off",
    "dino": "model.dino=none (or model.weights.dino=0): the DINO distillation loss (GAIA-1 §2.2) is off; "
            "tokens get no semantic inductive bias",
    "gan": "model.discriminator=null (or model.weights.gan=0): the GAN loss (GAIA-1 §2.2) is off",
}


@dataclass(frozen=True)
class LossWeights:
    """λ of each loss term; the defaults are GAIA-1 §4.1. A zero weight switches its term off."""

    l1: float = 0.2
    l2: float = 2.0
    perceptual: float = 0.1
    gan: float = 1.0
    codebook: float = 1.0
    dino: float = 0.1
    agents: float = 0.0
    """Not in GAIA-1: the L1/L2 terms weigh pixels inside agent boxes 1 + `agents` times (batch "agent_box")."""


class ImageTokenizerModule(AdversarialModule):
    """GAIA-1 tokenizer objective with generator/discriminator optimisation by hand.

    Args:
        net, optim, sched: see GaiaModule; `optim` and `sched` build both optimisers and schedules.
        discriminator: PatchDiscriminator factory, or None (GAN loss off).
        perceptual: factory of the frozen perceptual network (`load_perceptual` partial), or none.
        dino: factory of the frozen DINO teacher (`load_vision_teacher` partial), or none.
        weights: λ per term (LossWeights fields); missing fields keep the GAIA-1 §4.1 values.
        gan_start_step: generator steps before the discriminator trains and the GAN term enters.
        adaptive_weight_max: clamp of VQGAN's adaptive GAN weight.
        gradient_clip_val: norm clipping of each optimiser's gradients (None/0: off). Lightning's
            `trainer.gradient_clip_val` must be null: it is not supported with manual optimisation.
        dead_code_restart_every: every N generator steps, codes unused since the last restart are
            re-seeded from encoder outputs (0 disables). Keeps vocabulary usage up.
        init_from: tokenizer training checkpoint, or a weights folder with tokenizer.safetensors (e.g. "gaia1"),
            whose net weights start a fresh fit (a fine-tune, e.g. with `weights.agents`); a resumed run keeps its own.
    """

    component = "tokenizer"

    off_warnings = OFF_WARNINGS

    def __init__(
        self,
        net: Callable[[], ImageTokenizer],
        optim: Callable,
        sched: Callable | None = None,
        discriminator: Callable[[], nn.Module] | None = None,
        perceptual: Callable[[], nn.Module] | str | None = None,
        dino: Callable[[], nn.Module] | str | None = None,
        weights: Mapping[str, float] | None = None,
        gan_start_step: int = 0,
        adaptive_weight_max: float = 1e4,
        gradient_clip_val: float | None = 1.0,
        dead_code_restart_every: int = 0,
        init_from: str | None = None,
    ):
        self.weights = LossWeights(**dict(weights or {}))
        super().__init__(net, optim, sched, discriminator, {"perceptual": perceptual, "dino": dino}, gan_start_step,
                         adaptive_weight_max, gradient_clip_val)
        self.dead_code_restart_every, self.init_from = dead_code_restart_every, init_from
        self._usage: torch.Tensor | None = None
        self._val_tokens: list[torch.Tensor] = []

    @property
    def tokenizer(self) -> ImageTokenizer:
        self.configure_model()
        return self.net  # type: ignore[return-value]

    def on_fit_start(self) -> None:
        if self.init_from and self.trainer.ckpt_path is None:
            load_net_weights(self.tokenizer, self.init_from,
                             "a GAIA-1 tokenizer training checkpoint of the same preset", component="tokenizer")

    # ---- losses --------------------------------------------------------------------------

    def pixel_weights(self, image: torch.Tensor, agent_box: torch.Tensor | None) -> torch.Tensor | None:
        """(b, 1, H, W) weights 1 + λ_agents inside agent boxes (b, H, W), 1 elsewhere, scaled to mean 1 so the
        loss keeps its scale; None when `weights.agents` is 0."""
        if self.weights.agents == 0:
            return None
        if agent_box is None:
            raise ValueError("model.weights.agents > 0 needs the agents' boxes in the batch: set data.agent_boxes=true "
                             "(clips with agent boxes and camera specs)")
        if agent_box.shape != (image.shape[0], *image.shape[-2:]):
            raise ValueError(f"batch 'agent_box' {tuple(agent_box.shape)} does not match the images "
                             f"{tuple(image.shape)}")
        weight = 1 + self.weights.agents * agent_box[:, None].to(image.dtype)
        return weight / weight.mean()

    def reconstruction_terms(self, image: torch.Tensor, out: TokenizerOutput,
                             agent_box: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Weighted L1, L2 and perceptual terms of the image reconstruction loss (GAIA-1 §2.2); with
        `weights.agents` the L1/L2 pixels inside agent boxes (b, H, W) count 1 + λ_agents times."""
        w, recon = self.weights, out.reconstruction
        pixels = self.pixel_weights(image, agent_box)
        terms = pixel_terms(recon, image, w.l1, w.l2, pixels)
        if (perceptual := self.frozen_network("perceptual", image.device)) is not None:
            terms["perceptual"] = w.perceptual * perceptual(recon, image).mean()
        return terms

    def latent_terms(self, image: torch.Tensor, out: TokenizerOutput) -> dict[str, torch.Tensor]:
        """Weighted quantisation loss and DINO distillation (inductive-bias) loss (GAIA-1 §2.2)."""
        terms = {"codebook": self.weights.codebook * (out.codebook_loss + out.commitment_loss)}
        if (teacher := self.frozen_network("dino", image.device)) is not None:
            student = self.tokenizer.distill(out.quantized)  # (b, f, h, w)
            target = teacher(image)  # (b, f, gh, gw), no grad
            if student.shape[1] != target.shape[1]:
                raise ValueError(f"model.dino gives {target.shape[1]}-dim features but model.net.distill_dim="
                                 f"{student.shape[1]}: set model.net.distill_dim={target.shape[1]}")
            terms["dino"] = self.weights.dino * distillation_loss(student, target)
        return terms

    def losses(self, image: torch.Tensor, out: TokenizerOutput, agent_box: torch.Tensor | None = None
               ) -> dict[str, torch.Tensor]:
        """Weighted loss terms without the GAN term (as validated), and their total under 'loss'."""
        return self.generator_terms(image, out, with_gan=False, agent_box=agent_box)

    def generator_terms(self, image: torch.Tensor, out: TokenizerOutput, with_gan: bool,
                        agent_box: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """`losses` plus, when `with_gan`, λ_GAN·w·GAN with w from the decoder's last-layer gradients."""
        reconstruction = self.reconstruction_terms(image, out, agent_box)
        terms = {**reconstruction, **self.latent_terms(image, out)}
        loss = sum(terms.values())
        if with_gan:
            self.add_gan_term(terms, sum(reconstruction.values()), out.reconstruction, self.tokenizer.last_layer)
            loss = loss + terms["gan"]
        terms["loss"] = loss
        return terms

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> dict[str, torch.Tensor]:
        image = batch["image"]
        step = self.global_step  # generator steps so far: discriminator steps are not counted (see _step)

        def generate(with_gan: bool) -> tuple[dict[str, torch.Tensor], TokenizerOutput]:
            out = self.tokenizer(image)
            return self.generator_terms(image, out, with_gan, batch.get("agent_box")), out

        terms, out = self.adversarial_step(generate, lambda out: (image, out.reconstruction))
        self._track_usage(out.tokens, image, step)
        return {k: v.detach() for k, v in terms.items()}

    def _track_usage(self, tokens: torch.Tensor, image: torch.Tensor, step: int) -> None:
        if self.dead_code_restart_every <= 0:
            return
        k = self.tokenizer.codebook_size
        counts = torch.bincount(tokens.flatten(), minlength=k)
        self._usage = counts if self._usage is None else self._usage + counts
        if (step + 1) % self.dead_code_restart_every == 0:
            with torch.no_grad():
                features = self.tokenizer.encoder(image)
            restarted = self.tokenizer.quantizer.restart_dead_codes(features, self._usage)
            self.log("train/restarted_codes", float(restarted))
            self._usage = None

    # ---- validation and media ------------------------------------------------------------

    def validation_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> None:
        image = batch["image"]
        out = self.tokenizer(image)
        terms = self.losses(image, out, batch.get("agent_box"))
        recon = out.reconstruction.clamp(-1, 1)
        self.log_dict({f"val/{k}": v for k, v in terms.items()}, prog_bar=False)
        self.log("val/psnr", psnr(recon, image).mean(), prog_bar=True)
        self.log("val/ssim", ssim(recon, image).mean())
        if (boxes := batch.get("agent_box")) is not None and boxes.any():
            inside = ((recon - image) / 2).pow(2).mean(dim=1)[boxes].mean()
            self.log("val/psnr_in_boxes", 10 * torch.log10(1 / inside.clamp_min(1e-10)))
        self._val_tokens.append(out.tokens.detach().flatten().cpu())

    def on_validation_epoch_end(self) -> None:
        if not self._val_tokens:
            return
        tokens = torch.cat(self._val_tokens)
        k = self.tokenizer.codebook_size
        self.log("val/codebook_usage", torch.unique(tokens).numel() / k)
        self.log("val/perplexity", codebook_perplexity(tokens, k))
        self._val_tokens.clear()

    @torch.no_grad()
    def evaluation_pair(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """(input images, reconstructions), both (b, 3, H, W), for gaia_app.lit.evaluation.EvaluationCallback."""
        return batch["image"], self.tokenizer(batch["image"]).reconstruction.clamp(-1, 1)

    @torch.no_grad()
    def media(self, batch: dict[str, torch.Tensor]) -> dict[str, Any]:
        """What the Rerun media callback shows: inputs, reconstructions, token maps (hash and PCA colours, GAIA-1
        Fig. 3)."""
        image = batch["image"]
        out = self.tokenizer(image)
        return {
            "val/input": image,
            "val/reconstruction": out.reconstruction.clamp(-1, 1),
            "val/tokens": out.tokens,
            "val/tokens_pca": (out.tokens, self.codebook_embeddings().detach()),
        }

    def codebook_embeddings(self) -> nn.Parameter:
        """(k, e) code vectors, for the PCA colouring of token maps."""
        return self.tokenizer.quantizer.codebook.weight
