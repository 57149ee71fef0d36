"""Training callbacks of the Lightning layer."""

from __future__ import annotations

import lightning.pytorch as pl
from lightning.pytorch.callbacks import ModelCheckpoint


class FinalStepCheckpoint(ModelCheckpoint):
    """ModelCheckpoint whose last.ckpt also holds the final step of a run.

    Lightning's ModelCheckpoint writes last.ckpt every `every_n_train_steps`, and at the end of training only if no
    last.ckpt was written before: a run of max_steps=2600 checkpointed every 250 steps ends with last.ckpt at step
    2500, and its last 100 steps are lost to `generate.py`, `mode=export` and `ckpt_path=last`. The same holds for a
    run stopped by `trainer.max_time` between two checkpoints."""

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self.save_last and self._last_global_step_saved != trainer.global_step:
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
        super().on_train_end(trainer, pl_module)
