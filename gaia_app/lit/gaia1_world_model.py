"""Training of the GAIA-1 world model (GAIA-1 §2.3, §4.2).

Batch: {"tokens": (b, t, n) int64, "actions"?: (b, t, 2) float, "text"?: b lists of t captions}.
Absent keys mean absent conditions: the conditioner fills in its learned null embeddings.

Loss: eq. 1's cross-entropy on image tokens only, in nats/token with `*/perplexity` = exp(loss).
`train/loss` is drawn under the conditioning dropout of §4.2 (a random mode per example). Validation
scores every trained mode on every batch: `val/loss_unconditional`, `val/loss_actions`, `val/loss_text`
(and `val/loss_both` if its rate is > 0), each only when the batch carries what the mode conditions on;
`val/loss` is their mean weighted by the training rates, the expectation that `train/loss` estimates.
Gradient clipping (1.0, §4.2) is Lightning's `trainer.gradient_clip_val`, set by the world-model experiments.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import nn

from gaia_app.lit.captioned import CaptionedModule
from gaia_app.models.gaia1.world_model import DEFAULT_DROP, Conditions, WorldModel, next_token_loss

# mode of DEFAULT_DROP → (streams it drops, streams it needs in the batch)
MODE_STREAMS = {"unconditional": ({"text", "actions"}, set()), "actions": ({"text"}, {"actions"}),
                "text": ({"actions"}, {"text"}), "both": (set(), {"text", "actions"})}


class WorldModelModule(CaptionedModule):
    """GAIA-1 world model with its conditioning dropout and next-token objective.

    Args:
        net, optim, sched: see GaiaModule (§4.2: AdamW 1e-4, wd 0.1, betas 0.9/0.95; warm-up, cosine ÷10).
        text_encoder: factory of the text encoder (captions → (b, t, m, e)), or None (text never given).
        init_from: world-model training checkpoint, or a weights folder with world_model.safetensors (e.g. "gaia1",
            the shipped one), whose weights (net and text encoder, same preset) start a fresh fit: a fine-tune on
            other data with its own optimiser and schedule. A resumed run (ckpt_path) keeps its own weights.
    """

    component = "world_model"
    net_prefixes = {"net": "net.", "text_encoder": "text_encoder."}

    init_from_what = "a GAIA-1 world-model training checkpoint of the same preset"

    def __init__(self, net: Callable[[], WorldModel], optim: Callable, sched: Callable | None = None,
                 text_encoder: Callable[[], nn.Module] | None = None, init_from: str | None = None):
        super().__init__(net, optim, sched, text_encoder, init_from)

    @property
    def world_model(self) -> WorldModel:
        self.configure_model()
        return self.net  # type: ignore[return-value]

    def encode_text(self, batch: dict[str, Any]) -> torch.Tensor | None:
        """(b, t, m, e) text embeddings of the batch's captions; None without captions or without an encoder."""
        captions = batch.get("text")
        return self.text_encoder(captions) if captions is not None and self.text_encoder is not None else None

    def conditions(self, batch: dict[str, Any], text: torch.Tensor | None = None,
                   force_drop: dict[str, bool] | None = None) -> Conditions:
        """Condition tokens of a batch; training mode draws the conditioning dropout (GAIA-1 §2.3).
        text: the batch's encoded captions, if already computed."""
        tokens = batch["tokens"]
        text = self.encode_text(batch) if text is None else text
        return self.world_model.conditioner(tokens.shape[0], tokens.shape[1], text, batch.get("actions"), force_drop)

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        loss = next_token_loss(self.world_model, batch["tokens"], self.conditions(batch))
        self.log("train/loss", loss, prog_bar=True)
        self.log("train/perplexity", loss.detach().exp())
        return loss

    def mode_losses(self, batch: dict[str, Any]) -> dict[str, torch.Tensor]:
        """Loss of each conditioning mode trained with a rate > 0 whose streams the batch carries (§4.2)."""
        text = self.encode_text(batch)
        present = {name for name, value in (("text", text), ("actions", batch.get("actions"))) if value is not None}
        rates = dict(zip(DEFAULT_DROP, self.world_model.conditioner.mode_probs.tolist()))
        losses = {}
        for mode, (dropped, needed) in MODE_STREAMS.items():
            if rates[mode] > 0 and needed <= present:
                force = {name: name in dropped for name in ("text", "actions")}
                losses[mode] = next_token_loss(self.world_model, batch["tokens"], self.conditions(batch, text, force))
        if not losses:  # e.g. only the action mode is trained and the batch has no actions: it sees null conditions
            losses["unconditional"] = next_token_loss(self.world_model, batch["tokens"],
                                                      self.conditions(batch, text, {"text": True, "actions": True}))
        return losses

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        losses = self.mode_losses(batch)
        rates = dict(zip(DEFAULT_DROP, self.world_model.conditioner.mode_probs.tolist()))
        for mode, loss in losses.items():
            self.log(f"val/loss_{mode}", loss, sync_dist=True)
        weights = torch.tensor([rates[mode] or 1.0 for mode in losses], device=batch["tokens"].device)
        loss = (torch.stack(list(losses.values())) * weights).sum() / weights.sum()
        self.log("val/loss", loss, prog_bar=True, sync_dist=True)
        self.log("val/perplexity", loss.exp(), sync_dist=True)
