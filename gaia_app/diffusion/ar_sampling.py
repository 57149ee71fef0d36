"""Autoregressive image-token sampling for the GAIA-1 world model (GAIA-1 §5.1).

Legend:
    b batch, t0 context frames, f generated frames, T context length of the net (steps), n image
    tokens per frame, m text tokens per step, s tokens per step, d model width, V vocabulary.

One frame takes n forward passes, one per token. With the KV cache each pass feeds only the new
positions; without it (`use_cache=False`, the reference for tests and benchmarks) each pass
re-runs the whole window. Beyond T steps a sliding window keeps the last T - 1 frames as context: with learned
absolute step embeddings (GAIA-1 §2.1) every slide re-embeds and re-prefills the window, since each cached key
carries its old window index; with rotary step positions (`temporal_encoding=rope`, the net's `rolling_cache`) the
oldest step is dropped from the cache and the slide costs what any other frame costs (exact in the first layer,
an approximation of the re-prefilled window beyond it: `SamplingSession`). `SamplingSession` holds one rollout's
state between frames, so a closed loop can append each step's conditions as they arrive. `decode_step="compiled"`
decodes the tokens after a frame's first with a fixed-shape step on a static KV cache under torch.compile (CUDA
graphs on a GPU; gaia_app/diffusion/compiled_decode.py), the same tokens at a fraction of eager's launch cost.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch
from tqdm.auto import tqdm

from gaia_app.diffusion.compiled_decode import DECODE_STEPS, StaticStream, StepPool
from gaia_app.diffusion.guidance import ClassifierFreeGuidance
from gaia_app.nn.attention import KVCache
from gaia_app.utils import threads


class StepConditions(Protocol):
    """Condition tokens per step (text (b, t, m, d), actions (b, t, l, d)), e.g. gaia_app.models.gaia1's Conditions."""

    text: torch.Tensor
    actions: torch.Tensor

    def steps(self, start: int, stop: int) -> StepConditions: ...

    def cat(self, other: StepConditions) -> StepConditions: ...

    def then(self, other: StepConditions) -> StepConditions: ...


class TokenWorldModel(Protocol):
    """What the sampler needs of an autoregressive world model (gaia_app.models.gaia1.WorldModel has it): `frames`
    steps per context window, `m` text positions per step, embedding of tokens and conditions, the causal trunk
    (optionally KV-cached) and the token head. The sampler depends on this, not on a concrete model (DESIGN.md §3).
    Optional: `rolling_cache` True (with `step_len`, positions per step) when time is relative, so a sliding window
    drops the oldest step from the KV cache instead of re-embedding the window (gaia_app/nn/rope.py). Optional too:
    `embed_token`, `decode_token` and `static_cache`, the fixed-shape decode step of `decode_step="static"` /
    `"compiled"` (gaia_app/diffusion/compiled_decode.py; a net without them decodes eagerly)."""

    frames: int
    m: int
    head: Callable[[torch.Tensor], torch.Tensor]

    def embed(self, tokens: torch.Tensor, cond: StepConditions, start: int = 0, previous: torch.Tensor | None = None,
              previous_actions: torch.Tensor | None = None) -> torch.Tensor: ...

    def decode(self, x: torch.Tensor, cache: KVCache | None = None) -> torch.Tensor: ...

MODES = ("argmax", "sample", "top_k", "top_p")
# TokenPicker.prepare's result: the tokens, or the candidates' probabilities and their tokens
Prepared = torch.Tensor | tuple[torch.Tensor, torch.Tensor | None]


