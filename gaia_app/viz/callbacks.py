"""Lightning callbacks that put media (reconstructions, rollouts, token maps) into the Rerun recording.

Protocol: a LightningModule that wants media in Rerun defines
    media(batch) -> dict[str, value]
where each key is an entity path (`val/reconstruction`) and each value is one of
    (b, c, h, w) float in [-1, 1] or uint8          -> image grid of the first max_items
    (b, t, c, h, w)                                 -> videos side by side, one image per frame
    (b, v, t, c, h, w)                              -> first item, camera views side by side
    (b, h, w) integer                               -> token maps, hash colour per token id
    ((b, h, w) integer, (K, d) codebook) tuple      -> token maps, PCA colours (GAIA-1 Fig. 3)
    str or list[str]                                -> text log rows
Images and token maps sit on the `step` timeline (trainer.global_step); videos additionally
on the `frame` timeline (frame 0..t-1).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import lightning.pytorch as pl
import rerun as rr
import torch
from lightning.pytorch.utilities import rank_zero_warn

from gaia_app.viz.media import log_images, log_token_map, log_video, video_grid
from gaia_app.viz.rerun_logger import rerun_logger_of


def _is_text(value: Any) -> bool:
    return isinstance(value, str) or (
        isinstance(value, (list, tuple)) and len(value) > 0 and all(isinstance(v, str) for v in value)
    )


class RerunMediaCallback(pl.Callback):
    """Log `pl_module.media(batch)` for the first validation batch every `every_n_val_epochs`.

    `media` runs on every rank, because sharded models (FSDP, DeepSpeed ZeRO-3) need all ranks
    in each forward; only rank 0 writes. Sanity-check validation is skipped. Does nothing
    when the trainer has no RerunLogger or the module has no `media` method.
    """

    def __init__(self, every_n_val_epochs: int = 1, max_items: int = 4, jpeg_quality: int | None = 90) -> None:
        super().__init__()
        if every_n_val_epochs < 1 or max_items < 1:
            raise ValueError("every_n_val_epochs and max_items must be >= 1")
        self.every_n_val_epochs = every_n_val_epochs
        self.max_items = max_items
        self.jpeg_quality = jpeg_quality
        self._val_runs = 0  # validation loops seen, sanity check excluded

    def on_validation_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not trainer.sanity_checking:
            self._val_runs += 1

    def on_validation_batch_end(
        self,
        trainer: pl.Trainer,
        pl_module: pl.LightningModule,
        outputs: Any,
        batch: Any,
        batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        if not self._due(trainer, pl_module, batch_idx, dataloader_idx):
            return
        with torch.no_grad():
            media = pl_module.media(batch)
        if trainer.is_global_zero:
            self.log_media(trainer, media)

    def _due(self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch_idx: int, dataloader_idx: int) -> bool:
        """True on the first batch of the first dataloader of every n-th real validation loop."""
        return (
            batch_idx == 0
            and dataloader_idx == 0
            and not trainer.sanity_checking
            and (self._val_runs - 1) % self.every_n_val_epochs == 0
            and callable(getattr(pl_module, "media", None))
            and rerun_logger_of(trainer) is not None
        )

    def log_media(self, trainer: pl.Trainer, media: Mapping[str, Any]) -> None:
        """Log each entry of a media dict at trainer.global_step (rank 0 only)."""
        logger = rerun_logger_of(trainer)
        rec = logger.experiment
        rec.set_time("step", sequence=trainer.global_step)
        visual = [path for key, value in media.items() if (path := self._log_entry(rec, key, value))]
        logger.add_media_paths(visual)

    def _log_entry(self, rec: rr.RecordingStream, key: str, value: Any) -> str | None:
        """Log one media entry; returns its entity path when it is visual, None for text/skipped."""
        path = "/" + key.strip("/")
        n = self.max_items
        if _is_text(value):
            for line in [value] if isinstance(value, str) else value[:n]:
                rec.log(path, rr.TextLog(line))
            return None
        if isinstance(value, tuple) and len(value) == 2:
            log_token_map(rec, path, value[0][:n], codebook=value[1])
        elif not isinstance(value, torch.Tensor):
            rank_zero_warn(f"RerunMediaCallback: {key!r} is a {type(value).__name__}, not a tensor; skipped")
            return None
        elif value.ndim == 3 and not value.is_floating_point():
            log_token_map(rec, path, value[:n])
        elif value.ndim == 4:
            log_images(rec, path, value[:n], jpeg_quality=self.jpeg_quality)
        elif value.ndim == 5:
            log_video(rec, path, video_grid(value[:n]), jpeg_quality=self.jpeg_quality)
        elif value.ndim == 6:
            views = value[0]  # (v, t, c, h, w): one row of camera views per frame
            log_video(rec, path, video_grid(views, ncols=views.shape[0]), jpeg_quality=self.jpeg_quality)
        else:
            rank_zero_warn(f"RerunMediaCallback: {key!r} has unsupported shape {tuple(value.shape)}; skipped")
            return None
        return path
