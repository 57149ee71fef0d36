"""GAIA-1 world-model training-step cost vs a plain causal transformer of the same size (issue 5).

    python benchmarks/bench_world_model_train_step.py                  # tiny preset, commaVQ layout, batch 8
    python benchmarks/bench_world_model_train_step.py --depth 2 --threads 1 --json
    python benchmarks/bench_world_model_train_step.py --markdown

Target: training-step throughput within 15 % of a plain causal transformer of the same size with no
conditioning, i.e. step time world model / plain GPT ≤ 1.15 ("the interleaving costs little").

Candidates, one full training step each (zero_grad, forward, loss, backward, AdamW step), float32,
same batch, same AdamW settings (GAIA-1 §4.2: wd 0.1, betas 0.9/0.95):
  world_model   the tiny preset (conf/model/net/gaia1_world_model_tiny.yaml) with the commaVQ layout
                (n = 128, vocabulary 1024, T = 4, m = 1, l = 2), in training mode, so the conditioning
                dropout draws its modes; actions (b, t, 2) are given and text comes from the `learned`
                text encoder (conf/model/text_encoder/learned.yaml) on fixed captions (--text random:
                a random (b, t, m, e) tensor instead). Loss: next_token_loss (image tokens only).
  gpt_same_len  ACCEPTANCE COMPARISON. A plain GPT with the same CausalTransformer trunk (width, depth,
                heads, kv_heads, mlp) over the SAME sequence length t·(m+n+l): token embedding + one
                learned absolute position embedding + trunk + head, next-token cross-entropy on every
                position, all tokens from the image vocabulary. Same trunk, same positions per step:
                the same "size".
  gpt_image_only  Informative only: the same GPT over t·n positions, what the model would cost with no
                conditioning tokens in the sequence at all.

Timing: `--warmup` untimed steps per candidate, then up to `--repeats` rounds, but no round that would
end (judged by the previous one) past `--max-seconds` from the start of the warm-up, and at least
`--min-repeats` rounds (the whole script stays within about 3 minutes). Each round times one step of
every candidate, in alternating order (A B C, then C B A, ...) so that drifts of the shared CPU hit
all of them alike. Reported: the median step time per candidate and the ratio of medians (the
pass/fail number) with a bootstrap 90 % interval over rounds, and the median of the per-round ratios
as a robustness check (the JSON also holds the ratio of the fastest steps and every step time).
With 2 threads on a CPU shared with other jobs single steps vary by 2-10x; `--threads 1` gives much
steadier (and there, faster) steps.
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
import torch.nn.functional as F
from hydra.utils import instantiate
from omegaconf import OmegaConf
from torch import nn

from gaia_app.models.gaia1.world_model import WorldModel, next_token_loss
from gaia_app.nn.transformer import CausalTransformer

CONF = Path(__file__).resolve().parents[1] / "conf" / "model"
NET = CONF / "net" / "gaia1_world_model_tiny.yaml"
TEXT_ENCODER = CONF / "text_encoder" / "learned.yaml"
TARGET = 1.15
CAPTIONS = ("slow traffic ahead", "turn left at the junction", "green light", "rain on the highway")


class PlainGPT(nn.Module):
    """Token embedding + learned absolute positions + CausalTransformer + head: the unconditioned baseline."""

    def __init__(self, vocab_size: int, seq_len: int, dim: int, depth: int, heads: int, kv_heads: int | None,
                 mlp_ratio: float, dropout: float, tie_embeddings: bool = False):
        super().__init__()
        self.token_embedding = nn.Embedding(vocab_size, dim)
        self.position = nn.Parameter(torch.zeros(seq_len, dim))
        self.transformer = CausalTransformer(dim, depth, heads, kv_heads, mlp_ratio, dropout)
        self.head = nn.Linear(dim, vocab_size, bias=False)
        self.transformer.initialize_weights()  # same init as WorldModel.initialize_weights
        for p in (self.token_embedding.weight, self.position, self.head.weight):
            nn.init.normal_(p, std=0.02)
        if tie_embeddings:  # mirrors WorldModel(tie_embeddings=True)
            self.head.weight = self.token_embedding.weight

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        """tokens (b, L) → logits (b, L, V)."""
        return self.head(self.transformer(self.token_embedding(tokens) + self.position[: tokens.shape[1]]))


def gpt_loss(net: PlainGPT, window: torch.Tensor) -> torch.Tensor:
    """Plain next-token objective: window (b, L + 1); inputs are its first L tokens, targets the last L."""
    logits = net(window[:, :-1])
    return F.cross_entropy(logits.flatten(0, 1), window[:, 1:].flatten())


def count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def adamw(params) -> torch.optim.Optimizer:
    return torch.optim.AdamW(params, lr=1e-4, weight_decay=0.1, betas=(0.9, 0.95))


def make_step(params: list[nn.Parameter], loss_fn: Callable[[], torch.Tensor]) -> Callable[[], float]:
    """One training step (zero_grad, forward + loss, backward, AdamW step) → its wall time in seconds."""
    opt = adamw(params)

    def step() -> float:
        start = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        loss = loss_fn()
        loss.backward()
        opt.step()
        return time.perf_counter() - start

    return step


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tokens", type=int, default=128, help="image tokens per frame n (commaVQ: 128)")
    p.add_argument("--vocab", type=int, default=1024, help="image vocabulary V (commaVQ: 1024)")
    p.add_argument("--frames", type=int, default=4, help="steps per window T (commaVQ experiment: 4)")
    p.add_argument("--text-tokens", type=int, default=1, help="text tokens per step m (commaVQ experiment: 1)")
    p.add_argument("--depth", type=int, default=None, help="override the preset's depth (commaVQ experiment: 2)")
    p.add_argument("--batch", type=int, default=8, help="batch size (commaVQ experiment: 8)")
    p.add_argument("--text", choices=("encoder", "random"), default="encoder",
                   help="text features: the learned text encoder on captions, or a random (b, t, m, e) tensor")
    p.add_argument("--warmup", type=int, default=2, help="untimed steps per candidate")
    p.add_argument("--repeats", type=int, default=60, help="most timed rounds (one step of each candidate per round)")
    p.add_argument("--min-repeats", type=int, default=5, help="fewest timed rounds, whatever the time budget")
    p.add_argument("--max-seconds", type=float, default=160.0,
                   help="time budget of warm-up + timed rounds: no round expected to end after it starts")
    p.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    p.add_argument("--no-image-only", action="store_true", help="skip the informative t·n-position GPT row")
    p.add_argument("--json", action="store_true", help="print the results as JSON instead of text")
    p.add_argument("--markdown", action="store_true", help="also print a markdown table for docs/benchmarks.md")
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args()


def main() -> None:
    args = parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    cfg = OmegaConf.load(NET)
    overrides = {"vocab_size": args.vocab, "image_tokens": args.tokens, "frames": args.frames,
                 "text_tokens": args.text_tokens}
    if args.depth is not None:
        overrides["depth"] = args.depth
    wm: WorldModel = instantiate(cfg, **overrides)().train()
    net_cfg = OmegaConf.merge(cfg, overrides)
    b, t, n, m, n_act = args.batch, args.frames, args.tokens, args.text_tokens, wm.l  # n_act: the paper's l
    seq_len = t * wm.step_len

    # --- A: world model, full conditioning path in training mode
    tokens = torch.randint(0, args.vocab, (b, t, n))
    actions = torch.randn(b, t, n_act)
    wm_params = list(wm.parameters())
    if args.text == "encoder":
        text_encoder = instantiate(OmegaConf.load(TEXT_ENCODER), dim=net_cfg.text_dim, tokens=m)().train()
        captions = [[CAPTIONS[(i + j) % len(CAPTIONS)] for j in range(t)] for i in range(b)]
        wm_params += list(text_encoder.parameters())
        text_features = lambda: text_encoder(captions)  # noqa: E731
    else:
        text_encoder = None
        random_text = torch.randn(b, t, m, net_cfg.text_dim)
        text_features = lambda: random_text  # noqa: E731

    def wm_loss() -> torch.Tensor:
        return next_token_loss(wm, tokens, wm.conditioner(b, t, text_features(), actions))

    # --- B: plain GPT, same trunk, same sequence length (and, informative, t·n positions)
    trunk = dict(dim=net_cfg.dim, depth=net_cfg.depth, heads=net_cfg.heads, kv_heads=net_cfg.kv_heads,
                 mlp_ratio=net_cfg.mlp_ratio, dropout=net_cfg.dropout,
                 tie_embeddings=wm.head.weight is wm.token_embedding.weight)
    gpts = {"gpt_same_len": seq_len}
    if not args.no_image_only:
        gpts["gpt_image_only"] = t * n
    models: dict[str, nn.Module] = {"world_model": wm}
    steps = {"world_model": make_step(wm_params, wm_loss)}
    positions = {"world_model": seq_len}
    for name, length in gpts.items():
        gpt = PlainGPT(args.vocab, length, **trunk).train()
        window = torch.randint(0, args.vocab, (b, length + 1))
        models[name], positions[name] = gpt, length
        steps[name] = make_step(list(gpt.parameters()), lambda gpt=gpt, window=window: gpt_loss(gpt, window))

    dtypes = {p.dtype for mdl in models.values() for p in mdl.parameters()}
    trunk_params = {name: count(mdl.transformer) for name, mdl in models.items()}
    if len(set(trunk_params.values())) != 1 or dtypes != {torch.float32}:
        raise RuntimeError(f"unfair comparison: trunk params {trunk_params}, dtypes {dtypes}")
    total_params = {name: count(mdl) for name, mdl in models.items()}
    if text_encoder is not None:
        total_params["world_model"] += count(text_encoder)

    names = list(steps)
    start = time.perf_counter()
    for name in names:
        for _ in range(args.warmup):
            steps[name]()
    times: dict[str, list[float]] = {name: [] for name in names}
    rounds, last_round = 0, 0.0
    while rounds < args.repeats and (rounds < args.min_repeats
                                     or time.perf_counter() - start + last_round <= args.max_seconds):
        round_start = time.perf_counter()
        for name in names if rounds % 2 == 0 else reversed(names):
            times[name].append(steps[name]())
        rounds, last_round = rounds + 1, time.perf_counter() - round_start
    wall = time.perf_counter() - start

    median = {name: statistics.median(v) for name, v in times.items()}
    rng = random.Random(args.seed)
    ratios = {}
    for name in gpts:
        a, g = times["world_model"], times[name]
        boot = sorted(statistics.median(a[i] for i in idx) / statistics.median(g[i] for i in idx)
                      for idx in ([rng.randrange(rounds) for _ in range(rounds)] for _ in range(2000)))
        ratios[name] = {
            "ratio_of_medians": median["world_model"] / median[name],
            "bootstrap_90": [boot[100], boot[1899]],
            "median_paired_ratio": statistics.median(x / y for x, y in zip(a, g)),
            "ratio_of_minima": min(a) / min(g),
        }
    acceptance = ratios["gpt_same_len"]["ratio_of_medians"]
    results = {
        "config": {"dim": net_cfg.dim, "depth": net_cfg.depth, "heads": net_cfg.heads, "kv_heads": net_cfg.kv_heads,
                   "mlp_ratio": net_cfg.mlp_ratio, "vocab": args.vocab, "frames": t, "text_tokens": m,
                   "image_tokens": n, "action_tokens": n_act, "batch": b, "text": args.text, "dtype": "float32",
                   "tie_embeddings": trunk["tie_embeddings"],
                   "threads": torch.get_num_threads(), "warmup": args.warmup, "rounds": rounds},
        "positions": positions,
        "trunk_params": trunk_params,
        "total_params": total_params,
        "median_step_s": median,
        "steps_per_s": {name: 1 / s for name, s in median.items()},
        "ratios": ratios,
        "acceptance": {"comparison": "world_model / gpt_same_len (ratio of median step times)",
                       "ratio": acceptance, "target": TARGET, "pass": acceptance <= TARGET},
        "wall_s": wall,
        "step_times_s": times,
    }
    if args.json:
        print(json.dumps(results, indent=2))
        return
    c = results["config"]
    print(f"dim={c['dim']} depth={c['depth']} heads={c['heads']} kv_heads={c['kv_heads']} mlp={c['mlp_ratio']} "
          f"V={c['vocab']} T={t} m={m} n={n} l={n_act} batch={b} text={args.text} float32 tied={c['tie_embeddings']} "
          f"threads={c['threads']} "
          f"warmup={args.warmup} rounds={rounds} (interleaved, alternating order)")
    print(f"{'candidate':16s} {'positions':>9s} {'trunk params':>12s} {'total params':>12s} "
          f"{'median ms/step':>14s} {'steps/s':>8s}")
    for name in names:
        print(f"{name:16s} {positions[name]:9d} {trunk_params[name]:12,d} {total_params[name]:12,d} "
              f"{median[name] * 1e3:14.1f} {1 / median[name]:8.2f}")
    for name, r in ratios.items():
        label = "ACCEPTANCE (same sequence length = same size)" if name == "gpt_same_len" else \
            "informative (no conditioning tokens at all)"
        lo, hi = r["bootstrap_90"]
        print(f"world_model / {name:14s} = {r['ratio_of_medians']:.3f} [90% {lo:.3f}-{hi:.3f}]  "
              f"median paired ratio {r['median_paired_ratio']:.3f}  {label}")
    verdict = "PASS" if acceptance <= TARGET else "FAIL"
    print(f"{verdict}: world_model / gpt_same_len = {acceptance:.3f} "
          f"(ratio of median step times, target ≤ {TARGET}); warm-up + timing {wall:.1f} s")
    if args.markdown:
        print()
        print("| candidate | positions | trunk params | total params | ms/step | ratio |")
        print("|---|---|---|---|---|---|")
        for name in names:
            ratio = "" if name == "world_model" else f"{median['world_model'] / median[name]:.2f}"
            if name == "gpt_same_len":
                ratio = f"**{ratio}** (target ≤ {TARGET})"
            print(f"| {name} | {positions[name]} | {trunk_params[name]:,} | {total_params[name]:,} | "
                  f"{median[name] * 1e3:.1f} | {ratio} |")


if __name__ == "__main__":
    main()
