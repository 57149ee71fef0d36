"""A fixed-shape decode step for the GAIA-1 autoregressive sampler, optionally compiled (issue 51; docs/gpu_speed.md).

Legend:
    b rollouts, B = copies·b rows (with guidance the conditioned and unconditioned streams stacked on the batch),
    n image tokens per frame, C cache capacity (positions), V vocabulary, l action tokens per step, d width.

Eager decoding of one token launches ≈15 small kernels per layer; at batch 1 on a GPU their launch cost, not their
arithmetic, sets the speed (4.5–8.3 ms per token measured). `DecodeStep` does one token's work in shapes that never
change from token to token: a StaticKVCache written in place at a slot read from a tensor, attention over the whole
capacity with the unfilled slots masked, the embedding slot and the rotary time read from tensors. So
`torch.compile(mode="reduce-overhead")` captures it once as a CUDA graph and replays it for every token (on a CPU,
plain `torch.compile`; `static` runs the same step uncompiled).

Inside the step: the previous token's embedding (every guidance stream), the trunk, the head, eq. 3 guidance, and the
whole token choice: `TokenPicker.prepare` (argmax and shared-noise Gumbel-max picks, or the candidates and their
probabilities) and the draw, from noise drawn beforehand (`TokenPicker.draw`, `finish_drawn`). A compiled graph
cannot take the caller's torch.Generator and continue its random stream, which is what makes a seeded rollout repeat
eager's tokens; so the noise each token's multinomial would draw is drawn eagerly before the call, in eager's order,
and the argmax that PyTorch's one-sample multinomial takes over it is taken inside. With the draw inside, one call
can decode `block` tokens (`tokens_per_call`), paying the call's overhead once for all of them. Pickers without
`prepare` (the vector simulator's RowwisePicker, one generator per row) get the guided logits, one token per call.

Eager, as before: the prefill, each frame's first token (its chunk: the previous frame's last image token, its actions
and this step's text), a window slide (StaticKVCache.drop_front shifts the cache in place: with rotary time
(`rolling_cache`) the oldest step leaves the cache, with learned time the window is re-prefilled into the same
buffers), and every token of a frame at window step 0 (a rollout without context: no previous frame to embed).

The tokens equal eager decoding's under a seed; the logits agree to float rounding (attention over C masked slots
reduces in another order than over the live ones), so a token can differ where two candidates tie to ~1e-6.
"""

from __future__ import annotations

import logging
import weakref
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from gaia_app.nn.attention import StaticKVCache

if TYPE_CHECKING:
    from gaia_app.diffusion.ar_sampling import SamplingSession

log = logging.getLogger(__name__)
# eager: the per-token eager loop; static: the fixed-shape step, uncompiled; compiled: the fixed-shape step compiled
DECODE_STEPS = ("eager", "static", "compiled")
NEEDS = ("embed_token", "decode_token", "static_cache", "step_len")  # what a net offers for the fixed-shape step


def compile_options(device: torch.device) -> dict[str, Any]:
    """torch.compile arguments for the step: CUDA graphs on CUDA (the launch-bound case), plain inductor elsewhere.
    fullgraph: a graph break would leave eager pieces between the captured ones, so it is an error (and a fallback)."""
    if device.type == "cuda":
        return {"mode": "reduce-overhead", "fullgraph": True}
    return {"fullgraph": True}


def cache_dtype(net: nn.Module, device: torch.device) -> torch.dtype:
    """The dtype of the keys the net computes: autocast's when it is on, else the weights'."""
    if torch.is_autocast_enabled(device.type):
        return torch.get_autocast_dtype(device.type)
    return next(net.parameters()).dtype


