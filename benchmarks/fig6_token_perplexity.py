"""GAIA-1 Fig. 6 (§5.1): per-token-position perplexity of a generated frame, real vs argmax vs sampling vs top-k.

    python train.py experiment=gaia1/world_model_commavq
    python benchmarks/fig6_token_perplexity.py --ckpt outputs/gaia1_world_model_commavq/<time>/checkpoints/last.ckpt

Uses the DataModule of the run's own config (same validation windows). In each window the first
t - 1 frames are the context and the last frame is the real next frame; the model generates that
frame with argmax, full sampling and top-k (the project's KV-cached sampler), and every frame is
scored by the model with teacher forcing: perplexity exp(-log p(z_i | context, z_<i)) at each
position i. Curves are geometric means over the windows (--frames 1: a single frame, as in the paper).
Writes into --out (default: <run dir>/fig6): token_perplexity.png, token_perplexity.json and the
Rerun recording token_perplexity.rrd (or --rrd), all atomically; prints the summary.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf
from tqdm import tqdm

import gaia_app.utils.resolvers  # noqa: F401
from gaia_app.eval.token_perplexity import frame_perplexity, mean_curves, summarize
from gaia_app.lit.checkpoint import load_module
from gaia_app.utils.run_dir import atomic_write_text
from gaia_app.viz.plots import save_figure, save_token_perplexity_rrd, token_perplexity_figure


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", required=True)
    parser.add_argument("--k", type=int, default=50, help="top-k cut-off (paper: 50)")
    parser.add_argument("--frames", type=int, default=8, help="validation windows (one generated frame each)")
    parser.add_argument("--out", default=None, help="output folder (default: <run dir>/fig6)")
    parser.add_argument("--rrd", default=None, help="Rerun recording path (default: <out>/token_perplexity.rrd)")
    parser.add_argument("--data", default=None, help="data config yaml (default: the run's config_resolved.yaml)")
    parser.add_argument("--temperature", type=float, default=1.0, help="sampling temperature (scoring is always at 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args()
    if args.frames < 1 or args.k < 1:
        parser.error("--frames and --k must be ≥ 1")
    return args


def load_datamodule(ckpt: str, data: str | None) -> Any:
    """The run's DataModule from its config_resolved.yaml (or a data config), set up for validation."""
    run_cfg = OmegaConf.load(data or str(Path(ckpt).parents[1] / "config_resolved.yaml"))
    datamodule = instantiate(run_cfg.data if "data" in run_cfg else run_cfg)
    datamodule.setup("fit")
    return datamodule


def windows(datamodule: Any, count: int, device: str) -> Iterator[dict[str, Any]]:
    """Validation batches {"tokens": (b, t, n), ...} on `device`, cut so that `count` windows come out in all."""
    left = count
    for batch in datamodule.val_dataloader():
        if left <= 0:
            return
        batch = {key: v[:left].to(device) if torch.is_tensor(v) else v[:left] for key, v in batch.items()}
        left -= batch["tokens"].shape[0]
        yield batch


@torch.no_grad()
def analyse(module: Any, batches: Iterator[dict[str, Any]], count: int, k: int, temperature: float,
            generator: torch.Generator) -> tuple[dict[str, torch.Tensor], int]:
    """Log-perplexities (w, n) per strategy over the windows (last frame real, the others context), context length."""
    net = module.world_model.eval()
    parts: dict[str, list[torch.Tensor]] = {}
    with tqdm(total=count, desc="fig6 windows", unit="window") as bar:
        for batch in batches:
            tokens = batch["tokens"]
            cond = module.conditions(batch)  # all t steps: context plus the frame to generate
            result = frame_perplexity(net, tokens[:, :-1], tokens[:, -1], cond, k, temperature, generator)
            for name, v in result.log_ppl.items():
                parts.setdefault(name, []).append(v.cpu())
            bar.update(tokens.shape[0])
    if not parts:
        raise ValueError("the validation set has no windows")
    context_frames = min(tokens.shape[1] - 1, net.frames - 1)  # frame_perplexity's window
    return {name: torch.cat(v) for name, v in parts.items()}, context_frames


def report(args: argparse.Namespace, log_ppl: dict[str, torch.Tensor], curves: dict[str, torch.Tensor], net: Any,
           context_frames: int) -> dict[str, Any]:
    """The JSON summary: settings, per-strategy statistics over all (w, n) positions, and the mean curves (n,)."""
    return {
        "checkpoint": str(Path(args.ckpt).resolve()),
        "k": args.k, "temperature": args.temperature, "seed": args.seed,
        "windows": next(iter(log_ppl.values())).shape[0], "context_frames": context_frames,
        "image_tokens": net.n, "vocab_size": net.vocab_size,
        "summary": {name: summarize(v) for name, v in log_ppl.items()},
        "curves_geometric_mean_ppl": {name: [round(x, 6) for x in c.tolist()] for name, c in curves.items()},
    }


def main() -> None:
    args = parse_args()
    module = load_module(args.ckpt, map_location=args.device).eval()
    datamodule = load_datamodule(args.ckpt, args.data)
    out = Path(args.out) if args.out else Path(args.ckpt).resolve().parents[1] / "fig6"
    generator = torch.Generator(device=args.device).manual_seed(args.seed)
    batches = windows(datamodule, args.frames, args.device)
    log_ppl, context_frames = analyse(module, batches, args.frames, args.k, args.temperature, generator)
    net, curves = module.world_model, mean_curves(log_ppl)
    results = report(args, log_ppl, curves, net, context_frames)
    title = f"GAIA-1 Fig. 6: {results['windows']} window(s), V={net.vocab_size}, n={net.n}"
    png = save_figure(token_perplexity_figure(curves, args.k, title), out / "token_perplexity.png")
    rrd = save_token_perplexity_rrd(args.rrd or out / "token_perplexity.rrd", curves, args.k, results["summary"])
    atomic_write_text(out / "token_perplexity.json", json.dumps(results, indent=2))
    rounded = {name: {key: round(v, 4) for key, v in stats.items()} for name, stats in results["summary"].items()}
    print(json.dumps(rounded, indent=2))
    print(f"wrote {png}, {out / 'token_perplexity.json'}" + (f", {rrd}" if rrd else " (Rerun off: no .rrd)"))


if __name__ == "__main__":
    main()