@dataclass(frozen=True)
class TokenPicker:
    """Chooses next tokens from logits: `argmax`, `sample` (full distribution), `top_k` (GAIA-1 §5.1, Fig. 6) or
    `top_p` (nucleus sampling: the fewest most likely tokens whose probability reaches p).

    temperature divides the logits before sampling; k is the top-k cut-off, p the nucleus mass. A fixed k keeps the
    same number of tokens whatever the entropy, so it trims broad distributions (detailed daylight texture) much more
    than peaked ones (dark night frames) and shifts unconditional samples towards the peaked scenes; the nucleus
    adapts its size to each distribution (docs/reference.md, the floor calibration table).
    """

    mode: str = "top_k"
    k: int = 50
    temperature: float = 1.0
    p: float = 0.9

    def __post_init__(self) -> None:
        if self.mode not in MODES or self.k < 1 or self.temperature <= 0 or not 0 < self.p <= 1:
            raise ValueError(f"TokenPicker: mode in {MODES}, k ≥ 1, temperature > 0, 0 < p ≤ 1; got {self}")

    def __call__(self, logits: torch.Tensor, generator: torch.Generator | None = None,
                 gumbel: torch.Tensor | None = None) -> torch.Tensor:
        """(b, V) logits → (b,) int64 tokens. gumbel (b, V): standard Gumbel noise per vocabulary entry; when given,
        the token is the Gumbel-max choice among the allowed tokens (the same distribution as without it), so rows
        handed the same noise pick the same token wherever their logits agree (`shared_gumbel`)."""
        return self.finish(self.prepare(logits, gumbel), generator)

    def prepare(self, logits: torch.Tensor, gumbel: torch.Tensor | None = None) -> Prepared:
        """The deterministic part of the choice (what a captured decode step runs, gaia_app/diffusion/
        compiled_decode.py): the tokens (b,) when no random draw is left (argmax, or `gumbel` given), else the
        candidates' probabilities (b, K) and their tokens (b, K) (None when column k is token k) for `finish`."""
        if self.mode == "argmax":
            return logits.argmax(-1)
        logits = logits.float() / self.temperature
        if gumbel is not None:
            return (self.allowed(logits) + gumbel).argmax(-1)
        if self.mode == "top_k":
            top, index = logits.topk(min(self.k, logits.shape[-1]), dim=-1)
            return top.softmax(-1), index
        if self.mode == "top_p":
            return nucleus(logits, self.p)
        return logits.softmax(-1), None

    @staticmethod
    def finish(prepared: Prepared, generator: torch.Generator | None = None) -> torch.Tensor:
        """Tokens (b,) from `prepare`'s result: one draw among the candidates when one is left, the same token
        torch.multinomial(probs, 1, generator) picks (`draw`). The compiled decode step draws the same noise before
        its call and picks inside it (`finish_drawn`), so both paths share this one mechanism."""
        if isinstance(prepared, torch.Tensor):
            return prepared
        probs = prepared[0]
        return TokenPicker.finish_drawn(prepared, TokenPicker.draw(tuple(probs.shape), generator, probs.device))

    def draw_shape(self, rows: int, vocabulary: int) -> tuple[int, int] | None:
        """The shape of the noise `finish` draws for `rows` rows of a vocabulary (None: argmax draws nothing)."""
        if self.mode == "argmax":
            return None
        return (rows, min(self.k, vocabulary)) if self.mode == "top_k" else (rows, vocabulary)

    @staticmethod
    def draw(shape: tuple[int, int], generator: torch.Generator | None, device: torch.device) -> torch.Tensor:
        """The standard exponential noise (shape) that `finish`'s multinomial draws from `generator`: PyTorch's
        one-sample multinomial is argmax(probs / q) with q = empty_like(probs).exponential_(1, generator)
        (tests/test_compiled_decode.py checks the two agree)."""
        return torch.empty(shape, device=device).exponential_(1, generator=generator)

    @staticmethod
    def finish_drawn(prepared: Prepared, noise: torch.Tensor | None) -> torch.Tensor:
        """`finish` with its noise drawn beforehand (`draw`): no generator inside, so a compiled graph can run it.
        noise (b, K) for prepared probabilities (b, K); None when `prepared` is already the tokens."""
        if isinstance(prepared, torch.Tensor):
            return prepared
        probs, index = prepared
        choice = (probs / noise).argmax(-1, keepdim=True)
        return (choice if index is None else index.gather(-1, choice)).squeeze(-1)

    def allowed(self, logits: torch.Tensor) -> torch.Tensor:
        """(b, V) tempered logits → the same with every token this picker cannot choose at −inf."""
        if self.mode == "sample":
            return logits
        if self.mode == "top_k":
            index = logits.topk(min(self.k, logits.shape[-1]), dim=-1).indices
        else:
            probs, index = logits.softmax(-1).sort(dim=-1, descending=True)
            index = index.masked_fill(probs.cumsum(-1) - probs >= self.p, -1)  # outside the nucleus
            index = torch.where(index < 0, index[:, :1], index)  # the most likely token stands in for them
        keep = torch.zeros_like(logits, dtype=torch.bool).scatter_(-1, index, True)
        return logits.masked_fill(~keep, -math.inf)