class DecodeStep(nn.Module):
    """`block` image tokens in fixed shapes: previous token (b,) → the chosen tokens (block, b) (or guided logits).

    The cache buffers and the per-frame inputs (`previous`, `previous_actions`) are registered buffers, so a
    compiled graph reads them at fixed addresses; eager code refills them between tokens and frames.
    """

    def __init__(self, net: nn.Module, cache: StaticKVCache, copies: int, n: int, actions: torch.Tensor,
                 picker: Any, guidance: Any, block: int = 1):
        super().__init__()
        self.net, self.cache, self.copies, self.picker, self.guidance = net, cache, copies, picker, guidance
        self.block = block
        self.layers = len(cache.buffers)
        for layer, (keys, values) in enumerate(cache.buffers):
            self.register_buffer(f"keys{layer}", keys, persistent=False)
            self.register_buffer(f"values{layer}", values, persistent=False)
        rows = actions.shape[0]
        previous = torch.zeros(rows, n, dtype=torch.long, device=actions.device)
        self.register_buffer("previous", previous, persistent=False)
        self.register_buffer("previous_actions", torch.zeros_like(actions), persistent=False)

    def begin_frame(self, previous: torch.Tensor, previous_actions: torch.Tensor) -> None:
        """Set the frame's inputs: previous (B, n) tokens of the step before, previous_actions (B, l, d) its actions."""
        self.previous.copy_(previous)
        self.previous_actions.copy_(previous_actions)

    def forward(self, token: torch.Tensor, where: torch.Tensor, scale: torch.Tensor | None = None,
                gumbel: torch.Tensor | None = None, noise: torch.Tensor | None = None) -> torch.Tensor:
        """`block` consecutive image tokens, each fed the one chosen before it.

        token (b,) int64: the image token just chosen; where (K, 4) int64, a row per token: its slot in the frame,
        its absolute position, the cached positions, the window step; scale (K,) float64 guidance scales (None
        unguided); gumbel (K, b, V): shared noise per token, or None; noise (K, b, c): the exponential noise each
        token's draw uses (`TokenPicker.draw`), or None (argmax, shared noise). → the tokens (K, b) int64; for a
        picker without `prepare` (block 1 only) the guided logits (b, V), chosen eagerly.
        """
        buffers = [(getattr(self, f"keys{i}"), getattr(self, f"values{i}")) for i in range(self.layers)]
        chosen = []
        for j in range(self.block):
            slot, position, length, step = where[j].unbind()
            x = self.net.embed_token(token.repeat(self.copies), slot, step, self.previous, self.previous_actions)
            logits = self.net.head(self.net.decode_token(x, buffers, length, position))  # (B, V)
            if self.guidance is not None:
                # scale in float64 as eager's Python float: (1 + s) rounds to the same float32 (equal tokens)
                logits = self.guidance(*logits.chunk(2), scale[j])
            if not hasattr(self.picker, "prepare"):
                return logits
            prepared = self.picker.prepare(logits, None if gumbel is None else gumbel[j])
            token = self.picker.finish_drawn(prepared, None if noise is None else noise[j])
            chosen.append(token)
        return torch.stack(chosen)


class FixedStep:
    """A DecodeStep, its callable (compiled or not) and the session using it; `tail`: a one-token step on the same
    cache for a frame's last tokens when a block of several does not divide them (None otherwise)."""

    def __init__(self, module: DecodeStep, key: tuple, run: Any, cuda_graphs: bool, compiled: bool = False,
                 tail: FixedStep | None = None):
        self.module, self.key, self.run, self.cuda_graphs, self.compiled = module, key, run, cuda_graphs, compiled
        self.tail = tail
        self.owner: weakref.ref | None = None
        self.warm = False  # a compiled step has run once: its graph exists

    def begin_frame(self, previous: torch.Tensor, previous_actions: torch.Tensor) -> None:
        """The frame's inputs for this step and its tail (`DecodeStep.begin_frame`)."""
        self.module.begin_frame(previous, previous_actions)
        if self.tail is not None:
            self.tail.begin_frame(previous, previous_actions)

    def free_for(self, session: SamplingSession) -> bool:
        owner = None if self.owner is None else self.owner()
        return owner is None or owner is session

    def __call__(self, *inputs: Any) -> Any:
        if self.cuda_graphs:  # the previous replay's outputs are consumed: let this replay reuse their memory
            torch.compiler.cudagraph_mark_step_begin()
        if not (self.compiled and self.warm):
            out = self.run(*inputs)
            self.warm = True
            return out
        # Dynamo re-checks ≈ every buffer and parameter before each call (143 µs of a 1.1 ms step on a 2-core CPU).
        # Nothing those guards watch changes between a warm step's calls: the inputs' shapes, dtypes and None-ness
        # (shared noise or not, guidance or not) and autocast are fixed by the pool's key, the buffers are static.
        # So only the guards that tell compiled graphs apart run.
        with torch.compiler.set_stance("default", skip_guard_eval_unsafe=True):
            return self.run(*inputs)


