"""What the GAIA-1 and GAIA-2 world-model LightningModules share: a net with an optional caption encoder built beside
it, and a fresh fit started from the weights of another run or of a weights folder (`model.init_from`)."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from gaia_app.lit.base import GaiaModule
from gaia_app.lit.checkpoint import load_net_weights


class CaptionedModule(GaiaModule):
    """A GaiaModule whose net reads captions through `text_encoder` (built in configure_model, like the net).

    Args:
        text_encoder: factory of the caption encoder, or None (captions never given).
        init_from: a training checkpoint of this component, or a weights folder holding `<component>.safetensors`
            (e.g. a shipped name), whose net weights start a fresh fit; a resumed run (ckpt_path) keeps its own.
    Subclasses name the checkpoint `init_from` should be in `init_from_what` (for errors).
    """

    init_from_what = "a training checkpoint of the same preset"

    def __init__(self, net: Callable[[], nn.Module], optim: Callable[..., torch.optim.Optimizer],
                 sched: Callable | None = None, text_encoder: Callable[[], nn.Module] | None = None,
                 init_from: str | None = None):
        super().__init__(net, optim, sched)
        self.text_encoder_factory = text_encoder if callable(text_encoder) else None
        self.text_encoder: nn.Module | None = None
        self.init_from = init_from

    def configure_model(self) -> None:
        """Build the net and the caption encoder once (idempotent)."""
        super().configure_model()
        if self.text_encoder is None and self.text_encoder_factory is not None:
            self.text_encoder = self.text_encoder_factory()

    def on_fit_start(self) -> None:
        if self.init_from and self.trainer.ckpt_path is None:
            self.load_init_weights()

    def load_init_weights(self) -> None:
        """Copy the net (and a trained caption encoder) weights of `init_from` in place (the optimiser state stays
        bound to the same tensors)."""
        self.configure_model()
        load_net_weights(self.net, self.init_from, self.init_from_what, component=self.component)
        # pretrained encoders (MiniLM, T5, CLIP) are frozen and read from their own files; only a trained encoder
        # (model/text_encoder=learned) is part of what the net learned to read, and lives in the checkpoint
        if self.text_encoder is not None and any(p.requires_grad for p in self.text_encoder.parameters()):
            load_net_weights(self.text_encoder, self.init_from, self.init_from_what, prefix="text_encoder.",
                             component=self.component)
