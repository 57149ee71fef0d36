"""GAIA-1 world-model sampling cost on this CPU (GAIA-1 §5.1): KV cache vs full recompute, guided vs unguided.

    python benchmarks/bench_world_model_sampling.py                  # commaVQ layout: 4 context frames → 1 frame
    python benchmarks/bench_world_model_sampling.py --tokens 64 --repeats 3

Builds the tiny preset (conf/model/net/gaia1_world_model_tiny.yaml) with the commaVQ token layout
(n = 128, vocabulary 1024, T = 5), random weights, and generates one frame after a 4-frame context:
  cached     KV-cached incremental decoding (one new position per forward)
  full       full recompute of the window at every token (the reference)
  guided     cached, with classifier-free guidance: both streams stacked in one forward
Targets (issue 5): full / cached ≥ 10 with identical argmax tokens; guided / cached ≤ 2.2.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from gaia_app.diffusion.ar_sampling import AutoregressiveSampler, TokenPicker
from gaia_app.diffusion.guidance import ClassifierFreeGuidance, LinearSchedule

NET = Path(__file__).resolve().parents[1] / "conf" / "model" / "net" / "gaia1_world_model_tiny.yaml"


def timed(fn, repeats: int) -> tuple[float, torch.Tensor]:
    """Best wall time of `repeats` calls (s) and the last output."""
    best, out = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tokens", type=int, default=128, help="image tokens per frame (commaVQ: 128)")
    parser.add_argument("--context", type=int, default=4)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.manual_seed(0)
    cfg = OmegaConf.load(NET)
    net = instantiate(cfg, vocab_size=1024, image_tokens=args.tokens, frames=args.context + 1)().eval()
    b, steps = args.batch, args.context + 1
    context = torch.randint(0, 1024, (b, args.context, args.tokens))
    cond = net.conditioner(b, steps, force_drop={"text": True, "actions": True})
    greedy = TokenPicker("argmax")
    t_cached, cached = timed(lambda: AutoregressiveSampler(greedy)(net, context, cond, frames=1), args.repeats)
    t_full, full = timed(lambda: AutoregressiveSampler(greedy, use_cache=False)(net, context, cond, frames=1),
                         args.repeats)
    guide = ClassifierFreeGuidance(3.0, LinearSchedule())
    t_guided, _ = timed(lambda: AutoregressiveSampler(greedy)(net, context, cond, cond, frames=1, guidance=guide),
                        args.repeats)
    print(f"threads={torch.get_num_threads()} n={args.tokens} context={args.context} batch={b} "
          f"window={steps * net.step_len} positions")
    print(f"cached  {t_cached:.3f} s/frame")
    print(f"full    {t_full:.3f} s/frame   full/cached = {t_full / t_cached:.1f}×  "
          f"identical tokens: {torch.equal(cached, full)}")
    print(f"guided  {t_guided:.3f} s/frame   guided/cached = {t_guided / t_cached:.2f}×")


if __name__ == "__main__":
    main()
