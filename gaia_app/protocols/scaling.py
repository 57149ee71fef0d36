"""Scaling-law sweep of the world model (GAIA-1 §6, Fig. 8): `python train.py experiment=gaia1/scaling`.

Each job of the Hydra sweep trains one world-model size; `ScalingPointCallback` writes its point (non-embedding
parameters N, training tokens, compute C = 6·N·tokens, final validation cross-entropy) to `scaling_point.json`.
When the sweep ends, `ScalingLawCallback` (a Hydra callback) fits f(C) = c + (C / a)^b to every point but the
largest-compute ones, predicts those, and writes `scaling_law.json`, `scaling_law.png` (Fig. 8a, 8b) and
`scaling_law.rrd` into the sweep dir. Refit a finished sweep with `python -m gaia_app.protocols.scaling <sweep dir>`.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
from hydra.experimental.callback import Callback as HydraCallback
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig

from gaia_app.eval.scaling import (
    PowerLaw,
    extrapolation_error,
    fit_power_law,
    non_embedding_parameters,
    training_compute,
)
from gaia_app.lit.strategies import block_types_of
from gaia_app.utils.run_dir import atomic_path, atomic_write_text

log = logging.getLogger(__name__)
POINT_FILE = "scaling_point.json"


class ScalingPointCallback(L.Callback):
    """Counts the image tokens the model is trained on and writes this run's scaling point at the end of fit.

    Args:
        metric: the validation cross-entropy to record (nats per image token).
        filename: written into the run dir (`trainer.default_root_dir`).
    """

    def __init__(self, metric: str = "val/loss", filename: str = POINT_FILE):
        super().__init__()
        self.metric, self.filename = metric, filename
        self.tokens = 0

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        self.tokens += int(batch["tokens"].numel()) * trainer.world_size

    def state_dict(self) -> dict[str, int]:
        return {"tokens": self.tokens}  # a resumed run keeps counting from its checkpoint

    def load_state_dict(self, state_dict: dict[str, int]) -> None:
        self.tokens = int(state_dict["tokens"])

    @rank_zero_only
    def on_fit_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.metric not in trainer.callback_metrics:
            raise KeyError(f"ScalingPointCallback: no {self.metric!r} in the final metrics "
                           f"({sorted(trainer.callback_metrics)}); validate at the last step (val_check_interval)")
        net = pl_module.net
        n = non_embedding_parameters(net, block_types_of(pl_module))
        point = {"non_embedding_parameters": n, "parameters": sum(p.numel() for p in net.parameters()),
                 "tokens": self.tokens, "compute": training_compute(n, self.tokens), "steps": trainer.global_step,
                 "val_loss": float(trainer.callback_metrics[self.metric])}
        atomic_write_text(Path(trainer.default_root_dir) / self.filename, json.dumps(point, indent=2))


def read_points(sweep_dir: Path) -> list[dict[str, Any]]:
    """Every job's scaling point under a sweep dir, by increasing compute."""
    points = [json.loads(p.read_text()) | {"job": p.parent.name} for p in sorted(sweep_dir.glob(f"*/{POINT_FILE}"))]
    return sorted(points, key=lambda p: p["compute"])


def fit_sweep(sweep_dir: Path, holdout: int = 1, tolerance: float = 0.05) -> dict[str, Any]:
    """Fit the law to all but the `holdout` largest-compute points, predict those; write JSON, PNG and .rrd."""
    points = read_points(sweep_dir)
    if len(points) < holdout + 3:
        raise ValueError(f"{sweep_dir}: {len(points)} scaling points ({POINT_FILE}); "
                         f"a fit needs 3 plus {holdout} held out")
    fitted, held = points[:-holdout], points[-holdout:]
    law = fit_power_law([p["compute"] for p in fitted], [p["val_loss"] for p in fitted])
    predictions = [{"job": p["job"], "compute": p["compute"], "val_loss": p["val_loss"],
                    "predicted": float(law(p["compute"])),
                    "relative_error": extrapolation_error(law, p["compute"], p["val_loss"])}
                   for p in held]
    result = {"law": law.as_dict(), "fitted": fitted, "held_out": predictions, "tolerance": tolerance,
              "compute_ratio": held[-1]["compute"] / fitted[-1]["compute"],
              "within_tolerance": all(p["relative_error"] <= tolerance for p in predictions)}
    atomic_write_text(sweep_dir / "scaling_law.json", json.dumps(result, indent=2))
    plot_scaling(points, law, len(fitted), sweep_dir / "scaling_law.png")
    log_scaling_to_rerun(points, law, len(fitted), sweep_dir / "scaling_law.rrd")
    return result


