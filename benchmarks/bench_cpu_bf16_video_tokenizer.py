"""Training-step cost of a GAIA-2 video tokenizer on a CPU: float32 against bfloat16 autocast, side by side.

    python benchmarks/bench_cpu_bf16_video_tokenizer.py --threads 1 --rounds 6     # the s = 4 road-users net
    python benchmarks/bench_cpu_bf16_video_tokenizer.py --experiment gaia2/video_tokenizer_tiny --json

Three arms of the same net and batch (an experiment's `model.net`, random weights, one batch of 2 random 3-camera
clips of 8 frames at 64 × 112, L1 + L2 reconstruction, AdamW):
- float32;
- bfloat16 autocast as the project runs it: the linear layers in bfloat16, SDPA in float32
  (`gaia_app.nn.spacetime.attention`);
- bfloat16 autocast with SDPA in bfloat16 too (what autocast alone would do), to show why attention stays in float32.

One round times one full step (zero_grad, forward, loss, backward, AdamW) of each arm in a rotating order, so that
drifts of a shared CPU hit all alike. Reported: median seconds per step, each bfloat16 arm's speed-up over float32
with a bootstrap 90 % interval over rounds, and the first step's loss of each arm (bfloat16 must not change what is
learned). On CPUs without AVX512-BF16 or AMX autocast emulates bfloat16 and is slower: measure before setting
`trainer.precision=bf16-mixed` on another machine.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import gaia_app.nn.spacetime as spacetime  # noqa: E402
from benchmarks.bench_cpu_bf16_train_step import bootstrap_ratio  # noqa: E402
from gaia_app.models.gaia2.video_tokenizer import VideoTokenizer  # noqa: E402

ARMS = ("float32", "bfloat16", "bfloat16_sdpa")


def experiment_net(experiment: str) -> VideoTokenizer:
    """The video tokenizer of a GAIA-2 tokenizer experiment config, random weights."""
    import gaia_app.utils.resolvers  # noqa: F401  (the configs' ${val_seed:...})

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=[f"experiment={experiment}"])
    return instantiate(cfg.model.net)()


def bfloat16_sdpa(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, **kwargs) -> torch.Tensor:
    """SDPA in the inputs' dtype: the arm without the float32 attention of `spacetime.attention`."""
    return F.scaled_dot_product_attention(q, k, v, **kwargs)


def make_step(net: VideoTokenizer, arm: str, video: torch.Tensor) -> Callable[[], tuple[float, float]]:
    """One training step of `arm` on video (b, v, T, 3, H, W) → (seconds, loss)."""
    optimizer = torch.optim.AdamW(net.parameters(), lr=1e-4, weight_decay=0.01, betas=(0.9, 0.95))
    attention = bfloat16_sdpa if arm == "bfloat16_sdpa" else spacetime.attention

    def step() -> tuple[float, float]:
        project_attention, spacetime.attention = spacetime.attention, attention
        try:
            start = time.perf_counter()
            optimizer.zero_grad(set_to_none=True)
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=arm != "float32"):
                error = net(video).reconstruction.float() - video
                loss = error.abs().mean() + error.square().mean()
            loss.backward()
            optimizer.step()
            return time.perf_counter() - start, float(loss.detach())
        finally:
            spacetime.attention = project_attention

    return step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--experiment", default="gaia2/road_users/video_tokenizer_s4")
    parser.add_argument("--clips", type=int, default=2, help="clips per step (the recipe's data.batch_size)")
    parser.add_argument("--cameras", type=int, default=3)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=6, help="timed rounds, one step of each arm per round")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    first = experiment_net(args.experiment)
    nets = {arm: first if arm == "float32" else experiment_net(args.experiment) for arm in ARMS}
    for net in nets.values():
        net.load_state_dict(first.state_dict())
    video = torch.rand(args.clips, args.cameras, args.frames, 3, 64, 112,
                       generator=torch.Generator().manual_seed(1)) * 2 - 1
    steps = {arm: make_step(net, arm, video) for arm, net in nets.items()}
    first_loss = {arm: step()[1] for arm, step in steps.items()}
    times: dict[str, list[float]] = {arm: [] for arm in ARMS}
    for r in range(args.rounds):
        for arm in ARMS[r % len(ARMS):] + ARMS[:r % len(ARMS)]:
            times[arm].append(steps[arm]()[0])
    median = {arm: statistics.median(t) for arm, t in times.items()}
    speedup = {arm: {"float32_over_arm": median["float32"] / median[arm],
                     "interval_90": list(bootstrap_ratio(times["float32"], times[arm]))} for arm in ARMS[1:]}
    result = {"experiment": args.experiment, "threads": args.threads, "rounds": args.rounds, "median_s": median,
              "speedup": speedup, "first_loss": first_loss, "times": times}
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print(f"{args.experiment}, {args.threads} thread(s), {args.rounds} rounds: float32 {median['float32']:.2f} s/step")
    for arm, s in speedup.items():
        low, high = s["interval_90"]
        print(f"  {arm}: {median[arm]:.2f} s/step, {s['float32_over_arm']:.2f}x [{low:.2f}, {high:.2f}] (90 %)")
    print("first-step loss: " + ", ".join(f"{arm} {loss:.4f}" for arm, loss in first_loss.items()))


if __name__ == "__main__":
    main()