def shared_gumbel(groups: torch.Tensor, vocabulary: int, generator: torch.Generator | None = None,
                  count: int | None = None) -> torch.Tensor:
    """Standard Gumbel noise (b, V), one draw per group: rows with equal `groups` (b,) int64 get the same noise.

    Counterfactual sampling (Gumbel-max coupling, Oberst & Sontag 2019): futures of one context under different
    commands share every draw, so where the command does not change the logits they pick the same tokens, and
    their differences come from the commands rather than from sampling luck, as re-simulated real futures share
    their world's randomness. Each future's own distribution is unchanged. count: the number of groups (more than
    the largest group index), when the caller knows it (saves a device sync per token)."""
    count = int(groups.max()) + 1 if count is None else count
    exponential = torch.empty(count, vocabulary, device=groups.device).exponential_(generator=generator)
    return -exponential.clamp_min(torch.finfo(torch.float32).tiny).log()[groups]


def check_groups(groups: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
    """noise_groups (b,) int64 ≥ 0 for a context (b, t0, n), moved to its device; ValueError otherwise."""
    if groups.shape != context.shape[:1] or groups.dtype != torch.long or (len(groups) and int(groups.min()) < 0):
        raise ValueError(f"noise_groups: expected ({context.shape[0]},) int64 ≥ 0, one per rollout; got "
                         f"{tuple(groups.shape)} {groups.dtype}")
    return groups.to(context.device)


def nucleus_sample(logits: torch.Tensor, p: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """(b, V) logits → (b,) tokens drawn from the smallest set of most likely tokens whose probability reaches p
    (the most likely token is always kept), renormalised."""
    return TokenPicker.finish(nucleus(logits, p), generator)


def nucleus(logits: torch.Tensor, p: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(b, V) logits → the probabilities sorted in descending order (b, V), those outside the nucleus of mass p
    zeroed, and their tokens (b, V)."""
    probs, index = logits.softmax(-1).sort(dim=-1, descending=True)
    before = probs.cumsum(-1) - probs  # mass of the more likely tokens
    return probs.masked_fill(before >= p, 0.0), index


def window_positions(net: TokenWorldModel) -> int:
    """The most positions one context window holds in the cache: T steps plus the next step's text (0 when the
    net does not say its step length)."""
    step_len = getattr(net, "step_len", 0)
    return net.frames * step_len + net.m if step_len else 0


class WindowStream:
    """Positions fed so far in one context window: a KV cache, or the embedded chunks re-run in full."""

    def __init__(self, net: TokenWorldModel, use_cache: bool, capacity: int | None = None):
        self.net = net
        # preallocated for a window's positions (it grows beyond them by concatenation)
        self.cache = KVCache(capacity or window_positions(net) or None) if use_cache else None
        self.chunks: list[torch.Tensor] = []

    def feed(self, x: torch.Tensor) -> torch.Tensor:
        """Append embedded positions x: (b, L, d); return the logits after the last one (b, V)."""
        if self.cache is not None:
            h = self.net.decode(x, self.cache)[:, -1]
        else:
            self.chunks.append(x)
            h = self.net.decode(torch.cat(self.chunks, dim=1))[:, -1]
        return self.net.head(h)


class AutoregressiveSampler:
    """Generates image tokens frame by frame, token by token, with optional classifier-free guidance.

    Args:
        picker: how each token is chosen from the (guided) logits.
        use_cache: KV-cached incremental decoding (True) or full recompute at every token.
        progress: a progress bar over generated frames.
        decode_step: how a token after a frame's first is decoded (gaia_app/diffusion/compiled_decode.py):
            "eager" (per-token eager PyTorch), "static" (a fixed-shape step on a static KV cache) or "compiled"
            (that step under torch.compile: CUDA-graph captured on CUDA; falls back to eager with one warning where
            it cannot compile). All three give the same tokens under a seed. Needs use_cache.
        cache_capacity: KV-cache positions per layer (None: one window, T steps plus the next step's text); less
            than a window is a ValueError.
        tokens_per_call: with decode_step "static" or "compiled", the image tokens one call of the fixed-shape step
            decodes, each token's draw inside it from noise drawn beforehand in eager's order (the same tokens);
            several per call spend the per-call overhead once for all of them.
    """

    def __init__(self, picker: TokenPicker | None = None, use_cache: bool = True, progress: bool = False,
                 decode_step: str = "eager", cache_capacity: int | None = None, tokens_per_call: int = 1):
        if decode_step not in DECODE_STEPS:
            raise ValueError(f"decode_step={decode_step!r}: expected one of {DECODE_STEPS}")
        if decode_step != "eager" and not use_cache:
            raise ValueError(f"decode_step={decode_step!r} decodes on a static KV cache: it needs use_cache=True")
        if cache_capacity is not None and (isinstance(cache_capacity, bool) or int(cache_capacity) != cache_capacity
                                           or cache_capacity < 1):
            raise ValueError(f"cache_capacity={cache_capacity!r}: expected a positive integer or None")
        self.picker = picker or TokenPicker()
        self.use_cache = use_cache
        self.progress = progress
        self.decode_step, self.cache_capacity = decode_step, cache_capacity
        if isinstance(tokens_per_call, bool) or int(tokens_per_call) != tokens_per_call or tokens_per_call < 1:
            raise ValueError(f"tokens_per_call={tokens_per_call!r}: expected a positive integer")
        self.tokens_per_call = int(tokens_per_call)
        self.steps = StepPool(decode_step, self.tokens_per_call) if decode_step != "eager" else None

    def capacity(self, net: TokenWorldModel) -> int:
        """KV-cache positions per layer for `net`'s window; ValueError when cache_capacity is below it."""
        needed = window_positions(net)
        if self.cache_capacity is not None and self.cache_capacity < needed:
            raise ValueError(f"cache_capacity={self.cache_capacity} positions is too small for the window of "
                             f"{needed} positions ({net.frames} steps × {net.step_len} + {net.m} text positions)")
        return self.cache_capacity or needed

    @torch.no_grad()
    def __call__(self, net: TokenWorldModel, context: torch.Tensor, cond: StepConditions,
                 uncond: StepConditions | None = None,
                 frames: int = 1, guidance: ClassifierFreeGuidance | None = None,
                 generator: torch.Generator | None = None, noise_groups: torch.Tensor | None = None) -> torch.Tensor:
        """Context (b, t0, n) int64 and conditions for t0 + f steps → tokens (b, t0 + f, n).

        With `guidance`, `uncond` (the unconditioned or negative-prompt stream) runs in the same
        forward as `cond`, stacked on the batch; eq. 3 combines their logits per token. noise_groups (b,) int64:
        rows with equal values share their sampling noise (`shared_gumbel`); None: every row draws its own.
        """
        _, t0, n = context.shape
        if cond.text.shape[1] < t0 + frames:
            raise ValueError(f"conditions cover {cond.text.shape[1]} steps, need t0 + frames = {t0 + frames}")
        session = self.session(net, context, cond, uncond, guidance, generator, noise_groups=noise_groups)
        scales = guidance.scales(frames, n) if guidance is not None else None
        new = [session.next_frame(None if scales is None else scales[k])
               for k in tqdm(range(frames), desc="world model", unit="frame", disable=not self.progress)]
        return torch.cat([context, *(frame[:, None] for frame in new)], dim=1)

    def session(self, net: TokenWorldModel, context: torch.Tensor, cond: StepConditions,
                uncond: StepConditions | None = None, guidance: ClassifierFreeGuidance | None = None,
                generator: torch.Generator | None = None, given: tuple[str, ...] = (),
                noise_groups: torch.Tensor | None = None) -> SamplingSession:
        """A rollout advanced one frame per call (`SamplingSession.next_frame`), its KV cache kept in between."""
        return SamplingSession(self, net, context, cond, uncond, guidance, generator, given, noise_groups)


class SamplingSession:
    """One batch of rollouts, sampled one frame per `next_frame` call, its window's KV cache kept in between.

    The sampler's own rollouts run a session to the end; a closed-loop simulator (pipelines/simulator.py) keeps one
    open for a whole episode and appends each step's conditions (`extend`) as its action arrives, so a step feeds
    only that frame's positions. `tokens` and `streams` hold the window only (the last T − 1 steps and the step
    being sampled); the steps before it are forgotten and counted in `dropped_steps`. On a slide, a net with
    learned absolute step embeddings (GAIA-1 §2.1) re-embeds and re-prefills its window, whose every key changes
    with the window's start; a net with relative time (`rolling_cache`, rotary steps) drops the oldest step from
    the cache instead. That is exact in the first layer only: deeper layers keep keys and values computed while
    the dropped step was in view (as Transformer-XL's segment memory and StreamingLLM do), so a rolled window
    approximates a re-prefilled one rather than equalling it (docs/simulator.md).

    context (b, t0, n) int64; cond, uncond: conditions of at least the t0 context steps (GAIA-1 §5.1 eq. 3 runs
    uncond in the same forward, stacked on the batch). given: names of the condition streams the caller built
    them from (e.g. "text", "negative"), so the caller can check that later steps bring the same ones.
    noise_groups (b,) int64: rows with equal values share every sampling draw (`shared_gumbel`; e.g. one context
    under several commands); None: each row draws its own noise.
    """

    def __init__(self, sampler: AutoregressiveSampler, net: TokenWorldModel, context: torch.Tensor,
                 cond: StepConditions, uncond: StepConditions | None = None,
                 guidance: ClassifierFreeGuidance | None = None, generator: torch.Generator | None = None,
                 given: tuple[str, ...] = (), noise_groups: torch.Tensor | None = None):
        if (guidance is None) != (uncond is None):
            raise ValueError("classifier-free guidance needs both `guidance` and `uncond` (or neither)")
        if cond.text.shape[1] < context.shape[1]:
            raise ValueError(f"conditions cover {cond.text.shape[1]} steps, the context has {context.shape[1]}")
        self.sampler, self.net, self.guidance, self.generator = sampler, net, guidance, generator
        self.tokens = context
        self.streams = cond if uncond is None else cond.cat(uncond)
        self.dropped_steps = 0
        self.stream: WindowStream | None = None
        self.given = tuple(given)
        self.noise_groups = None if noise_groups is None else check_groups(noise_groups, context)
        self.noise_count = None if noise_groups is None else int(noise_groups.max()) + 1
        self.capacity = sampler.capacity(net)  # first: a cache too small for the window fails here

    @property
    def known_steps(self) -> int:
        """Steps known so far (context and generated), counted from the first context step."""
        return self.dropped_steps + self.tokens.shape[1]

    @torch.no_grad()
    def extend(self, cond: StepConditions, uncond: StepConditions | None = None) -> None:
        """Append the conditions of further steps: (b, k, ...) each, uncond given exactly when guided."""
        if (self.guidance is None) != (uncond is None):
            raise ValueError("this session is " + ("guided: extend needs uncond" if self.guidance is not None
                                                   else "unguided: extend takes no uncond"))
        self.streams = self.streams.then(cond if uncond is None else cond.cat(uncond))

    @torch.no_grad()
    def next_frame(self, scales: torch.Tensor | None = None) -> torch.Tensor:
        """Sample the next step's n tokens → (b, n). scales (n,): guidance per token (a one-frame rollout's
        `guidance.scales(1, n)[0]` when None)."""
        threads.tick()  # follow the load other processes put on the CPUs (gaia_app/utils/threads.py)
        net, (b, known, n) = self.net, self.tokens.shape
        if known >= net.frames:  # keep the last T − 1 steps: the window then ends with the step being sampled
            self.forget(known - (net.frames - 1))
        t = self.tokens.shape[1]
        if self.streams.text.shape[1] <= t:
            raise ValueError(f"no conditions for step {self.known_steps}: extend the session first")
        if self.guidance is not None and scales is None:
            scales = self.guidance.scales(1, n)[0]
        tokens = torch.cat([self.tokens, self.tokens.new_zeros(b, 1, n)], dim=1)
        if self.stream is None:
            self.stream = self.open_stream()
            x = self.prefill(tokens, t)
        else:  # the previous frame's last image token and its actions, then this step's text
            x = torch.cat([self.embed_step(tokens, t - 1)[:, net.m + n - 1 :], self.embed_step(tokens, t)[:, : net.m]],
                          dim=1)
        logits = self.stream.feed(x)
        tokens[:, t, 0] = first = self.pick(logits, scales, 0)
        start = 1
        if isinstance(self.stream, StaticStream):  # tokens 1.. by the fixed-shape step, the rest (if any) eagerly
            start = self.stream.decode_frame(self, tokens, t, scales, first, logits.shape[-1])
        for i in range(start, n):  # token i follows token i − 1, at position m + i − 1 of the step
            x = self.embed_step(tokens, t)[:, net.m + i - 1 : net.m + i]
            tokens[:, t, i] = self.pick(self.stream.feed(x), scales, i)
        self.tokens = tokens
        return tokens[:, t]

    def pick(self, logits: torch.Tensor, scales: torch.Tensor | None, i: int) -> torch.Tensor:
        """Token i of the frame (b,) from the streams' logits (B, V): guided by scales[i] (eq. 3), then picked."""
        if self.guidance is not None:
            cond_logits, uncond_logits = logits.chunk(2)
            logits = self.guidance(cond_logits, uncond_logits, scales[i].item())
        return self.sampler.picker(logits, self.generator, self.gumbel(logits.shape[-1]))

    def open_stream(self) -> WindowStream | StaticStream:
        """A new window's stream: on a fixed-shape step when the sampler asks for one (and it can have one)."""
        if self.sampler.steps is not None:
            stream = self.sampler.steps.stream(self, self.capacity)
            if stream is not None:
                return stream
        return WindowStream(self.net, self.sampler.use_cache, self.capacity)

    def gumbel(self, vocabulary: int) -> torch.Tensor | None:
        """The next token's shared noise (b, V), or None when every row draws its own."""
        if self.noise_groups is None:
            return None
        return shared_gumbel(self.noise_groups, vocabulary, self.generator, self.noise_count)

    def forget(self, count: int) -> None:
        """Drop the `count` oldest steps: from the KV cache with relative time, else the window is re-prefilled."""
        if not 0 < count <= self.tokens.shape[1]:
            raise ValueError(f"cannot forget {count} of the window's {self.tokens.shape[1]} steps")
        cache = None if self.stream is None else self.stream.cache
        if cache is not None and getattr(self.net, "rolling_cache", False):
            cache.drop_front(count * self.net.step_len)  # first: it raises on a cache too short, changing nothing
        else:
            self.stream = None
        self.tokens = self.tokens[:, count:]
        self.streams = self.streams.steps(count, self.streams.text.shape[1])
        self.dropped_steps += count

    def embed_step(self, tokens: torch.Tensor, t: int) -> torch.Tensor:
        """Embedded positions (B, s, d) of window step t (tokens (b, ≥ t + 1, n), every stream stacked on B)."""
        copies = self.streams.text.shape[0] // tokens.shape[0]  # one copy per stream
        both = tokens[:, t : t + 1].repeat(copies, 1, 1)
        previous = tokens[:, t - 1].repeat(copies, 1) if t > 0 else None
        previous_actions = self.streams.actions[:, t - 1] if t > 0 else None
        return self.net.embed(both, self.streams.steps(t, t + 1), t, previous, previous_actions)

    def prefill(self, tokens: torch.Tensor, t: int) -> torch.Tensor:
        """The window's known steps 0..t-1 in full, then step t's text: (B, t·s + m, d)."""
        both = tokens[:, :t].repeat(self.streams.text.shape[0] // tokens.shape[0], 1, 1)
        known = self.net.embed(both, self.streams.steps(0, t), 0)
        return torch.cat([known, self.embed_step(tokens, t)[:, : self.net.m]], dim=1)
