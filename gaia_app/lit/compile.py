"""`torch.compile` of a trained net as a callback: `train.py compile.enabled=true` (see conf/train.yaml)."""

from __future__ import annotations

import lightning as L
from torch import nn


class CompileNet(L.Callback):
    """Compile `pl_module.net` in place (`nn.Module.compile`) once the strategy has wrapped or sharded it.

    In place, so parameter names, and with them checkpoints, are the same as an eager run's (a `torch.compile(net)`
    wrapper would prefix every key with `_orig_mod.`).

    Args:
        backend: torch.compile backend ("inductor"; "eager" only traces, for tests).
        mode: inductor mode (None, "reduce-overhead", "max-autotune").
        dynamic: dynamic shapes (None lets torch decide).
    """

    def __init__(self, backend: str = "inductor", mode: str | None = None, dynamic: bool | None = None):
        super().__init__()
        self.backend, self.mode, self.dynamic = backend, mode, dynamic

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        net = getattr(pl_module, "net", None)
        if not isinstance(net, nn.Module):
            raise ValueError(f"compile.enabled=true: {type(pl_module).__name__} has no `net` module to compile")
        net.compile(backend=self.backend, mode=self.mode, dynamic=self.dynamic)
