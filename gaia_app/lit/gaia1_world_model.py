"""Training of the GAIA-1 world model (GAIA-1 §2.3, §4.2).

Batch: {"tokens": (b, t, n) int64, "actions"?: (b, t, 2) float, "text"?: b lists of t captions}.
Absent keys mean absent conditions: the conditioner fills in its learned null embeddings.

Loss: eq. 1's cross-entropy on image tokens only, logged as `train/loss` and `val/loss` in
nats/token with `*/perplexity` = exp(loss). Gradient clipping (1.0, §4.2) is Lightning's
`trainer.gradient_clip_val`, set by the world-model experiments.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import nn

from gaia_app.lit.base import GaiaModule
from gaia_app.models.gaia1.world_model import Conditions, WorldModel, next_token_loss


class WorldModelModule(GaiaModule):
    """GAIA-1 world model with its conditioning dropout and next-token objective.

    Args:
        net, optim, sched: see GaiaModule (§4.2: AdamW 1e-4, wd 0.1, betas 0.9/0.95; warm-up, cosine ÷10).
        text_encoder: factory of the text encoder (captions → (b, t, m, e)), or None (text never given).
    """

    def __init__(self, net: Callable[[], WorldModel], optim: Callable, sched: Callable | None = None,
                 text_encoder: Callable[[], nn.Module] | None = None):
        super().__init__(net, optim, sched)
        self.text_encoder_factory = text_encoder if callable(text_encoder) else None
        self.text_encoder: nn.Module | None = None

    @property
    def world_model(self) -> WorldModel:
        self.configure_model()
        return self.net  # type: ignore[return-value]

    def configure_model(self) -> None:
        """Build the world model and the text encoder once (idempotent)."""
        super().configure_model()
        if self.text_encoder is None and self.text_encoder_factory is not None:
            self.text_encoder = self.text_encoder_factory()

    def conditions(self, batch: dict[str, Any]) -> Conditions:
        """Condition tokens of a batch; training mode draws the conditioning dropout (GAIA-1 §2.3)."""
        tokens, captions = batch["tokens"], batch.get("text")
        # captions without an encoder (text_encoder=null) count as absent text
        text = self.text_encoder(captions) if captions is not None and self.text_encoder is not None else None
        return self.world_model.conditioner(tokens.shape[0], tokens.shape[1], text, batch.get("actions"))

    def step(self, batch: dict[str, Any], split: str) -> torch.Tensor:
        loss = next_token_loss(self.world_model, batch["tokens"], self.conditions(batch))
        self.log(f"{split}/loss", loss, prog_bar=True, sync_dist=split == "val")
        self.log(f"{split}/perplexity", loss.detach().exp(), sync_dist=split == "val")
        return loss

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        return self.step(batch, "train")

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        self.step(batch, "val")
