"""Where a commanded contrast is lost: the GAIA-2 world model's estimate of the clean future along its sampler, against
the latent contrast of the real re-simulated continuations (issue 50, "diagnose before you scale").

Legend: N scenes, K solver steps, v cameras, g generated latent steps, C h w latent channels and grid.

The action table (protocols/gaia2_actions.py) reads a contrast (accelerate − brake speed, left − right curvature) from
decoded frames through a probe, so it says how much of a command the finished futures show, not where the rest went.
This readout stays in the world model's latent space. For each held-out scene and each contrast pair (high, low) of
`model.evaluate.commands`, both futures sampled from one noise (as the action table samples them):

    D_real   = z(high) − z(low): the tokenizer's latents of the two re-simulated continuations, generated steps;
    D_k      = x̂(high, k) − x̂(low, k): the sampler's estimate of the clean generated latents at solver step k,
               x̂ = x + (1 − τ_k)·v (v the velocity the solver steps with, guided where guidance is on), k = 0 … K − 1;
               at k = 0 (τ = 0, pure noise) it is the model's conditional mean of the future;
    D_sample = the same difference of the finished samples;
    share    = ⟨D, D_real⟩ ÷ ⟨D_real, D_real⟩: how much of the real latent contrast D carries, 1 all of it, 0 none
               (the component of D along D_real; a future that moves its scene as the real one does scores 1);
    cosine   = ⟨D, D_real⟩ ÷ (|D|·|D_real|), and norm = |D| ÷ |D_real|: how much of D is anything else;
    uniform  = the share of |D|² in a change that is the same for every token of the grid (per camera, step,
               channel and position within a token's patch): the kind of change a per-step AdaLN modulation makes
               when nothing spatial shapes it (the real contrast's own, a displacement of the scene, is
               `real_uniform`);
    share_poolP = the share of both contrasts projected onto fields constant over P × P grid cells (blocks at the
               edges may be smaller): what D carries of the real contrast at a coarser scale. The real contrast's own
               block means score 1 here, and on `share` they score `real_coarse`, the part of the real contrast's
               energy that survives the projection: a future that moves its scene right but draws it this blurred.
    share_strong / share_weak = the share over the quarter of the grid cells (`STRONG_QUANTILE`; cameras, rows and
               columns of each generated step, channels summed) with the largest |D_real|², and over the other cells:
               does the net carry the command where the real latents change most, or nowhere? `real_strong` is the
               fraction of the real contrast's energy in its strong cells. Per scene, share = real_strong·share_strong
               + (1 − real_strong)·share_weak, so when real_strong is near 1 the split says little beyond `share`.

Reading it: if the conditional mean (k = 0, unguided) carries much of D_real and the samples little, the sampler
loses the command; if both carry little, the net has not learnt it, and sampling cannot bring it back. A perfect
net's conditional mean need not score 1: what the context does not predict (content entering the view) is not in
it. Guidance multiplies the
conditional − unconditional difference, so `--scales 1 4` of the benchmark separates what the net's conditional
mean carries from what guidance adds. Per-scene values, with 95 % intervals over scenes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from contextlib import contextmanager
from typing import Any, Iterator

import numpy as np
import torch
from einops import rearrange
from omegaconf import DictConfig
from tqdm.auto import tqdm

from gaia_app.data.clip import Clip
from gaia_app.data.latent_cache import LatentClip
from gaia_app.data.synthetic.generate import SyntheticSample
from gaia_app.diffusion.flow_matching import FlowSampler
from gaia_app.eval.controllability import contrast_pairs, probe_clips
from gaia_app.eval.intervals import mean_interval
from gaia_app.pipelines.gaia2 import Gaia2Pipeline, with_labels
from gaia_app.protocols.controllability import CONTRASTS, commanded_actions
from gaia_app.protocols.gaia2_actions import check_action_agents, noise_draws, resimulated, scene_noise_seeds

POOLS = (2, 4)  # grid cells averaged per side for the coarse shares (a cell: 4 px for the s = 4 tokenizer, 8 for s = 8)
STRONG_QUANTILE = 0.75  # cells at or above this quantile of the real contrast's energy per cell count as strong
MEASURES = ("share", "cosine", "norm", "uniform", *(f"share_pool{p}" for p in POOLS), "share_strong", "share_weak")


class TracingSampler(FlowSampler):
    """A FlowSampler that also keeps, at each solver step, its estimate of the clean generated latents
    x̂ = x + (1 − τ)·v of the steps after the first `clean_steps` (Euler: one velocity per step)."""

    def __init__(self, sampler: FlowSampler, clean_steps: int):
        super().__init__(sampler.steps, sampler.schedule, sampler.solver, sampler.threshold, sampler.progress)
        if sampler.solver != "euler":
            raise ValueError(f"sampler.solver={sampler.solver!r}: the contrast trace reads one velocity per solver "
                             "step; use model.sampler.solver=euler")
        self.clean_steps = clean_steps
        self.estimates: list[torch.Tensor] = []

    @torch.no_grad()
    def __call__(self, velocity: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], noise: torch.Tensor,
                 start: int = 0) -> torch.Tensor:
        def traced(x: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
            v = velocity(x, tau)
            ahead = (1 - tau).view(-1, *([1] * (x.dim() - 1)))
            self.estimates.append((x + ahead * v)[:, :, self.clean_steps:].detach().clone())
            return v

        return super().__call__(traced, noise, start)


@contextmanager
def tracing(pipeline: Gaia2Pipeline, clean_steps: int) -> Iterator[TracingSampler]:
    """Swap the world pipeline's sampler for a TracingSampler of the same grid while the block runs."""
    world = pipeline.world
    original = world.sampler
    world.sampler = TracingSampler(original, clean_steps)
    try:
        yield world.sampler
    finally:
        world.sampler = original


