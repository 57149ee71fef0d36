"""Plumbing shared by the autoencoders trained with reconstruction + frozen-network + GAN losses
(GAIA-1 image tokenizer, GAIA-2 video tokenizer).

Optimisation is manual, with two optimisers: every batch takes one generator step and, once the GAN
is active, one discriminator step on the hinge loss. `trainer.global_step` counts generator steps only.

The frozen networks (perceptual, DINO teacher) are loaded from local checkpoints when fitting or
validating starts. They are kept out of the module tree on purpose: they are not in the state dict, so
checkpoints stay small and `load_module` works without the teacher files. They are in no optimiser,
and DDP/FSDP wrapping and precision casts leave them alone.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import torch
from lightning.pytorch.core.optimizer import LightningOptimizer, do_nothing_closure
from torch import nn

from gaia_app.lit.base import GaiaModule, decay_groups
from gaia_app.nn.discriminator import adaptive_gan_weight, hinge_discriminator_loss, hinge_generator_loss

log = logging.getLogger(__name__)


def pixel_terms(recon: torch.Tensor, target: torch.Tensor, l1: float, l2: float,
                pixels: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """λ_L1·L1 and λ_L2·L2 of a reconstruction, each pixel weighted by `pixels` (broadcast, mean 1) where given."""
    if pixels is None:
        return {"l1": l1 * (recon - target).abs().mean(), "l2": l2 * (recon - target).pow(2).mean()}
    return {"l1": l1 * (pixels * (recon - target).abs()).mean(), "l2": l2 * (pixels * (recon - target).pow(2)).mean()}


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


class AdversarialModule(GaiaModule):
    """Generator (the net) + optional discriminator, frozen loss networks, manual two-optimiser steps.

    Args:
        net, optim, sched: see GaiaModule; `optim` and `sched` build both optimisers and schedules.
        discriminator: discriminator factory, or None (GAN loss off).
        frozen: {name: factory or none} of frozen loss networks; `weight_of(name)` > 0 switches each on.
        gan_start_step: generator steps before the discriminator trains and the GAN term enters.
        adaptive_weight_max: clamp of VQGAN's adaptive GAN weight.
        gradient_clip_val: norm clipping of each optimiser's gradients (None/0: off). Lightning's
            `trainer.gradient_clip_val` must be null: it is not supported with manual optimisation.
    Subclasses set `off_warnings` ({name: message}, "gan" included) and implement `weight_of`.
    """

    off_warnings: Mapping[str, str] = {}

    def __init__(self, net: Callable[[], nn.Module], optim: Callable, sched: Callable | None,
                 discriminator: Callable[[], nn.Module] | None, frozen: Mapping[str, Any], gan_start_step: int,
                 adaptive_weight_max: float, gradient_clip_val: float | None):
        super().__init__(net, optim, sched)
        self.automatic_optimization = False
        gan_on = not is_off(discriminator) and self.weight_of("gan") > 0
        self.discriminator_factory = factory_or_none("discriminator", discriminator) if gan_on else None
        self.frozen_factories = {name: factory_or_none(name, spec) for name, spec in frozen.items()}
        # a plain dict, so the frozen networks are not submodules (see the module docstring)
        self.frozen: dict[str, nn.Module | None] = {}
        self._warned_off: set[str] = set()
        self.discriminator: nn.Module | None = None
        self.gan_start_step = gan_start_step
        self.adaptive_weight_max = adaptive_weight_max
        self.gradient_clip_val = gradient_clip_val

    def weight_of(self, name: str) -> float:
        """λ of the loss term `name` (0 switches it off)."""
        return float(getattr(self.weights, name))

    def configure_model(self) -> None:
        """Build generator and discriminator once (idempotent, as Lightning requires)."""
        super().configure_model()
        if self.discriminator is None and self.discriminator_factory is not None:
            self.discriminator = self.discriminator_factory()

    # ---- frozen loss networks -------------------------------------------------------------

    def setup(self, stage: str) -> None:
        if stage in ("fit", "validate"):
            self.load_frozen_networks()

    def load_frozen_networks(self) -> None:
        """Load every frozen network once; log a warning for each loss that is off."""
        for name, factory in self.frozen_factories.items():
            if name not in self.frozen:
                self.frozen[name] = factory() if factory is not None and self.weight_of(name) > 0 else None
        off = [name for name in self.frozen_factories if self.frozen[name] is None]
        if self.discriminator_factory is None:
            off.append("gan")
        for name in [n for n in off if n not in self._warned_off and n in self.off_warnings]:
            log.warning(self.off_warnings[name])
            self._warned_off.add(name)

    def frozen_network(self, name: str, device: torch.device) -> nn.Module | None:
        """The loaded frozen network on `device` (moved on first use, a no-op afterwards), or None."""
        network = self.frozen.get(name)
        return None if network is None else network.to(device)

    # ---- GAN ---------------------------------------------------------------------------

    def gan_active(self, step: int) -> bool:
        """True once `gan_start_step` generator steps are done (and a discriminator exists)."""
        return self.discriminator_factory is not None and step >= self.gan_start_step

    def discriminator_terms(self, real: torch.Tensor, fake: torch.Tensor) -> dict[str, torch.Tensor]:
        """Hinge loss of the discriminator on real inputs and (detached) reconstructions, plus its mean logits."""
        real_logits, fake_logits = self.discriminator(real), self.discriminator(fake)
        return {
            "disc_loss": hinge_discriminator_loss(real_logits, fake_logits),
            "logits_real": real_logits.detach().mean(),
            "logits_fake": fake_logits.detach().mean(),
        }

    def add_gan_term(self, terms: dict[str, torch.Tensor], reconstruction: torch.Tensor, fake: torch.Tensor,
                     last_layer: torch.Tensor) -> None:
        """Add λ_GAN·w·GAN (and w) to `terms` in place: the hinge generator loss of `fake` (in the discriminator's
        layout), w VQGAN's adaptive weight balancing it against the `reconstruction` loss at `last_layer`."""
        gan = hinge_generator_loss(self.discriminator(fake))
        weight = adaptive_gan_weight(reconstruction, gan, last_layer, self.adaptive_weight_max)
        terms["gan"] = self.weight_of("gan") * weight * gan
        terms["adaptive_weight"] = weight

    def adversarial_step(self, generate: Callable[[bool], tuple[dict[str, torch.Tensor], Any]],
                         real_and_fake: Callable[[Any], tuple[torch.Tensor, torch.Tensor]],
                         ) -> tuple[dict[str, torch.Tensor], Any]:
        """One generator step on `generate(with_gan)` → (terms with "loss", output), then, once the GAN is active,
        one discriminator step on `real_and_fake(output)` (the fake is detached here). Returns (terms, output)."""
        with_gan = self.gan_active(self.global_step)
        opt_g, opt_d = self._optimizers()
        with self.toggled_optimizer(opt_g):  # no gradients into the discriminator from the generator loss
            terms, out = generate(with_gan)
            self._step(opt_g, terms["loss"], counted=True)
        if with_gan:
            with self.toggled_optimizer(opt_d):
                real, fake = real_and_fake(out)
                terms.update(self.discriminator_terms(real, fake.detach()))
                self._step(opt_d, terms["disc_loss"], counted=False)
        self._step_schedulers(with_gan)
        self.log_dict({f"train/{k}": v for k, v in terms.items() if k != "loss"})
        self.log("train/loss", terms["loss"], prog_bar=True)
        return terms, out

    # ---- optimisation --------------------------------------------------------------------

    def generator_parameters(self) -> Iterable[nn.Parameter]:
        """What the generator optimiser updates (default: every trainable net parameter)."""
        return [p for p in self.net.parameters() if p.requires_grad]

    def configure_optimizers(self) -> Any:
        self.configure_model()
        optimizers = [self.optim_factory(decay_groups(self.net, self.generator_parameters()))]
        if self.discriminator is not None:
            optimizers.append(self.optim_factory(decay_groups(self.discriminator)))
        if not self.sched_factory:  # sched=constant composes to an empty node
            return optimizers
        names = ("lr/generator", "lr/discriminator")
        schedulers = [{"scheduler": self.sched_factory(o), "interval": "step", "name": n}
                      for o, n in zip(optimizers, names)]
        return optimizers, schedulers

    def configure_callbacks(self) -> list:
        # the earliest hook of fit, before Lightning's own check, so the error can name the config keys
        clip = self.trainer.gradient_clip_val
        if self.trainer.state.fn == "fit" and clip:
            raise ValueError(
                f"trainer.gradient_clip_val={clip}, but {type(self).__name__} optimises generator and discriminator "
                f"by hand and clips both itself (model.gradient_clip_val={self.gradient_clip_val}): "
                "set trainer.gradient_clip_val=null"
            )
        return []

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
            # trainer.max_steps and gan_start_step mean what the papers' "steps" mean.
            self.trainer.strategy.optimizer_step(optimizer.optimizer, closure=do_nothing_closure)

    def _step_schedulers(self, with_gan: bool) -> None:
        schedulers = self.lr_schedulers()
        if schedulers is None:
            return
        schedulers = schedulers if isinstance(schedulers, list) else [schedulers]
        schedulers[0].step()
        if with_gan and len(schedulers) > 1:
            schedulers[1].step()  # the discriminator's schedule counts its own steps, from gan_start_step
