"""Training of the GAIA-1 image tokenizer (GAIA-1 §2.2, §4.1).

Batch: {"image": (b, 3, H, W) float in [-1, 1]}.

The generator is the tokenizer (encoder, quantiser, decoder and DINO projection). Its loss is
    λ_L1·L1 + λ_L2·L2 + λ_perc·perceptual + λ_GAN·w·GAN + λ_cb·(codebook + commitment) + λ_DINO·(1 − cos)
with w VQGAN's adaptive weight. Optimisation is manual, with two optimisers: every batch takes one
generator step and, from `gan_start_step` on, one discriminator step on the hinge loss.

The frozen networks (perceptual VGG, DINO teacher) are loaded from local checkpoints when fitting or
validating starts. They are kept out of the module tree on purpose: they are not in the state dict, so
checkpoints stay small and `load_module` works without the teacher files. They are in no optimiser,
and DDP/FSDP wrapping and precision casts leave them alone.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from lightning.pytorch.core.optimizer import LightningOptimizer, do_nothing_closure
from torch import nn

from gaia_app.encoders import distillation_loss
from gaia_app.eval.metrics import codebook_perplexity, psnr, ssim
from gaia_app.lit.base import GaiaModule
from gaia_app.models.gaia1.tokenizer import ImageTokenizer, TokenizerOutput
from gaia_app.nn.discriminator import adaptive_gan_weight, hinge_discriminator_loss, hinge_generator_loss

log = logging.getLogger(__name__)

FROZEN = ("perceptual", "dino")
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


def is_off(spec: Any) -> bool:
    """True for a switched-off loss network: None, "none", or the empty node that `encoder=none` composes to."""
    if spec is None:
        return True
    if isinstance(spec, str):
        return spec.strip().lower() in ("none", "null", "")
    return isinstance(spec, Mapping) and len(spec) == 0


def factory_or_none(name: str, spec: Any) -> Callable[[], nn.Module] | None:
    """A loss-network factory (Hydra `_partial_`), or None when the loss is switched off."""
    if is_off(spec):
        return None
    if not callable(spec):
        raise TypeError(f"model.{name}={spec!r} is not a network factory (a Hydra node with _partial_: true): pick a "
                        f"config option (encoder@model.{name}=<conf/encoder/ option> for perceptual and dino), "
                        f"or switch the loss off with model.{name}=none")
    return spec


class ImageTokenizerModule(GaiaModule):
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
    """

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
    ):
        super().__init__(net, optim, sched)
        self.automatic_optimization = False
        self.weights = LossWeights(**dict(weights or {}))
        gan_on = not is_off(discriminator) and self.weights.gan > 0
        self.discriminator_factory = factory_or_none("discriminator", discriminator) if gan_on else None
        self.frozen_factories = {"perceptual": factory_or_none("perceptual", perceptual), "dino": factory_or_none("dino", dino)}
        # a plain dict, so the frozen networks are not submodules (see the module docstring)
        self.frozen: dict[str, nn.Module | None] = {}
        self._warned_off: set[str] = set()
        self.discriminator: nn.Module | None = None
        self.gan_start_step = gan_start_step
        self.adaptive_weight_max = adaptive_weight_max
        self.gradient_clip_val = gradient_clip_val
        self.dead_code_restart_every = dead_code_restart_every
        self._usage: torch.Tensor | None = None
        self._val_tokens: list[torch.Tensor] = []

    @property
    def tokenizer(self) -> ImageTokenizer:
        self.configure_model()
        return self.net  # type: ignore[return-value]

    def configure_model(self) -> None:
        """Build tokenizer and discriminator once (idempotent, as Lightning requires)."""
        super().configure_model()
        if self.discriminator is None and self.discriminator_factory is not None:
            self.discriminator = self.discriminator_factory()

    # ---- frozen loss networks -------------------------------------------------------------

    def setup(self, stage: str) -> None:
        if stage in ("fit", "validate"):
            self.load_frozen_networks()

    def load_frozen_networks(self) -> None:
        """Load the perceptual network and the DINO teacher once; log a warning for each loss that is off."""
        for name in FROZEN:
            if name not in self.frozen:
                factory = self.frozen_factories[name]
                use = factory is not None and getattr(self.weights, name) > 0
                self.frozen[name] = factory() if use else None
        off = [name for name in FROZEN if self.frozen[name] is None]
        if self.discriminator_factory is None:
            off.append("gan")
        for name in [n for n in off if n not in self._warned_off]:
            log.warning(OFF_WARNINGS[name])
            self._warned_off.add(name)

    def frozen_network(self, name: str, device: torch.device) -> nn.Module | None:
        """The loaded frozen network on `device` (moved on first use, a no-op afterwards), or None."""
        network = self.frozen.get(name)
        return None if network is None else network.to(device)

    # ---- losses --------------------------------------------------------------------------

    def reconstruction_terms(self, image: torch.Tensor, out: TokenizerOutput) -> dict[str, torch.Tensor]:
        """Weighted L1, L2 and perceptual terms of the image reconstruction loss (GAIA-1 §2.2)."""
        w, recon = self.weights, out.reconstruction
        terms = {"l1": w.l1 * F.l1_loss(recon, image), "l2": w.l2 * F.mse_loss(recon, image)}
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

    def losses(self, image: torch.Tensor, out: TokenizerOutput) -> dict[str, torch.Tensor]:
        """Weighted loss terms without the GAN term (as validated), and their total under 'loss'."""
        return self.generator_terms(image, out, with_gan=False)

    def generator_terms(self, image: torch.Tensor, out: TokenizerOutput, with_gan: bool) -> dict[str, torch.Tensor]:
        """`losses` plus, when `with_gan`, λ_GAN·w·GAN with w from the decoder's last-layer gradients."""
        reconstruction = self.reconstruction_terms(image, out)
        terms = {**reconstruction, **self.latent_terms(image, out)}
        loss = sum(terms.values())
        if with_gan:
            gan = hinge_generator_loss(self.discriminator(out.reconstruction))
            weight = adaptive_gan_weight(sum(reconstruction.values()), gan, self.tokenizer.last_layer, self.adaptive_weight_max)
            terms["gan"] = self.weights.gan * weight * gan
            loss = loss + terms["gan"]
            terms["adaptive_weight"] = weight
        terms["loss"] = loss
        return terms

    def discriminator_terms(self, image: torch.Tensor, fake: torch.Tensor) -> dict[str, torch.Tensor]:
        """Hinge loss of the discriminator on real images and (detached) reconstructions, plus its mean logits."""
        real_logits, fake_logits = self.discriminator(image), self.discriminator(fake)
        return {
            "disc_loss": hinge_discriminator_loss(real_logits, fake_logits),
            "logits_real": real_logits.detach().mean(),
            "logits_fake": fake_logits.detach().mean(),
        }

    def gan_active(self, step: int) -> bool:
        """True once `gan_start_step` generator steps are done (and a discriminator exists)."""
        return self.discriminator_factory is not None and step >= self.gan_start_step

    # ---- optimisation --------------------------------------------------------------------

    def configure_optimizers(self) -> Any:
        self.configure_model()
        optimizers = [self.optim_factory([p for p in self.net.parameters() if p.requires_grad])]
        if self.discriminator is not None:
            optimizers.append(self.optim_factory(self.discriminator.parameters()))
        if not self.sched_factory:  # sched=constant composes to an empty node
            return optimizers
        names = ("lr/generator", "lr/discriminator")
        schedulers = [{"scheduler": self.sched_factory(o), "interval": "step", "name": n} for o, n in zip(optimizers, names)]
        return optimizers, schedulers

    def configure_callbacks(self) -> list:
        # the earliest hook of fit, before Lightning's own check, so the error can name the config keys
        clip = self.trainer.gradient_clip_val
        if self.trainer.state.fn == "fit" and clip:
            raise ValueError(
                f"trainer.gradient_clip_val={clip}, but ImageTokenizerModule optimises generator and discriminator "
                f"by hand and clips both itself (model.gradient_clip_val={self.gradient_clip_val}): "
                "set trainer.gradient_clip_val=null"
            )
        return []

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> dict[str, torch.Tensor]:
        image = batch["image"]
        step = self.global_step  # generator steps so far: discriminator steps are not counted (see _step)
        with_gan = self.gan_active(step)
        opt_g, opt_d = self._optimizers()
        with self.toggled_optimizer(opt_g):  # no gradients into the discriminator from the generator loss
            out = self.tokenizer(image)
            terms = self.generator_terms(image, out, with_gan)
            self._step(opt_g, terms["loss"], counted=True)
        if with_gan:
            with self.toggled_optimizer(opt_d):
                terms.update(self.discriminator_terms(image, out.reconstruction.detach()))
                self._step(opt_d, terms["disc_loss"], counted=False)
        self._step_schedulers(with_gan)
        self.log_dict({f"train/{k}": v for k, v in terms.items() if k != "loss"})
        self.log("train/loss", terms["loss"], prog_bar=True)
        self._track_usage(out.tokens, image, step)
        return {k: v.detach() for k, v in terms.items()}

    def _optimizers(self) -> tuple[LightningOptimizer, LightningOptimizer | None]:
        optimizers = self.optimizers()
        optimizers = optimizers if isinstance(optimizers, list) else [optimizers]
        return optimizers[0], optimizers[1] if len(optimizers) > 1 else None

    def _step(self, optimizer: LightningOptimizer, loss: torch.Tensor, counted: bool) -> None:
        """zero_grad, backward, clip, step."""
        optimizer.zero_grad()
        self.manual_backward(loss)
        if self.gradient_clip_val:
            self.clip_gradients(optimizer, gradient_clip_val=self.gradient_clip_val, gradient_clip_algorithm="norm")
        if counted:
            optimizer.step()
        else:
            # Lightning counts every LightningOptimizer.step() as a trainer step (Lightning issue #17958);
            # stepping through the strategy keeps global_step == generator steps == batches, so
            # trainer.max_steps and gan_start_step mean what the paper's "steps" mean.
            self.trainer.strategy.optimizer_step(optimizer.optimizer, closure=do_nothing_closure)

    def _step_schedulers(self, with_gan: bool) -> None:
        schedulers = self.lr_schedulers()
        if schedulers is None:
            return
        schedulers = schedulers if isinstance(schedulers, list) else [schedulers]
        schedulers[0].step()
        if with_gan and len(schedulers) > 1:
            schedulers[1].step()  # the discriminator's schedule counts its own steps, from gan_start_step

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
        terms = self.losses(image, out)
        recon = out.reconstruction.clamp(-1, 1)
        self.log_dict({f"val/{k}": v for k, v in terms.items()}, prog_bar=False)
        self.log("val/psnr", psnr(recon, image).mean(), prog_bar=True)
        self.log("val/ssim", ssim(recon, image).mean())
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
        """What the Rerun media callback shows: inputs, reconstructions, token maps (hash and PCA colours, GAIA-1 Fig. 3)."""
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
