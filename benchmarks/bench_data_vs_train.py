"""Is the synthetic world fast enough to feed tiny-config training? Both measured side by side.

    python benchmarks/bench_data_vs_train.py                    # the demo's experiment
    python benchmarks/bench_data_vs_train.py --batches 20 experiment=gaia1/tokenizer_tiny data.batch_size=8

Composes the experiment's config, then on ONE thread times (a) producing `--batches` training
batches from its DataModule and (b) the same number of tokenizer generator steps (forward,
reconstruction + codebook losses, backward, AdamW) on those batches. The GAN step of the real
module only adds training time, so the ratio is conservative. Target: data / train < 1, i.e. one
loader worker keeps a training process busy.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import torch
import torch.nn.functional as F
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import open_dict

import gaia_app.utils.resolvers  # noqa: F401

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


def load_config(overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="train", overrides=overrides)
    with open_dict(cfg):
        cfg.paths.output_dir = "/tmp/bench_data_vs_train"
        cfg.data.num_workers = 0
    return cfg


def time_batches(datamodule, count: int) -> tuple[float, list[dict]]:
    datamodule.setup("fit")
    loader = iter(datamodule.train_dataloader())
    start = time.perf_counter()
    batches = [next(loader) for _ in range(count)]
    return time.perf_counter() - start, batches


def time_train_steps(net: torch.nn.Module, batches: list[dict]) -> float:
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4)
    net(batches[0]["image"])  # warm-up: first-call allocations are not steady state
    start = time.perf_counter()
    for batch in batches:
        x = batch["image"]
        out = net(x)
        loss = 0.2 * F.l1_loss(out.reconstruction, x) + 2.0 * F.mse_loss(out.reconstruction, x)
        loss = loss + out.codebook_loss + out.commitment_loss
        opt.zero_grad()
        loss.backward()
        opt.step()
    return time.perf_counter() - start


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batches", type=int, default=20)
    p.add_argument("overrides", nargs="*", default=["experiment=gaia1/tokenizer_tiny"])
    args = p.parse_args()
    cv2.setNumThreads(1)
    torch.set_num_threads(1)
    cfg = load_config(args.overrides)
    data_s, batches = time_batches(instantiate(cfg.data), args.batches)
    net = instantiate(cfg.model.net)()
    train_s = time_train_steps(net, batches)
    frames = batches[0]["image"].shape[0]
    print(f"batch: {frames} frames of {tuple(batches[0]['image'].shape[1:])}, {args.batches} batches, 1 thread")
    print(f"data  {data_s / args.batches * 1000:8.1f} ms/batch  ({frames * args.batches / data_s:6.1f} frames/s)")
    print(f"train {train_s / args.batches * 1000:8.1f} ms/batch  ({frames * args.batches / train_s:6.1f} frames/s)")
    print(f"data / train = {data_s / train_s:.2f}  (target < 1)")


if __name__ == "__main__":
    main()