def traced_rollout(pipeline: Gaia2Pipeline, context: torch.Tensor, cond: Any, new_steps: int, seed: int
                   ) -> torch.Tensor:
    """(K + 1, v, g, C, h, w): the sampler's estimates of the generated latents at each solver step, then the
    finished sample, for one future continuing `context` (1, v, c, C, h, w) under `cond` from noise `seed`."""
    c = context.shape[2]
    with tracing(pipeline, c) as tracer:
        x = pipeline.world.rollout(context, [cond], new_steps, torch.Generator(context.device).manual_seed(seed))
        estimates = [e[0] for e in tracer.estimates]
    return torch.stack([*estimates, x[0, :, c:]]).cpu()


def projections(trace: torch.Tensor, real: torch.Tensor, patch: int = 1) -> dict[str, torch.Tensor]:
    """trace (k, v, g, C, h, w) contrasts, real (v, g, C, h, w) the real contrast, patch the world model's token side
    → {share, cosine, norm, uniform, share_poolP} (k,) each (module docstring)."""
    flat, reference = trace.flatten(1).double(), real.flatten().double()
    energy = reference.square().sum()
    if energy <= 0:
        raise ValueError("the two re-simulated continuations have identical latents: no contrast to trace")
    dot = flat @ reference
    norms = flat.norm(dim=1)
    return {"share": dot / energy, "cosine": dot / (norms * energy.sqrt()).clamp_min(1e-12),
            "norm": norms / energy.sqrt(), "uniform": uniform_share(trace, patch),
            **{f"share_pool{p}": pooled_share(trace, real, p) for p in POOLS}, **split_shares(trace, real)}


def strong_cells(real: torch.Tensor) -> torch.Tensor:
    """(v, g, 1, h, w) bool: in each latent step of a real contrast (v, g, C, h, w), the ⌈(1 − STRONG_QUANTILE)·n⌉
    of its n grid cells (cameras × rows × columns) with the largest energy summed over channels. Per step, because a
    command's contrast grows along the rollout (a speed command's displacement about as t²): pooled over steps, the
    split would mostly pick the last step. A fixed count, not a threshold: ties cannot make every cell strong."""
    v, g, _, h, w = real.shape
    energy = rearrange(real.double().square().sum(dim=-3), "v g h w -> g (v h w)")
    count = math.ceil((1 - STRONG_QUANTILE) * energy.shape[1])
    strong = torch.zeros_like(energy, dtype=torch.bool).scatter_(1, energy.topk(count, dim=1).indices, True)
    return rearrange(strong, "g (v h w) -> v g 1 h w", v=v, h=h, w=w)


