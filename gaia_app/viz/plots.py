"""Analysis plots: matplotlib PNGs (Agg canvas, no display) and Rerun scalar curves (GAIA-1 Fig. 6).

Legend: n image tokens per frame (token positions).

Curves are {strategy: (n,) perplexity per token position} for the strategies "real", "argmax",
"sample" and "top_k" (see gaia_app.eval.token_perplexity). Rerun entities:
  /analysis/token_perplexity/<strategy>      perplexity on the `token_position` timeline
  /analysis/token_log_perplexity/<strategy>  log-perplexity (nats): Rerun 0.41's plot axes have no
                                             log scale, so this is the view that reads like Fig. 6
  /analysis/summary                          static Markdown of the summary statistics
"""

from __future__ import annotations

import io
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from gaia_app.utils.run_dir import atomic_path, atomic_write_bytes

ArrayLike = torch.Tensor | np.ndarray

ROOT = "analysis/token_perplexity"
LOG_ROOT = "analysis/token_log_perplexity"
POSITION = "token_position"
COLORS = {"real": (90, 90, 90), "argmax": (31, 119, 180), "sample": (214, 39, 40), "top_k": (44, 160, 44)}
# Fig. 6's panels: each generation strategy against the real frame
PANELS = ("argmax", "sample", "top_k")


def label(strategy: str, k: int | None = None) -> str:
    """Legend name of a strategy ("top_k" → "top-k=50")."""
    return f"top-k={k}" if strategy == "top_k" and k is not None else strategy.replace("_", "-")


def _numpy(curve: ArrayLike) -> np.ndarray:
    """(n,) tensor or array → float64 numpy."""
    if isinstance(curve, torch.Tensor):
        curve = curve.detach().cpu().double().numpy()
    return np.asarray(curve, dtype=np.float64)


def token_perplexity_figure(curves: Mapping[str, ArrayLike], k: int | None = None, title: str | None = None) -> Figure:
    """Fig. 6 as one row of panels: argmax, sampling, top-k, each over the real frame's curve; log-y.

    curves: {strategy: (n,) perplexity}; a panel whose strategy is absent is left out.
    """
    panels = [s for s in PANELS if s in curves]
    fig = Figure(figsize=(5 * len(panels), 3.6), layout="constrained")
    FigureCanvasAgg(fig)  # Agg canvas on this figure only: no pyplot, no global backend, no display
    axes = fig.subplots(1, len(panels), sharey=True, squeeze=False)[0]
    for ax, (tag, strategy) in zip(axes, zip("abc", panels)):
        for name in ("real", strategy) if "real" in curves else (strategy,):
            y = _numpy(curves[name])
            ax.plot(np.arange(len(y)), y, lw=0.8, color=np.array(COLORS[name]) / 255, label=label(name, k))
        ax.set(yscale="log", xlabel="token position", title=f"({tag}) {label(strategy, k)}")
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    axes[0].set_ylabel("perplexity")
    if title:
        fig.suptitle(title)
    return fig


class RerunDisabled(Exception):
    """Raised inside `atomic_path` to discard the empty file of a disabled recording."""


def save_figure(fig: Figure, path: str | Path, dpi: int = 120) -> Path:
    """Render `fig` as PNG into memory, then write it atomically; returns the path."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)


def token_perplexity_blueprint() -> rrb.Blueprint:
    """Log-perplexity curves (the Fig. 6 view) above the raw perplexities, summary on the side."""
    curves = rrb.Vertical(
        rrb.TimeSeriesView(origin=LOG_ROOT, name="log-perplexity (nats) vs token position"),
        rrb.TimeSeriesView(origin=ROOT, name="perplexity vs token position"),
    )
    return rrb.Blueprint(rrb.Horizontal(curves, rrb.TextDocumentView(origin="/analysis/summary", name="summary"),
                                        column_shares=[3, 1]), collapse_panels=True)


def log_token_perplexity(rec: rr.RecordingStream, curves: Mapping[str, ArrayLike], k: int | None = None,
                         summary: Mapping[str, Any] | None = None) -> None:
    """One entity per strategy under ROOT (perplexity) and LOG_ROOT (nats), x = `token_position` timeline.

    curves: {strategy: (n,) perplexity}. Each curve goes in one columnar call (n rows at once).
    """
    for name, curve in curves.items():
        y = _numpy(curve)
        style = rr.SeriesLines(names=label(name, k), colors=[COLORS.get(name, (0, 0, 0))])
        positions = [rr.TimeColumn(POSITION, sequence=np.arange(len(y)))]
        for root, values in ((ROOT, y), (LOG_ROOT, np.log(y))):
            rec.log(f"{root}/{name}", style, static=True)
            rec.send_columns(f"{root}/{name}", indexes=positions, columns=rr.Scalars.columns(scalars=values))
    if summary is not None:
        body = f"# Token perplexity (GAIA-1 Fig. 6)\n\n```json\n{json.dumps(summary, indent=2)}\n```\n"
        rec.log("/analysis/summary", rr.TextDocument(body, media_type=rr.MediaType.MARKDOWN), static=True)


def save_token_perplexity_rrd(path: str | Path, curves: Mapping[str, ArrayLike], k: int | None = None,
                              summary: Mapping[str, Any] | None = None, recording_id: str | None = None) -> Path | None:
    """Write the curves to a new .rrd atomically (temp file, then rename); None when Rerun is off (RERUN=off).

    curves: {strategy: (n,) perplexity}.
    """
    try:
        with atomic_path(path) as tmp:
            rec = rr.RecordingStream("gaia_app", recording_id=recording_id)
            rec.save(tmp, default_blueprint=token_perplexity_blueprint())
            log_token_perplexity(rec, curves, k, summary)
            rec.flush()
            rec.disconnect()  # closes the file: the footer is written before the rename
            if tmp.stat().st_size == 0:  # a disabled stream writes nothing: keep any older file
                raise RerunDisabled
    except RerunDisabled:
        return None
    return path
