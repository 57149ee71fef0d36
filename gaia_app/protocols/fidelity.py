"""Fidelity of rollouts against real continuations: the metrics every rollout table shares (issue 49 item 4).

`score` compares candidate futures with the real ones (both (b, t0 + f, 3, H, W), scored from frame t0 − 1 on):
psnr / ssim / lpips per generated frame, fvmd (a Fréchet distance on motion features, nothing to load) between the
sets of clips, fid / fdd over future frames, agent_iou of a segmentation probe. lpips, fid and fdd need local
weights (DESIGN.md §6: nothing downloads): `check_metrics` names the missing one before any work, `feature_metrics`
loads them once for every row. The settings node holds `metrics` and the checkpoints (`evaluate` for
mode=evaluate, `controllability.fidelity` for the controllability table).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

from gaia_app.encoders.perceptual import load_perceptual
from gaia_app.eval.agent_iou import agent_iou
from gaia_app.eval.feature_distance import fdd, fid
from gaia_app.eval.fvmd import FVMD
from gaia_app.eval.metrics import psnr, ssim
from gaia_app.models.probes import AgentSegmentationProbe

METRICS = ("psnr", "ssim", "lpips", "fvmd", "fid", "fdd", "agent_iou")


def check_metrics(settings: Any, where: str = "evaluate") -> None:
    """Named errors for unknown metrics and for fid / fdd / lpips without their local checkpoints; `settings` is
    the node at `where` (its metrics and checkpoint keys)."""
    e = settings
    unknown = sorted(set(e.metrics) - set(METRICS))
    if unknown or not e.metrics:
        raise ValueError(f"{where}.metrics={list(e.metrics)}: choose from {list(METRICS)}")
    if "fid" in e.metrics and not e.fid_checkpoint:
        raise ValueError(f"{where}.metrics has fid: set {where}.fid_checkpoint to local Inception-v3 FID weights")
    if "fdd" in e.metrics and not e.fdd_checkpoint:
        raise ValueError(f"{where}.metrics has fdd: set {where}.fdd_checkpoint to a local DINO checkpoint")
    if "lpips" in e.metrics and not e.lpips_checkpoint:
        raise ValueError(f"{where}.metrics has lpips: set {where}.lpips_checkpoint to local VGG16 weights "
                         f"(and {where}.lpips_heads_checkpoint to the LPIPS heads)")


def feature_metrics(settings: Any, where: str = "evaluate") -> dict[str, Any]:
    """The networks of the chosen lpips / fid / fdd metrics of the settings node at `where`, loaded once for every
    row."""
    e, out = settings, {}
    if "lpips" in e.metrics:
        out["lpips"] = load_perceptual(checkpoint=e.lpips_checkpoint, heads_checkpoint=e.lpips_heads_checkpoint,
                                       config_key=f"{where}.lpips_checkpoint")
    if "fid" in e.metrics:
        out["fid"] = fid(e.fid_checkpoint, f"{where}.fid_checkpoint")
    if "fdd" in e.metrics:
        out["fdd"] = fdd(e.fdd_checkpoint, e.fdd_kind, f"{where}.fdd_checkpoint")
    return out


def score(metrics: Sequence[str], real: torch.Tensor, candidate: torch.Tensor, t0: int,
          networks: dict[str, Any] | None = None,
          agents: tuple[AgentSegmentationProbe, torch.Tensor] | None = None) -> dict[str, float]:
    """Metrics of candidate futures against real ones; both (b, t0 + f, 3, H, W), scored from frame t0 − 1 on.
    networks: `feature_metrics` (lpips distance, fid / fdd metrics whose networks each row reuses); agents: the agent
    probe and the real clips' agent masks (b, t0 + f, H, W), for agent_iou."""
    networks, out = networks or {}, {}
    real_future, future = real[:, t0:].flatten(0, 1), candidate[:, t0:].flatten(0, 1)
    if "psnr" in metrics:
        out["psnr"] = float(psnr(future, real_future).mean())
    if "ssim" in metrics:
        out["ssim"] = float(ssim(future, real_future).mean())
    if "lpips" in metrics:
        with torch.no_grad():
            out["lpips"] = float(networks["lpips"](future, real_future).mean())
    if "fvmd" in metrics:
        out["fvmd"] = FVMD().update(real[:, t0 - 1:], real=True).update(candidate[:, t0 - 1:], real=False).compute()
    for name in ("fid", "fdd"):
        if name in metrics:
            out[name] = networks[name].fresh().update(real_future, real=True).update(future, real=False).compute()
    if agents is not None:
        out["agent_iou"] = agent_iou(agents[0], candidate[:, t0:], agents[1][:, t0:])
    return out


ARROWS = {"psnr": "↑", "ssim": "↑", "lpips": "↓", "fvmd": "↓", "fid": "↓", "fdd": "↓", "agent_iou": "↑"}


def held_frame(real: torch.Tensor, t0: int) -> torch.Tensor:
    """Clips (b, T, 3, H, W) whose future repeats the last context frame t0 − 1: a future that never moves."""
    return torch.cat([real[:, :t0], real[:, t0 - 1:t0].expand(-1, real.shape[1] - t0, -1, -1, -1)], 1)


def fidelity_table(settings: Any, where: str, real: torch.Tensor, candidates: dict[str, torch.Tensor],
                   t0: int) -> dict[str, Any]:
    """{metrics, rows: {name: scores}}: each candidate (b, T, 3, H, W) against the real clips, with the metrics of
    the settings node at `where` (networks loaded once for every row)."""
    metrics, networks = list(settings.metrics), feature_metrics(settings, where)
    return {"metrics": metrics, "rows": {name: score(metrics, real, video, t0, networks)
                                         for name, video in candidates.items()}}


def table_markdown(table: dict[str, Any], names: dict[str, str]) -> list[str]:
    """A `fidelity_table` as markdown lines, rows labelled by `names` (key → label)."""
    metrics = table["metrics"]
    lines = ["| futures vs real continuations | " + " | ".join(f"{m} {ARROWS[m]}" for m in metrics) + " |",
             "|---" * (len(metrics) + 1) + "|"]
    return lines + [f"| {names[key]} | " + " | ".join(f"{row[m]:.3f}" for m in metrics) + " |"
                    for key, row in table["rows"].items()]
