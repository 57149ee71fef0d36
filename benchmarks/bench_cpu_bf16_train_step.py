"""Training-step cost of the GAIA-1 reference world model on a CPU in float32 vs bfloat16 autocast, side by side.

    python benchmarks/bench_cpu_bf16_train_step.py                  # the recipe's net and batch, 2 threads
    python benchmarks/bench_cpu_bf16_train_step.py --rounds 6 --json

The net is `experiment=gaia1/reference/world_model`'s (d 128, 4 layers, 12 steps × 112 tokens, vocabulary 1024, action
shortcut and deltas), one batch of 4 random windows with actions, AdamW. One round times one full step (zero_grad,
forward, next-token loss, backward, AdamW) of each precision, in alternating order (A B, then B A) so that drifts of
a shared CPU hit both alike. Reported: median seconds per step, the ratio float32 / bfloat16 of the medians with a
bootstrap 90 % interval over rounds, and the loss of the same batch under both (bfloat16 must not change what is
learned: the recipe's validation losses are compared in docs/reference.md).

CPUs with AVX512-BF16 or AMX multiply bfloat16 at twice the float32 rate or more; on CPUs without them autocast
emulates bfloat16 and is slower, so measure before setting `trainer.precision=bf16-mixed` on another machine.
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from gaia_app.models.gaia1.world_model import WorldModel, next_token_loss

CONF = Path(__file__).resolve().parents[1] / "conf"


def reference_net(experiment: str = "gaia1/reference/world_model") -> WorldModel:
    """The world model of a world-model experiment config (the recipe's by default), random weights."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=[f"experiment={experiment}"])
    return instantiate(cfg.model.net)()


def make_step(net: WorldModel, batch: int, dtype: torch.dtype | None, seed: int) -> Callable[[], tuple[float, float]]:
    """One training step under autocast to `dtype` (None: float32) → (seconds, loss)."""
    generator = torch.Generator().manual_seed(seed)
    tokens = torch.randint(0, net.vocab_size, (batch, net.frames, net.n), generator=generator)
    actions = (torch.randn(batch, net.frames, 2, generator=generator) * torch.tensor([3.0, 0.02])
               + torch.tensor([10.0, 0.0]))
    optimizer = torch.optim.AdamW(net.parameters(), lr=1e-4, weight_decay=0.1, betas=(0.9, 0.95))

    def step() -> tuple[float, float]:
        start = time.perf_counter()
        optimizer.zero_grad(set_to_none=True)
        with torch.autocast("cpu", dtype=dtype or torch.bfloat16, enabled=dtype is not None):
            cond = net.conditioner(batch, net.frames, actions=actions, force_drop={"text": True})
            loss = next_token_loss(net, tokens, cond)
        loss.backward()
        optimizer.step()
        return time.perf_counter() - start, float(loss.detach())

    return step


def bootstrap_ratio(a: list[float], b: list[float], draws: int = 2000, seed: int = 0) -> tuple[float, float]:
    """90 % bootstrap interval of median(a) / median(b), resampling rounds."""
    rng = random.Random(seed)
    rounds = list(range(len(a)))
    ratios = sorted(statistics.median(a[i] for i in pick) / statistics.median(b[i] for i in pick)
                    for pick in ([rng.choice(rounds) for _ in rounds] for _ in range(draws)))
    return ratios[int(0.05 * draws)], ratios[int(0.95 * draws) - 1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=4, help="windows per step (the recipe's data.batch_size)")
    parser.add_argument("--rounds", type=int, default=12, help="timed rounds, one step of each precision per round")
    parser.add_argument("--warmup", type=int, default=2, help="untimed steps per precision")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--experiment", default="gaia1/reference/world_model",
                        help="whose net (e.g. gaia1/road_users/world_model_d4: 448 tokens per frame)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    nets = {"float32": reference_net(args.experiment), "bfloat16": reference_net(args.experiment)}
    nets["bfloat16"].load_state_dict(nets["float32"].state_dict())
    steps = {name: make_step(net, args.batch, None if name == "float32" else torch.bfloat16, seed=1)
             for name, net in nets.items()}
    first_loss = {name: step()[1] for name, step in steps.items()}
    for step in steps.values():
        for _ in range(args.warmup - 1):
            step()
    times: dict[str, list[float]] = {name: [] for name in steps}
    for r in range(args.rounds):
        for name in (list(steps) if r % 2 == 0 else list(reversed(steps))):
            times[name].append(steps[name]()[0])
    low, high = bootstrap_ratio(times["float32"], times["bfloat16"])
    result = {"batch": args.batch, "threads": args.threads, "rounds": args.rounds,
              "median_s": {name: statistics.median(t) for name, t in times.items()},
              "float32_over_bfloat16": statistics.median(times["float32"]) / statistics.median(times["bfloat16"]),
              "interval_90": [low, high], "first_loss": first_loss, "times": times}
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print(f"float32 {result['median_s']['float32']:.3f} s/step, bfloat16 autocast {result['median_s']['bfloat16']:.3f} "
          f"s/step: {result['float32_over_bfloat16']:.2f}× [{low:.2f}, {high:.2f}] (90 %, {args.rounds} rounds); "
          f"first-step loss {first_loss['float32']:.4f} vs {first_loss['bfloat16']:.4f}")


if __name__ == "__main__":
    main()
