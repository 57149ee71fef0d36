"""Validation cross-entropy of a trained GAIA-1 world model on commaVQ tokens vs two baselines (issue 5).

    python train.py experiment=gaia1/world_model_commavq
    python benchmarks/eval_world_model_commavq.py \\
        --ckpt outputs/gaia1_world_model_commavq/<time>/checkpoints/best_step_*.ckpt

Uses the DataModule of the run's own config (same windows, same time split). Reports, in nats/token
on validation frames 2..T of each window (frame 1 has no previous frame to copy):
  model        eq. 1 cross-entropy of the world model (text/actions absent → null embeddings)
  unigram      add-one-smoothed token frequencies of the training windows
  copy_prev    the token at the same position one frame earlier, smoothed with the best ε
Lower is better; the model should beat both.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

import gaia_app.utils.resolvers  # noqa: F401
from gaia_app.eval.token_baselines import copy_previous_cross_entropy, model_cross_entropy, unigram_cross_entropy
from gaia_app.lit.checkpoint import load_module


def stack(dataset) -> torch.Tensor:
    """All windows of a TokenWindows dataset: (windows, t, n)."""
    return torch.stack([dataset[i]["tokens"] for i in range(len(dataset))])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", required=True)
    parser.add_argument("--data", default=None, help="data config yaml (default: the run's config_resolved.yaml)")
    parser.add_argument("--batch", type=int, default=8)
    args = parser.parse_args()
    module = load_module(args.ckpt).eval()
    net = module.world_model.eval()
    run_cfg = OmegaConf.load(args.data or str(Path(args.ckpt).parents[1] / "config_resolved.yaml"))
    datamodule = instantiate(run_cfg.data if "data" in run_cfg else run_cfg)
    datamodule.setup("fit")
    vocab = module.world_model.vocab_size
    train, val = stack(datamodule.train_set), stack(datamodule.val_set)
    copy_ce, eps = copy_previous_cross_entropy(val, vocab)
    results = {
        "model": model_cross_entropy(lambda x: net(x, module.conditions({"tokens": x})), val, args.batch),
        "unigram": unigram_cross_entropy(train, val[:, 1:], vocab),
        "copy_prev": copy_ce,
        "copy_prev_eps": eps,
        "val_windows": len(val),
        "val_tokens_scored": val[:, 1:].numel(),
    }
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
