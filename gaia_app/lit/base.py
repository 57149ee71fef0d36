"""Shared Lightning plumbing: optimiser and schedule from `_partial_` configs, net built in configure_model."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import lightning as L
import torch
from torch import nn


class GaiaModule(L.LightningModule):
    """Base for every component.

    Args:
        net: a factory (Hydra `_partial_: true`) building the pure-torch network; built in
            `configure_model()` so FSDP/DeepSpeed can shard it (STYLE.md §10).
        optim: optimiser factory taking parameters (e.g. partial AdamW).
        sched: schedule factory taking the optimiser, or None for a constant LR.
    """

    def __init__(self, net: Callable[[], nn.Module], optim: Callable[..., torch.optim.Optimizer], sched: Callable | None = None):
        super().__init__()
        self.net_factory = net
        self.optim_factory = optim
        self.sched_factory = sched
        self.net: nn.Module | None = None

    def configure_model(self) -> None:
        """Build the network once (the hook runs at every stage and must be idempotent)."""
        if self.net is None:
            self.net = self.net_factory()

    def configure_optimizers(self) -> Any:
        self.configure_model()
        params = [p for p in self.trainer.model.parameters() if p.requires_grad] if self._trainer else self.parameters()
        optimizer = self.optim_factory(params)
        if not self.sched_factory:  # sched=constant composes to an empty node
            return optimizer
        scheduler = self.sched_factory(optimizer)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}
