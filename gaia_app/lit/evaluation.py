"""A Lightning callback that computes evaluation metrics on the validation set (docs/evaluation.md).

Protocol: a LightningModule that can be evaluated defines
    evaluation_pair(batch) -> (real, generated)
two tensors of one shape in [-1, 1]: images (b, 3, H, W) or videos (b, t, 3, H, W) (reconstructions for a
tokenizer, decoded windows for a video decoder). The metrics stream over the first `max_batches` validation
batches of every `every_n_val_epochs`-th validation run and are logged as `eval/<name>` through the module's
loggers (Rerun, CSV, ...). Fréchet statistics and the PSNR/SSIM sums are all-reduced across DDP ranks, so every
rank logs the same value.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import lightning.pytorch as pl
import torch
import torch.distributed as dist

from gaia_app.encoders.perceptual import load_perceptual
from gaia_app.eval.feature_distance import fdd, fid
from gaia_app.eval.fvmd import FVMD
from gaia_app.eval.metrics import psnr, ssim

METRICS = ("psnr", "ssim", "lpips", "fvmd", "fid", "fdd")


class _Mean:
    """Running mean of per-item values, summed over DDP ranks at the end."""

    def __init__(self, fn):
        self.fn, self.total, self.count = fn, torch.zeros((), dtype=torch.float64), torch.zeros((), dtype=torch.float64)

    def update(self, real: torch.Tensor, generated: torch.Tensor) -> None:
        values = self.fn(generated.flatten(0, -4), real.flatten(0, -4)).double().cpu()
        self.total += values.sum()
        self.count += values.numel()

    def compute(self) -> float:
        both = torch.stack([self.total, self.count])
        if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
            dist.all_reduce(both, op=dist.ReduceOp.SUM)
        return float(both[0] / both[1].clamp_min(1))


class EvaluationCallback(pl.Callback):
    """Compute `metrics` (subset of METRICS) from `pl_module.evaluation_pair(batch)` on validation.

    fvmd needs videos of ≥ 3 frames; fid needs `fid_checkpoint` (local Inception-v3 FID weights); fdd needs
    `fdd_checkpoint` (a local DINO checkpoint, `fdd_kind`); lpips
    needs `lpips_checkpoint` (local VGG16 weights) and, for LPIPS proper, `lpips_heads_checkpoint` (without the
    heads it is the plain VGG feature distance).
    """

    def __init__(self, metrics: Sequence[str] = ("psnr", "ssim", "fvmd"), every_n_val_epochs: int = 1,
                 max_batches: int = 4, fid_checkpoint: str | None = None, fdd_checkpoint: str | None = None,
                 fdd_kind: str = "dino_vits16",
                 lpips_checkpoint: str | None = None, lpips_heads_checkpoint: str | None = None) -> None:
        super().__init__()
        unknown = sorted(set(metrics) - set(METRICS))
        if unknown or not metrics:
            raise ValueError(f"callbacks.evaluation.metrics={list(metrics)}: choose from {list(METRICS)}")
        if "fid" in metrics and not fid_checkpoint:
            raise ValueError("callbacks.evaluation.metrics has fid: set callbacks.evaluation.fid_checkpoint to local "
                             "Inception-v3 FID weights (docs/evaluation.md)")
        if "fdd" in metrics and not fdd_checkpoint:
            raise ValueError("callbacks.evaluation.metrics has fdd: set callbacks.evaluation.fdd_checkpoint to a local "
                             "DINO checkpoint (docs/tokenizer.md, 'Local checkpoints')")
        if "lpips" in metrics and not lpips_checkpoint:
            raise ValueError("callbacks.evaluation.metrics has lpips: set callbacks.evaluation.lpips_checkpoint "
                             "to local VGG16 weights (and lpips_heads_checkpoint to the LPIPS heads; "
                             "docs/tokenizer.md)")
        if every_n_val_epochs < 1 or max_batches < 1:
            raise ValueError("callbacks.evaluation: every_n_val_epochs and max_batches must be >= 1")
        self.metrics, self.every_n_val_epochs, self.max_batches = list(metrics), every_n_val_epochs, max_batches
        self.fid_checkpoint, self.fdd_checkpoint, self.fdd_kind = fid_checkpoint, fdd_checkpoint, fdd_kind
        self.lpips_checkpoint, self.lpips_heads_checkpoint = lpips_checkpoint, lpips_heads_checkpoint
        self._val_runs = 0
        self._state: dict[str, Any] | None = None

    def on_validation_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        self._val_runs += 1
        due = (self._val_runs - 1) % self.every_n_val_epochs == 0
        if due and not callable(getattr(pl_module, "evaluation_pair", None)):
            raise TypeError(f"callbacks.evaluation: {type(pl_module).__name__} has no evaluation_pair(batch) method")
        self._state = self._fresh_state() if due else None

    def _fresh_state(self) -> dict[str, Any]:
        state: dict[str, Any] = {}
        if "psnr" in self.metrics:
            state["psnr"] = _Mean(psnr)
        if "ssim" in self.metrics:
            state["ssim"] = _Mean(ssim)
        if "lpips" in self.metrics:
            state["lpips"] = _Mean(load_perceptual(checkpoint=self.lpips_checkpoint,
                                                   heads_checkpoint=self.lpips_heads_checkpoint,
                                                   config_key="callbacks.evaluation.lpips_checkpoint"))
        if "fvmd" in self.metrics:
            state["fvmd"] = FVMD()
        if "fid" in self.metrics:
            state["fid"] = fid(self.fid_checkpoint, "callbacks.evaluation.fid_checkpoint")
        if "fdd" in self.metrics:
            state["fdd"] = fdd(self.fdd_checkpoint, self.fdd_kind, "callbacks.evaluation.fdd_checkpoint")
        return state

    def on_validation_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any,
                                batch_idx: int, dataloader_idx: int = 0) -> None:
        if self._state is None or dataloader_idx != 0 or batch_idx >= self.max_batches:
            return
        with torch.no_grad():
            real, generated = pl_module.evaluation_pair(batch)
        if real.shape != generated.shape:
            raise ValueError(f"{type(pl_module).__name__}.evaluation_pair gave real {tuple(real.shape)} and "
                             f"generated {tuple(generated.shape)}: expected one shape")
        with torch.no_grad():
            self._update(pl_module, real.detach().float().cpu(), generated.detach().float().cpu())

    def _update(self, pl_module: pl.LightningModule, real: torch.Tensor, generated: torch.Tensor) -> None:
        for metric in self._state.values():
            if isinstance(metric, _Mean):
                metric.update(real, generated)
            elif isinstance(metric, FVMD):
                if real.ndim != 5:
                    raise ValueError(f"callbacks.evaluation: fvmd needs videos (b, t, 3, H, W), "
                                     f"{type(pl_module).__name__} gives {tuple(real.shape)}")
                metric.update(real, real=True).update(generated, real=False)
            else:
                metric.update(real, real=True).update(generated, real=False)

    def on_validation_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self._state is None:
            return
        for name, metric in self._state.items():
            pl_module.log(f"eval/{name}", metric.compute())
        self._state = None