def split_shares(trace: torch.Tensor, real: torch.Tensor) -> dict[str, torch.Tensor]:
    """{share_strong, share_weak}: (k,) each, the share of the real contrast (v, g, C, h, w) that each contrast of
    `trace` (k, v, g, C, h, w) carries over the strong cells and over the rest (module docstring)."""
    strong = strong_cells(real).expand_as(real)
    out = {}
    for name, cells in (("share_strong", strong), ("share_weak", ~strong)):
        reference = torch.where(cells, real.double(), 0.0)
        out[name] = (trace.double().flatten(1) @ reference.flatten()) / reference.square().sum().clamp_min(1e-24)
    return out


def strong_energy(real: torch.Tensor) -> float:
    """The share of a real contrast's energy (v, g, C, h, w) in its strong cells."""
    energy = real.double().square()
    return float(torch.where(strong_cells(real), energy, 0.0).sum() / energy.sum().clamp_min(1e-24))


def uniform_share(contrast: torch.Tensor, patch: int = 1) -> torch.Tensor:
    """(k,) the share of each contrast's energy (k, v, g, C, h, w) in its mean over the tokens of the grid, taken
    separately at each of the patch × patch positions within a token (a token-constant change repeats every patch)."""
    k, h, w = contrast.shape[0], contrast.shape[-2], contrast.shape[-1]
    if h % patch or w % patch:
        raise ValueError(f"latent grid {h}×{w} is not a whole number of {patch}×{patch} patches")
    tokens = contrast.double().unflatten(-1, (w // patch, patch)).unflatten(-3, (h // patch, patch))
    mean = tokens.mean(dim=(-4, -2), keepdim=True).expand_as(tokens)
    return mean.reshape(k, -1).square().sum(1) / tokens.reshape(k, -1).square().sum(1).clamp_min(1e-24)


def block_coordinates(contrast: torch.Tensor, cells: int) -> torch.Tensor:
    """(…, ⌈h/cells⌉, ⌈w/cells⌉): each cells × cells block's mean times the square root of its number of cells (blocks
    at the edges may be smaller): the contrast (…, h, w) projected onto block-constant fields, in an orthonormal basis,
    so that its sums of products and squares are those of the projected fields."""
    *lead, h, w = contrast.shape
    flat = contrast.double().reshape(-1, 1, h, w)
    means = torch.nn.functional.avg_pool2d(flat, cells, ceil_mode=True, count_include_pad=False)
    rows = torch.tensor([min(cells, h - i) for i in range(0, h, cells)], dtype=torch.float64)
    cols = torch.tensor([min(cells, w - j) for j in range(0, w, cells)], dtype=torch.float64)
    return (means * (rows[:, None] * cols).sqrt()).reshape(*lead, *means.shape[-2:])


def pooled_share(trace: torch.Tensor, real: torch.Tensor, cells: int) -> torch.Tensor:
    """(k,) ⟨P D, P D_real⟩ ÷ |P D_real|², P the projection onto fields constant over cells × cells blocks; trace
    (k, …, h, w), real (…, h, w)."""
    reference = block_coordinates(real, cells).flatten()
    energy = reference.square().sum().clamp_min(1e-24)
    return block_coordinates(trace, cells).flatten(1) @ reference / energy


def coarse_energy(contrast: torch.Tensor, cells: int) -> float:
    """|P D|² ÷ |D|²: the share of a contrast's energy (…, h, w) that its projection onto fields constant over
    cells × cells blocks keeps."""
    return float(block_coordinates(contrast, cells).square().sum() / contrast.double().square().sum().clamp_min(1e-24))


def check_settings(cfg: DictConfig) -> None:
    """ValueError naming the setting unless the trace can read it: one future per scene and command
    (model.evaluate.noise_draws=1), the Euler solver, a known model.evaluate.action_agents."""
    check_action_agents(cfg)
    if noise_draws(cfg) != 1:
        raise ValueError("the contrast trace samples one future per scene and command: set "
                         "model.evaluate.noise_draws=1")
    if cfg.model.sampler.solver != "euler":
        raise ValueError(f"model.sampler.solver={cfg.model.sampler.solver!r}: the contrast trace reads one velocity "
                         "per solver step; use model.sampler.solver=euler")


def contrast_trace(cfg: DictConfig, pipeline: Gaia2Pipeline, scenes: list[tuple[SyntheticSample, LatentClip]],
                   generator: torch.Generator, ceilings: dict[tuple[int, bytes], Clip] | None = None
                   ) -> dict[str, Any]:
    """The trace of the module docstring: per contrast, per measure, per solver step (and the sample), the mean over
    scenes with its 95 % interval, and the per-scene values. One noise seed per scene, drawn from `generator` as the
    action table draws them (one draw), so the finished samples are the action table's model futures.

    ceilings: shared with other traces or action tables of the same scenes (keyed by scene and actions)."""
    ceilings = {} if ceilings is None else ceilings
    g = cfg.model
    check_settings(cfg)
    first, frames = g.context_steps * pipeline.temporal, g.steps * pipeline.temporal
    rate = float(scenes[0][0].clip.fps)
    contexts = probe_clips([sample.clip for sample, _ in scenes], rate, frames)
    commands = [tuple(cmd) for cmd in g.evaluate.commands]
    commanded = commanded_actions(contexts, first, frames - first, rate, commands)  # (C·N, f, 2) command-major
    pairs = contrast_pairs(commanded[:, first:-1].unflatten(0, (len(commands), -1)))
    n, new_steps, patch = len(scenes), g.steps - g.context_steps, pipeline.world.model.patch
    seeds = [draws[0] for draws in scene_noise_seeds(generator, n, 1)]
    used = sorted({index for pair in pairs for index in pair})
    per_scene: dict[str, dict[str, list[list[float]]]] = {m: {k: [] for k in MEASURES} for m in CONTRASTS}
    real_uniform: dict[str, list[float]] = {m: [] for m in CONTRASTS}
    real_coarse: dict[str, dict[str, list[float]]] = {m: {f"pool{p}": [] for p in POOLS} for m in CONTRASTS}
    real_strong: dict[str, list[float]] = {m: [] for m in CONTRASTS}
    for i in tqdm(range(n), desc="contrast trace"):
        _, clip = scenes[i]
        real, traces = {}, {}
        for command in used:
            actions = commanded[command * n + i].numpy()
            key = (i, actions.tobytes())
            if key not in ceilings:
                ceilings[key] = resimulated(cfg, i, actions.astype(np.float64))
            real[command] = pipeline.window(pipeline.encode(ceilings[key]), 0, g.steps)[0][0, :, g.context_steps:].cpu()
            target = with_labels(clip, first, actions[first:])
            context, _ = pipeline.window(target, 0, g.context_steps)
            _, cond = pipeline.window(target, 0, g.steps)
            cond = cond.without("agents") if g.evaluate.action_agents == "dropped" else cond
            traces[command] = traced_rollout(pipeline, context, cond, new_steps, seeds[i])
        for metric, (high, low) in zip(CONTRASTS, pairs):
            values = projections(traces[high] - traces[low], real[high] - real[low], patch)
            real_uniform[metric].append(float(uniform_share((real[high] - real[low])[None], patch)[0]))
            real_strong[metric].append(strong_energy(real[high] - real[low]))
            for cells in POOLS:
                real_coarse[metric][f"pool{cells}"].append(coarse_energy(real[high] - real[low], cells))
            for measure in MEASURES:
                per_scene[metric][measure].append(values[measure].tolist())
    taus = pipeline.world.sampler.taus()[:-1].tolist()
    return {"scenes": n, "commands": [list(cmd) for cmd in commands], "agents": g.evaluate.action_agents,
            "contrasts": {metric: ["/".join(commands[high]), "/".join(commands[low])]
                          for metric, (high, low) in zip(CONTRASTS, pairs)},
            "taus": taus, "guidance_scale": float(pipeline.world.guidance.scale),
            "summary": {metric: {measure: summarise(values) for measure, values in measures.items()}
                        for metric, measures in per_scene.items()},
            "real_uniform": {metric: summarise([[v] for v in values])[0] for metric, values in real_uniform.items()},
            "real_coarse": {metric: {pool: summarise([[v] for v in values])[0] for pool, values in pools.items()}
                            for metric, pools in real_coarse.items()},
            "real_strong": {metric: summarise([[v] for v in values])[0] for metric, values in real_strong.items()},
            "per_scene": per_scene, "per_scene_real_uniform": real_uniform, "per_scene_real_coarse": real_coarse,
            "per_scene_real_strong": real_strong}


def summarise(values: list[list[float]]) -> list[dict[str, float]]:
    """Per solver step (and the sample, last): the mean over scenes with its 95 % interval."""
    out = []
    for column in zip(*values):
        estimate = mean_interval(column)
        out.append({"mean": estimate.mean, "low": estimate.low, "high": estimate.high})
    return out


def nearest_steps(taus: list[float], wanted: tuple[float, ...] = (0.0, 0.1, 0.25, 0.5, 0.75, 0.9)) -> list[int]:
    """Indices of the solver steps whose τ is nearest each of `wanted` (without repeats, in order)."""
    picked = []
    for tau in wanted:
        index = int(np.argmin([abs(t - tau) for t in taus]))
        if index not in picked:
            picked.append(index)
    return picked


def markdown(trace: dict[str, Any], name: str) -> list[str]:
    """One table per weights folder: rows contrast × measure, columns a few solver steps' τ and the sample."""
    steps = nearest_steps(trace["taus"])
    head = [f"τ = {trace['taus'][k]:.2f}" for k in steps] + ["sample"]
    lines = [f"Contrast trace of weights={name} ({trace['scenes']} scenes, guidance ×{trace['guidance_scale']:g}, "
             f"agent boxes {trace['agents']}; mean over scenes [95 % interval]). share: the part of the real "
             "re-simulated latent contrast that the sampler's estimate of the clean future carries (1 all, 0 none)",
             "", "| contrast | measure | " + " | ".join(head) + " |", "|---|---" + "|---:" * len(head) + "|"]
    for metric, (high, low) in trace["contrasts"].items():
        for measure in MEASURES:
            cells = [trace["summary"][metric][measure][k] for k in [*steps, -1]]
            lines.append(f"| {metric.replace('_', ' ')} ({high} − {low}) | {measure} | "
                         + " | ".join(f"{c['mean']:+.3f} [{c['low']:+.3f}, {c['high']:+.3f}]" for c in cells) + " |")
    real = "; ".join(f"{metric.replace('_', ' ')} {c['mean']:.3f} [{c['low']:.3f}, {c['high']:.3f}]"
                     for metric, c in trace["real_uniform"].items())
    coarse = "; ".join(f"{metric.replace('_', ' ')} "
                       + ", ".join(f"{pool} {c['mean']:.3f}" for pool, c in pools.items())
                       for metric, pools in trace["real_coarse"].items())
    strong = "; ".join(f"{metric.replace('_', ' ')} {c['mean']:.3f} [{c['low']:.3f}, {c['high']:.3f}]"
                       for metric, c in trace["real_strong"].items())
    return [*lines, "", f"uniform share of the real contrasts themselves: {real}",
            f"energy of the real contrasts left after pooling (what a blurred but right future could carry): {coarse}",
            f"fraction of the real contrasts' energy in their strong cells (the top {1 - STRONG_QUANTILE:.0%} of each "
            f"step's cells): {strong}"]
