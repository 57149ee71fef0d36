"""Training of the GAIA-1 image tokenizer (GAIA-1 §2.2, §4.1).

Batch: {"image": (b, 3, H, W) float in [-1, 1]}.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from gaia_app.eval.metrics import codebook_perplexity, psnr, ssim
from gaia_app.lit.base import GaiaModule
from gaia_app.models.gaia1.tokenizer import ImageTokenizer, TokenizerOutput


class ImageTokenizerModule(GaiaModule):
    """Reconstruction (λ·L1 + λ·L2) and quantisation losses with the paper's weights (§4.1).

    Args:
        net, optim, sched: see GaiaModule.
        l1_weight, l2_weight, codebook_weight: GAIA-1 §4.1 λ values (0.2, 2.0, 1.0).
        dead_code_restart_every: every N optimiser steps, codes unused since the last restart are
            re-seeded from encoder outputs (0 disables). Keeps vocabulary usage up.
    """

    def __init__(
        self,
        net: Callable[[], ImageTokenizer],
        optim: Callable,
        sched: Callable | None = None,
        l1_weight: float = 0.2,
        l2_weight: float = 2.0,
        codebook_weight: float = 1.0,
        dead_code_restart_every: int = 0,
    ):
        super().__init__(net, optim, sched)
        self.l1_weight = l1_weight
        self.l2_weight = l2_weight
        self.codebook_weight = codebook_weight
        self.dead_code_restart_every = dead_code_restart_every
        self._usage: torch.Tensor | None = None
        self._val_tokens: list[torch.Tensor] = []

    @property
    def tokenizer(self) -> ImageTokenizer:
        self.configure_model()
        return self.net  # type: ignore[return-value]

    def losses(self, image: torch.Tensor, out: TokenizerOutput) -> dict[str, torch.Tensor]:
        """Weighted loss terms and their total under 'loss'."""
        terms = {
            "l1": self.l1_weight * F.l1_loss(out.reconstruction, image),
            "l2": self.l2_weight * F.mse_loss(out.reconstruction, image),
            "codebook": self.codebook_weight * (out.codebook_loss + out.commitment_loss),
        }
        terms["loss"] = sum(terms.values())
        return terms

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        image = batch["image"]
        out = self.tokenizer(image)
        terms = self.losses(image, out)
        self.log_dict({f"train/{k}": v for k, v in terms.items()}, prog_bar=False)
        self.log("train/loss", terms["loss"], prog_bar=True)
        self._track_usage(out.tokens, image)
        return terms["loss"]

    def _track_usage(self, tokens: torch.Tensor, image: torch.Tensor) -> None:
        if self.dead_code_restart_every <= 0:
            return
        k = self.tokenizer.codebook_size
        counts = torch.bincount(tokens.flatten(), minlength=k)
        self._usage = counts if self._usage is None else self._usage + counts
        if (self.global_step + 1) % self.dead_code_restart_every == 0:
            with torch.no_grad():
                features = self.tokenizer.encoder(image)
            restarted = self.tokenizer.quantizer.restart_dead_codes(features, self._usage)
            self.log("train/restarted_codes", float(restarted))
            self._usage = None

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
    def media(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """What the Rerun media callback shows: inputs, reconstructions, token maps (GAIA-1 Fig. 3)."""
        image = batch["image"]
        out = self.tokenizer(image)
        return {
            "val/input": image,
            "val/reconstruction": out.reconstruction.clamp(-1, 1),
            "val/tokens": out.tokens,
        }

    def codebook_embeddings(self) -> nn.Parameter:
        """(k, e) code vectors, for the PCA colouring of token maps."""
        return self.tokenizer.quantizer.codebook.weight
