"""Shared Lightning plumbing: optimiser and schedule from `_partial_` configs, net built in configure_model."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import lightning as L
import torch
from torch import nn
from torch.distributed.fsdp import FullyShardedDataParallel

from gaia_app.utils import threads
from gaia_app.weights.nets import NETS_RECORD

# layers whose weight matrices AdamW decays; everything else (embeddings, positions, null tokens, action
# projections, norms, biases, bare Parameters) is left alone: decaying a learned null token or a rarely-used
# embedding row pulls it to zero whatever the data says (GPT-2/minGPT practice)
DECAYED_LAYERS = (nn.Linear, nn.Conv1d, nn.Conv2d, nn.Conv3d, nn.ConvTranspose1d, nn.ConvTranspose2d,
                  nn.ConvTranspose3d)


def decay_groups(module: nn.Module, params: Iterable[nn.Parameter] | None = None) -> list[dict[str, Any]]:
    """Optimiser groups of `params` (default: the module's trainable ones): DECAYED_LAYERS weights keep the
    optimiser's weight decay, the rest get 0. A weight shared with an nn.Embedding (tied head) is not decayed."""
    params = [p for p in (module.parameters() if params is None else params) if p.requires_grad]
    embeddings = {id(m.weight) for m in module.modules() if isinstance(m, nn.Embedding)}
    decayed = {id(m.weight) for m in module.modules() if isinstance(m, DECAYED_LAYERS)} - embeddings
    groups = [{"params": [p for p in params if id(p) in decayed]},
              {"params": [p for p in params if id(p) not in decayed], "weight_decay": 0.0}]
    return [group for group in groups if group["params"]]


class GaiaModule(L.LightningModule):
    """Base for every component.

    Args:
        net: a factory (Hydra `_partial_: true`) building the pure-torch network; built in
            `configure_model()` so FSDP/DeepSpeed can shard it (STYLE.md §10).
        optim: optimiser factory taking parameters (e.g. partial AdamW).
        sched: schedule factory taking the optimiser, or None for a constant LR.
    """

    # what this module's checkpoints hold for inference (gaia_app/weights/nets.py reads it back, so loaders never
    # name LightningModule classes): the component and {net key of the model config: state-dict prefix}
    component: str | None = None
    net_prefixes: dict[str, str] = {"net": "net."}

    def __init__(self, net: Callable[[], nn.Module], optim: Callable[..., torch.optim.Optimizer],
                 sched: Callable | None = None):
        super().__init__()
        self.net_factory = net
        self.optim_factory = optim
        self.sched_factory = sched
        self.net: nn.Module | None = None

    def configure_model(self) -> None:
        """Build the network once (the hook runs at every stage and must be idempotent)."""
        if self.net is None:
            self.net = self.net_factory()

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Record which nets the checkpoint holds and under which state-dict prefixes."""
        if self.component is not None:
            checkpoint[NETS_RECORD] = {"component": self.component, "prefixes": dict(self.net_prefixes)}

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        """Follow the load other processes put on the CPUs (gaia_app/utils/threads.py; a clock read between counts)."""
        threads.tick()

    def clip_gradients(self, optimizer: torch.optim.Optimizer, gradient_clip_val: float | None = None,
                       gradient_clip_algorithm: str | None = None) -> None:
        """Clip as Lightning does (its `configure_gradient_clipping` hook calls this for `trainer.gradient_clip_val`),
        except under FSDP (`trainer=fsdp`): there each rank holds a shard of the gradients, so their global norm comes
        from FSDP's own `clip_grad_norm_`. Lightning's FSDP precision plugin refuses norm clipping instead (Lightning
        issue #19235), which stopped every experiment that clips at its first step."""
        wrapped = self.trainer.model if self._trainer is not None else None
        by_norm = (gradient_clip_algorithm or "norm") == "norm"
        if gradient_clip_val and by_norm and isinstance(wrapped, FullyShardedDataParallel):
            wrapped.clip_grad_norm_(gradient_clip_val)
            return
        super().clip_gradients(optimizer, gradient_clip_val, gradient_clip_algorithm)

    def configure_optimizers(self) -> Any:
        self.configure_model()
        optimizer = self.optim_factory(decay_groups(self.trainer.model if self._trainer else self))
        if not self.sched_factory:  # sched=constant composes to an empty node
            return optimizer
        scheduler = self.sched_factory(optimizer)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}