class StepPool:
    """A sampler's fixed-shape decode steps, kept across sessions so that their buffers and a compiled step's
    captured graphs are reused (a new batch size, picker or net builds another); one session uses a step at a time.

    mode: "static" or "compiled". After a compiled step fails (no working compiler, torch.compile raising) the pool
    logs one warning and hands out no more steps: the sampler decodes eagerly from then on.
    tokens_per_call: image tokens each call of a step decodes, the token choice inside (`DecodeStep.block`); a
    picker without `prepare` (the vector simulator's RowwisePicker) decodes one per call.
    """

    def __init__(self, mode: str, tokens_per_call: int = 1):
        self.mode, self.tokens_per_call = mode, tokens_per_call
        self.steps: list[FixedStep] = []
        self.failure: str | None = None

    def block_for(self, picker: Any) -> int:
        """Tokens per call for `picker`: the eager choice of a picker without `prepare` comes between tokens."""
        return self.tokens_per_call if hasattr(picker, "prepare") else 1

    def fall_back(self, reason: str) -> None:
        """Decode eagerly from now on; the first reason is logged, in one line."""
        if self.failure is None:
            self.failure = reason
            log.warning("decode_step=%s: %s; decoding eagerly instead", self.mode, reason)

    def stream(self, session: SamplingSession, capacity: int) -> StaticStream | None:
        """A window stream on a free step, its cache emptied; None when decoding falls back to eager."""
        missing = [name for name in NEEDS if not hasattr(session.net, name)]
        if self.failure is None and missing:
            self.fall_back(f"{type(session.net).__name__} has no fixed-shape decode ({', '.join(missing)})")
        if self.failure is None and self.mode == "compiled" and not torch._dynamo.is_dynamo_supported():
            self.fall_back("torch.compile is not supported on this Python/PyTorch build")
        if self.failure is not None:
            return None
        step = self.acquire(session, capacity)
        if step is None:
            return None
        step.module.cache.reset()
        step.owner = weakref.ref(session)
        return StaticStream(self, step)

    def acquire(self, session: SamplingSession, capacity: int) -> FixedStep | None:
        net, tokens, streams = session.net, session.tokens, session.streams
        device = tokens.device
        # everything that changes the step's graph: a warm compiled step skips Dynamo's guards (FixedStep.__call__)
        key = (id(net), streams.text.shape[0], tokens.shape[0], tokens.shape[2], tuple(streams.actions.shape[2:]),
               streams.actions.dtype, capacity, cache_dtype(net, device), device, session.sampler.picker,
               session.guidance, session.noise_groups is None, torch.is_autocast_enabled(device.type),
               self.block_for(session.sampler.picker))
        for step in self.steps:
            if step.key == key and step.module.net is net and step.free_for(session):
                return step
        self.steps = [s for s in self.steps if s.key == key or not s.free_for(session)]  # drop idle ones of old keys
        cache = net.static_cache(key[1], capacity, key[7], device)
        block = key[-1]
        tail = None
        if block > 1 and (key[3] - 1) % block:  # the frame's last tokens, one per call on the same cache
            tail = self.build(net, cache, key, 1, streams.actions[:, 0])
            if tail is None:
                return None
        step = self.build(net, cache, key, block, streams.actions[:, 0], tail)
        if step is not None:
            self.steps.append(step)
        return step

    def build(self, net: nn.Module, cache: StaticKVCache, key: tuple, block: int, actions: torch.Tensor,
              tail: FixedStep | None = None) -> FixedStep | None:
        """A step of `block` tokens per call on `cache`, compiled in mode "compiled" (None after a failed compile)."""
        module = DecodeStep(net, cache, key[1] // key[2], key[3], actions, key[9], key[10], block)
        run, cuda_graphs = module, False
        if self.mode == "compiled":
            for tensor in module.buffers(recurse=False):  # static addresses: never copied into a graph's inputs
                torch._dynamo.mark_static_address(tensor)
            try:
                # dynamic=False: every shape is fixed by the pool's key, and a graph Dynamo made dynamic after a
                # size change (another batch or k) fails the guard-free calls of a warm step
                run = torch.compile(module, **({"dynamic": False} | compile_options(actions.device)))
            except Exception as error:  # noqa: BLE001 — any failure to compile means: decode eagerly
                self.fall_back(f"torch.compile raised {type(error).__name__}: {first_line(error)}")
                return None
            cuda_graphs = compile_options(actions.device).get("mode") == "reduce-overhead"
        return FixedStep(module, key, run, cuda_graphs, compiled=self.mode == "compiled", tail=tail)


def first_line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0][:200] if text else "no message"