def plot_scaling(points: list[dict[str, Any]], law: PowerLaw, fitted: int, path: Path) -> None:
    """Fig. 8: (a) validation cross-entropy vs compute with the fit and the prediction; (b) vs parameters."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    compute = np.array([p["compute"] for p in points])
    loss = np.array([p["val_loss"] for p in points])
    params = np.array([p["non_embedding_parameters"] for p in points])
    curve = np.geomspace(compute.min() / 2, compute.max() * 2, 100)
    fig, (ax_c, ax_n) = plt.subplots(1, 2, figsize=(10, 4))
    ax_c.plot(curve, law(curve), "--", color="gray", label=f"fit c + (C/a)^b, b = {law.b:.3f}")
    ax_c.scatter(compute[:fitted], loss[:fitted], label="fitted runs")
    ax_c.scatter(compute[fitted:], loss[fitted:], marker="*", s=150, color="C3", label="held out (predicted)")
    ax_c.set(xscale="log", xlabel="training compute C = 6·N·tokens (FLOPs)", ylabel="validation cross-entropy (nats)",
             title="(a) loss vs compute")
    ax_c.legend()
    ax_n.scatter(params, loss, c=np.arange(len(points)) >= fitted, cmap="coolwarm")
    ax_n.set(xscale="log", xlabel="non-embedding parameters N", ylabel="validation cross-entropy (nats)",
             title="(b) loss vs parameters")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)


def log_scaling_to_rerun(points: list[dict[str, Any]], law: PowerLaw, fitted: int, path: Path) -> None:
    """Points and the fitted curve in log10(compute) × loss space (2D view), one recording file."""
    import rerun as rr

    rec = rr.RecordingStream("gaia_app", recording_id="scaling_law")
    with atomic_path(path) as tmp:
        rec.save(str(tmp))
        xy = np.array([[np.log10(p["compute"]), p["val_loss"]] for p in points])
        rec.log("scaling/fitted", rr.Points2D(xy[:fitted], radii=0.01, colors=[40, 120, 220]), static=True)
        rec.log("scaling/held_out", rr.Points2D(xy[fitted:], radii=0.02, colors=[220, 60, 40]), static=True)
        curve = np.geomspace(min(p["compute"] for p in points) / 2, max(p["compute"] for p in points) * 2, 100)
        rec.log("scaling/law", rr.LineStrips2D([np.stack([np.log10(curve), law(curve)], axis=1)]), static=True)
        rec.log("scaling/summary", rr.TextDocument(json.dumps({"law": law.as_dict(), "points": points}, indent=2)),
                static=True)
        rec.flush()
        rec.disconnect()


class ScalingLawCallback(HydraCallback):
    """Hydra callback: after the sweep, fit the law and report the held-out prediction (GAIA-1 §6)."""

    def __init__(self, holdout: int = 1, tolerance: float = 0.05):
        self.holdout, self.tolerance = holdout, tolerance

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        try:
            result = fit_sweep(sweep_dir, self.holdout, self.tolerance)
        except Exception:  # Hydra turns callback errors into warnings: say it loudly, with the refit command
            log.exception("scaling-law fit of %s failed; refit with `python -m gaia_app.protocols.scaling %s`",
                          sweep_dir, sweep_dir)
            raise
        log.info("%s", summary(result))


def summary(result: dict[str, Any]) -> str:
    law = result["law"]
    lines = [f"scaling law f(C) = {law['c']:.4f} + (C / {law['a']:.3g})^{law['b']:.4f} "
             f"fitted on {len(result['fitted'])} runs"]
    for p in result["held_out"]:
        lines.append(f"  held out {p['job']}: C = {p['compute']:.3g} "
                     f"({result['compute_ratio']:.1f}× the largest fitted), "
                     f"val loss {p['val_loss']:.4f}, predicted {p['predicted']:.4f}, "
                     f"error {100 * p['relative_error']:.2f}% "
                     f"(tolerance {100 * result['tolerance']:.0f}%)")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(
        description="Refit the scaling law of a finished `experiment=gaia1/scaling` sweep.")
    parser.add_argument("sweep_dir", type=Path)
    parser.add_argument("--holdout", type=int, default=1)
    parser.add_argument("--tolerance", type=float, default=0.05)
    args = parser.parse_args()
    print(summary(fit_sweep(args.sweep_dir, args.holdout, args.tolerance)))


if __name__ == "__main__":
    main()