class StaticStream:
    """A context window decoded on a StaticKVCache: eager chunks (`feed`) and the fixed-shape step per token."""

    def __init__(self, pool: StepPool, step: FixedStep):
        self.pool, self.step = pool, step
        self.net, self.cache = step.module.net, step.module.cache

    def feed(self, x: torch.Tensor) -> torch.Tensor:
        """Append embedded positions x: (B, L, d) eagerly; return the logits after the last one (B, V)."""
        return self.net.head(self.net.decode(x, self.cache)[:, -1])

    def decode_frame(self, session: SamplingSession, tokens: torch.Tensor, t: int, scales: torch.Tensor | None,
                     token: torch.Tensor, vocabulary: int) -> int:
        """Pick tokens 1.. of window step t (tokens (b, ≥ t + 1, n), token 0 picked: `token` (b,)) with the
        fixed-shape step; scales (n,): guidance per token or None; vocabulary: V. Return the index of the first token
        left to the eager loop (n when none, 1 at window step 0 or after a fallback)."""
        if t == 0 or self.step is None or self.pool.failure is not None:
            return 1
        n, b = tokens.shape[2], tokens.shape[0]
        self.step.begin_frame(tokens[:, t - 1].repeat(self.step.module.copies, 1), session.streams.actions[:, t - 1])
        index = torch.arange(n - 1, device=tokens.device)
        where = torch.stack([index, index + self.cache.next_position, index + self.cache.length,
                             torch.full_like(index, t)], dim=1)  # (n − 1, 4): token i + 1's inputs in row i
        scales = None if scales is None else scales[1:].to(tokens.device, torch.float64)
        picker = session.sampler.picker
        i = 1
        while i < n:
            step = self.step if n - i >= self.step.module.block else self.step.tail
            block = step.module.block
            rows = slice(i - 1, i - 1 + block)
            gumbel, noise = self.draws(session, picker, block, b, vocabulary)
            try:
                out = step(token, where[rows], None if scales is None else scales[rows], gumbel, noise)
            except Exception as error:  # noqa: BLE001 — a compiled step that cannot run: decode eagerly
                if self.pool.mode != "compiled":
                    raise
                self.pool.fall_back(f"the compiled step raised {type(error).__name__}: {first_line(error)}")
                self.step = None
                return i
            if hasattr(picker, "prepare"):
                # a captured graph's outputs live in its memory pool, overwritten by the next replay
                chosen = out.clone() if step.cuda_graphs else out  # (block, b)
                tokens[:, t, i : i + block] = chosen.T
                token = chosen[-1]
            else:
                token = picker(out, session.generator, session.gumbel(out.shape[-1]))
                tokens[:, t, i] = token
            self.cache.advance(block)
            i += block
        return n

    @staticmethod
    def draws(session: SamplingSession, picker: Any, block: int, rows: int,
              vocabulary: int) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """The random draws of the next `block` tokens, in eager decoding's order: per token its shared noise
        (gumbel (block, b, V)) when rows share noise, else the exponential noise of its multinomial draw (noise
        (block, b, c)); None where a token draws nothing (argmax) or the picker draws eagerly (no `prepare`)."""
        if not hasattr(picker, "prepare"):
            return None, None
        gumbel = [session.gumbel(vocabulary) for _ in range(block)] if session.noise_groups is not None else None
        shape = picker.draw_shape(rows, vocabulary)
        if gumbel is not None or shape is None:
            return None if gumbel is None else torch.stack(gumbel), None
        device = session.tokens.device
        return None, torch.stack([picker.draw(shape, session.generator, device) for _ in range(block)])
