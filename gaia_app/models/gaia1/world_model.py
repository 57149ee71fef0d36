"""GAIA-1 world model: a causal transformer over interleaved text · image · action tokens (GAIA-1 §2.1, §2.3).

Legend:
    b batch, t time steps (≤ T, the context length), m text tokens per step, n image tokens per step,
    l = 2 action tokens per step (speed, curvature), s = m + n + l tokens per step, d model width,
    e text-encoder width, V image vocabulary (tokenizer codebook size).

Per step the sequence holds (c_t, z_t, a_t); the whole input is (c_1, z_1, a_1, …, c_T, z_T, a_T).
Image token z_{t,i} is predicted from the hidden state one position earlier, so it sees
z_{<t}, z_{t,<i}, c_{≤t} and a_{<t} (eq. 1): the action of step t comes after z_t.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from einops import rearrange, repeat
from torch import nn

from gaia_app.nn.attention import KVCache, StaticKVCache
from gaia_app.nn.rope import StepRotary
from gaia_app.nn.transformer import CausalTransformer, TransformerBlock

STREAMS = ("text", "actions")
TEMPORAL_ENCODINGS = ("learned", "rope")
# conditioning modes drawn per training example (GAIA-1 §4.2: 20% / 40% / 40%, no both-conditions share)
DEFAULT_DROP = {"unconditional": 0.2, "actions": 0.4, "text": 0.4, "both": 0.0}
# (speed m/s, curvature 1/m) → (a − mean) / std before the linear projection. Raw curvature (~0.01 1/m) is
# ~1000× smaller than speed (~10 m/s), so through one shared initialisation its signal would vanish. These are
# the built-in synthetic world's scales (64 clips: mean 12.0 m/s and −0.002 1/m, std 7.7 m/s and 0.031 1/m);
# data with other speeds sets model.net.action_norm. The values are buffers, so checkpoints carry them.
DEFAULT_ACTION_NORM = {"mean": (10.0, 0.0), "std": (8.0, 0.03)}
# std of the step-to-step change of each action (action_deltas): at 6.25 Hz a brake of −4 m/s² changes the
# speed by −0.64 m/s per step, 0.08 of the speed's std above, while its change per step is ≈ 1.5 of this one;
# a command's curvature jumps by ≈ 0.02 1/m at the step it starts
DEFAULT_DELTA_STD = (0.4, 0.01)


@dataclass
class Conditions:
    """Condition tokens in model space: text (b, t, m, d), actions (b, t, l, d)."""

    text: torch.Tensor
    actions: torch.Tensor

    def steps(self, start: int, stop: int) -> Conditions:
        return Conditions(self.text[:, start:stop], self.actions[:, start:stop])

    def cat(self, other: Conditions) -> Conditions:
        """Stack two conditions along the batch (the guided and unguided streams in one forward)."""
        return Conditions(torch.cat([self.text, other.text]), torch.cat([self.actions, other.actions]))

    def then(self, other: Conditions) -> Conditions:
        """These steps followed by `other`'s (concatenated along time: a closed loop's next step)."""
        return Conditions(torch.cat([self.text, other.text], 1), torch.cat([self.actions, other.actions], 1))


class WorldModelConditioner(nn.Module):
    """Projects text embeddings and actions to d; drops them to learned null embeddings (GAIA-1 §2.1, §2.3).

    Args:
        dim: d. text_dim: e, width of the text encoder's output. text_tokens: m. action_tokens: l.
        drop: probabilities of the training modes {unconditional, actions, text, both} (normalised);
            a dropped stream is replaced by its null embedding, so the sequence layout never changes.
        action_norm: {"mean": (l,), "std": (l,)} in physical units (DEFAULT_ACTION_NORM when None), and with
            action_deltas {"delta_std": (l,)}, the std of each action's change per step (DEFAULT_DELTA_STD).
        action_deltas: each action token also embeds the action's change since the previous step (a_t − a_{t−1},
            0 at the first step given). Not in the paper: a command changes the speed by a few percent of its range
            per step, too little for the token of the speed alone to tell braking from cruising.
    """

    def __init__(self, dim: int, text_dim: int, text_tokens: int, action_tokens: int = 2,
                 drop: Mapping[str, float] | None = None, action_norm: Mapping[str, Sequence[float]] | None = None,
                 action_deltas: bool = False):
        super().__init__()
        norm = {"delta_std": DEFAULT_DELTA_STD, **dict(action_norm or DEFAULT_ACTION_NORM)}
        mean, std, delta_std = ([float(v) for v in norm.get(key, ())]  # floats: works on meta too
                                for key in ("mean", "std", "delta_std"))
        if (any(len(v) != action_tokens or min(v, default=0.0) <= 0 for v in (std, delta_std))
                or len(mean) != action_tokens):
            raise ValueError(f"action_norm needs 'mean', 'std' (and 'delta_std') with {action_tokens} values each, "
                             f"std > 0; got {dict(norm)}")
        # persistent: the scales the projection was trained with travel with the weights
        self.register_buffer("action_mean", torch.tensor(mean))
        self.register_buffer("action_std", torch.tensor(std))
        self.text_tokens, self.action_tokens = text_tokens, action_tokens
        self.text_proj = nn.Linear(text_dim, dim)
        # l independent scalar → d linear layers, one per action channel (speed, curvature)
        self.action_weight = nn.Parameter(torch.randn(action_tokens, dim) * 0.02)
        self.action_bias = nn.Parameter(torch.zeros(action_tokens, dim))
        self.action_deltas = action_deltas
        if action_deltas:
            self.register_buffer("delta_std", torch.tensor(delta_std))
            self.delta_weight = nn.Parameter(torch.randn(action_tokens, dim) * 0.02)
        self.null_text = nn.Parameter(torch.randn(text_tokens, dim) * 0.02)
        self.null_actions = nn.Parameter(torch.randn(action_tokens, dim) * 0.02)
        rates = {**DEFAULT_DROP, **dict(drop or {})}
        if set(rates) != set(DEFAULT_DROP) or min(rates.values()) < 0 or sum(rates.values()) <= 0:
            raise ValueError(f"drop needs non-negative rates for {sorted(DEFAULT_DROP)}, got {dict(drop or {})}")
        probs = torch.tensor([rates[k] for k in DEFAULT_DROP])
        self.register_buffer("mode_probs", probs / probs.sum(), persistent=False)

    def forward(self, batch: int, steps: int, text: torch.Tensor | None = None, actions: torch.Tensor | None = None,
                force_drop: Mapping[str, bool | torch.Tensor] | None = None) -> Conditions:
        """Condition tokens for `steps` steps; absent or dropped streams become null embeddings.

        text: (b, t, m, e) or None; actions: (b, t, l) or None.
        force_drop: per stream, True/False or a (b,) bool tensor that replaces the random drop
            (inference: e.g. {"text": True, "actions": False} is the unconditioned CFG stream).
        """
        keep = self.keep_masks(batch, force_drop)
        null_text = repeat(self.null_text, "m d -> b t m d", b=batch, t=steps)
        null_actions = repeat(self.null_actions, "l d -> b t l d", b=batch, t=steps)
        text_tokens = null_text if text is None else self.text_proj(text)
        action_tokens = null_actions if actions is None else self.embed_actions(actions)
        return Conditions(
            text=torch.where(keep["text"][:, None, None, None], text_tokens, null_text),
            actions=torch.where(keep["actions"][:, None, None, None], action_tokens, null_actions),
        )

    def normalise_actions(self, actions: torch.Tensor) -> torch.Tensor:
        """(…, l) physical (speed m/s, curvature 1/m) → (…, l) in units of the training data's std."""
        return (actions - self.action_mean) / self.action_std

    def embed_actions(self, actions: torch.Tensor) -> torch.Tensor:
        """(b, t, l) physical actions → (b, t, l, d): one scalar → d linear map per channel (GAIA-1 §2.1), plus
        one of the change since the previous step with action_deltas."""
        tokens = self.normalise_actions(actions)[..., None] * self.action_weight + self.action_bias
        if self.action_deltas:
            tokens = tokens + self.action_changes(actions)[..., None] * self.delta_weight
        return tokens

    def action_changes(self, actions: torch.Tensor) -> torch.Tensor:
        """(b, t, l) physical actions → (b, t, l) a_t − a_{t−1} in units of delta_std, 0 at the first step."""
        change = torch.diff(actions, dim=1, prepend=actions[:, :1])
        return change / self.delta_std

    def keep_masks(self, batch: int, force_drop: Mapping[str, bool | torch.Tensor] | None) -> dict[str, torch.Tensor]:
        """(b,) bool per stream: True keeps it. Random modes in training, keep-all in eval, then `force_drop`."""
        device = self.null_text.device
        if self.training:
            mode = torch.multinomial(self.mode_probs, batch, replacement=True)  # index into DEFAULT_DROP
            keep = {"actions": (mode == 1) | (mode == 3), "text": (mode == 2) | (mode == 3)}
        else:
            keep = {name: torch.ones(batch, dtype=torch.bool, device=device) for name in STREAMS}
        for name, drop in (force_drop or {}).items():
            if name not in STREAMS:
                raise ValueError(f"force_drop: unknown stream {name!r}, expected one of {STREAMS}")
            keep[name] = ~torch.as_tensor(drop, dtype=torch.bool, device=device).expand(batch)
        return keep


class WorldModel(nn.Module):
    """Decoder-only transformer predicting image tokens from interleaved text·image·action (GAIA-1 §2.3).

    Args:
        vocab_size: V, image-token vocabulary. dim, depth, heads, kv_heads, mlp_ratio: transformer
            (kv_heads < heads: grouped-query attention). frames: T, context length in steps.
        text_tokens: m (≥ 1: the last text token of a step predicts that step's first image token).
        image_tokens: n. action_tokens: l. text_dim: e.
        cond_drop: conditioning-mode rates (see WorldModelConditioner). checkpointing: activation checkpointing.
        action_norm: per-channel mean and std of the actions (see DEFAULT_ACTION_NORM).
        tie_embeddings: share the token embedding with the output head, so "predict the token embedded
            here" needs no separately learned output row per token (helps small token sets).
        previous_frame_shortcut: add to the position that predicts z_{t,i} the embedding of z_{t-1,i}, the
            token at the same grid cell one frame earlier (not in the paper; off in the paper preset).
            Learning to find that cell by attention alone takes far more data than a CPU run sees: on
            one minute of commaVQ tokens the model without it memorises the training frames and never
            beats copying the previous frame (docs/world_model.md has the ablation).
        action_shortcut: add to every position that predicts an image token of step t the sum of the action
            embeddings of step t - 1, the command that moved the ego from frame t - 1 to frame t (not in the
            paper; off in the paper preset). In GAIA-1 each action is one token that every image token has to
            find by attention; at CPU scale the model never learns to, and rollouts ignore their commands
            (docs/world_model.md measures both).
        temporal_encoding: "learned" (GAIA-1 §2.1: one learned embedding per window step) or "rope" (rotary
            positions over steps, gaia_app/nn/rope.py; not in the paper). With "rope" the attention sees only how
            far apart two steps are, so a sampler slides its window by dropping the oldest step from the KV cache
            instead of re-embedding the window (`rolling_cache`).
    """

    block_types = (TransformerBlock,)

    def __init__(self, vocab_size: int, dim: int, depth: int, heads: int, kv_heads: int | None = None,
                 frames: int = 26, text_tokens: int = 32, image_tokens: int = 576, action_tokens: int = 2,
                 text_dim: int = 384, mlp_ratio: float = 4.0, dropout: float = 0.0,
                 cond_drop: Mapping[str, float] | None = None, checkpointing: bool = False,
                 tie_embeddings: bool = False, previous_frame_shortcut: bool = False,
                 action_norm: Mapping[str, Sequence[float]] | None = None, action_shortcut: bool = False,
                 action_deltas: bool = False, temporal_encoding: str = "learned"):
        super().__init__()
        if text_tokens < 1:
            raise ValueError("text_tokens must be ≥ 1: the last text token of step t predicts z_{t,1}")
        if temporal_encoding not in TEMPORAL_ENCODINGS:
            raise ValueError(f"temporal_encoding={temporal_encoding!r}: expected one of {TEMPORAL_ENCODINGS}")
        self.temporal_encoding = temporal_encoding
        self.vocab_size, self.frames = vocab_size, frames
        self.m, self.n, self.l = text_tokens, image_tokens, action_tokens
        self.step_len = text_tokens + image_tokens + action_tokens
        self.previous_frame_shortcut = previous_frame_shortcut
        self.action_shortcut = action_shortcut
        self.conditioner = WorldModelConditioner(dim, text_dim, text_tokens, action_tokens, cond_drop, action_norm,
                                                 action_deltas)
        self.token_embedding = nn.Embedding(vocab_size, dim)
        if temporal_encoding == "learned":
            self.temporal = nn.Parameter(torch.zeros(frames, dim))  # shared by all tokens of a step
        self.spatial = nn.Parameter(torch.zeros(self.step_len, dim))  # position within a step
        rotary = StepRotary(dim // heads, self.step_len) if temporal_encoding == "rope" else None
        self.transformer = CausalTransformer(dim, depth, heads, kv_heads, mlp_ratio, dropout, checkpointing, rotary)
        self.head = nn.Linear(dim, vocab_size, bias=False)
        self.initialize_weights()
        if tie_embeddings:
            self.head.weight = self.token_embedding.weight

    def initialize_weights(self) -> None:
        """GPT-2 init for the transformer and head, N(0, 0.02) for embeddings and positions."""
        self.transformer.initialize_weights()
        for p in (self.token_embedding.weight, self.spatial, self.head.weight):
            nn.init.normal_(p, std=0.02)
        if self.temporal_encoding == "learned":
            nn.init.normal_(self.temporal, std=0.02)

    @property
    def rolling_cache(self) -> bool:
        """Whether a sampler may slide its window by dropping the oldest step from the KV cache (relative time)."""
        return self.temporal_encoding == "rope"

    def embed(self, tokens: torch.Tensor, cond: Conditions, start: int = 0,
              previous: torch.Tensor | None = None, previous_actions: torch.Tensor | None = None) -> torch.Tensor:
        """Interleaved, position-embedded inputs of whole steps (GAIA-1 §2.1).

        tokens: (b, t, n) int64; cond: t steps; start: window index of the first step → (b, t·s, d).
        previous: (b, n) tokens of the step before tokens[:, 0] within the window (previous-frame
            shortcut only); None when tokens[:, 0] opens the window.
        previous_actions: (b, l, d) action tokens (cond.actions) of that step (action shortcut only).
        """
        t = tokens.shape[1]
        if start + t > self.frames:
            raise ValueError(f"steps {start}..{start + t - 1} exceed the context of T={self.frames} steps")
        x = torch.cat([cond.text, self.token_embedding(tokens), cond.actions], dim=2)  # (b, t, s, d)
        x = x + self.spatial
        if self.temporal_encoding == "learned":  # with "rope" time enters the attention instead
            x = x + self.temporal[start : start + t, None]
        if self.previous_frame_shortcut:
            x = x + self.shortcut(tokens, previous)
        if self.action_shortcut:
            x = x + self.shortcut_actions(cond.actions, previous_actions)
        return rearrange(x, "b t s d -> b (t s) d")

    def shortcut_actions(self, actions: torch.Tensor, previous: torch.Tensor | None) -> torch.Tensor:
        """(b, t, s, d): the summed action tokens of step t - 1 (actions: (b, t, l, d)) at the n positions
        predicting z_{t,·}; zeros for the step opening the window unless `previous` (b, l, d) gives its actions."""
        earlier = actions[:, :-1].sum(dim=2)  # (b, t - 1, d)
        if previous is None:
            first = actions.new_zeros(actions.shape[0], 1, actions.shape[-1])
        else:
            first = previous.sum(1)[:, None]
        earlier = repeat(torch.cat([first, earlier], dim=1), "b t d -> b t n d", n=self.n)
        return nn.functional.pad(earlier, (0, 0, self.m - 1, self.l + 1))

    def shortcut(self, tokens: torch.Tensor, previous: torch.Tensor | None) -> torch.Tensor:
        """(b, t, s, d): embedding of z_{t-1,i} at the position predicting z_{t,i}, i.e. slot m - 1 + i.

        The step opening the window gets zeros there, exactly as in training windows.
        """
        earlier = self.token_embedding(tokens[:, :-1])  # (b, t - 1, n, d)
        if previous is None:  # built from the shape, not from `earlier`, which is empty for a 1-step window
            first = earlier.new_zeros(earlier.shape[0], 1, *earlier.shape[2:])
        else:
            first = self.token_embedding(previous[:, None])
        earlier = torch.cat([first, earlier], dim=1)
        # slots before m - 1 (text) and after m + n - 2 (last image token, actions) get nothing
        return nn.functional.pad(earlier, (0, 0, self.m - 1, self.l + 1))

    def decode(self, x: torch.Tensor, cache: KVCache | None = None) -> torch.Tensor:
        """Hidden states (b, L, d) of embedded positions x: (b, L, d), after the cache's positions if given."""
        return self.transformer(x, cache)

    def embed_token(self, tokens: torch.Tensor, slot: torch.Tensor, step: torch.Tensor, previous: torch.Tensor,
                    previous_actions: torch.Tensor) -> torch.Tensor:
        """The input (b, 1, d) of image token z_{step,slot}: what `embed` puts at position m + slot of window step
        `step`, summed in the same order, with slot and step as 0-dim int64 tensors so that one fixed-shape decode
        step serves every token. tokens: (b,) int64; previous: (b, n) tokens of step − 1 (previous-frame shortcut);
        previous_actions: (b, l, d) its action tokens (action shortcut). For step ≥ 1 (`embed` gives step 0 none)."""
        x = self.token_embedding(tokens)[:, None] + self.spatial.index_select(0, (self.m + slot).view(1))
        if self.temporal_encoding == "learned":
            x = x + self.temporal.index_select(0, step.view(1))
        feeds = slot + 1 < self.n  # this position predicts z_{step,slot+1}; the last image token predicts none
        if self.previous_frame_shortcut:  # embedding of z_{step−1,slot+1}, see `shortcut`
            earlier = self.token_embedding(previous.index_select(1, (slot + 1).clamp(max=self.n - 1).view(1)))
            x = x + torch.where(feeds, earlier, torch.zeros_like(earlier))
        if self.action_shortcut:  # the summed actions of step − 1, see `shortcut_actions`
            earlier = previous_actions.sum(1)[:, None]
            x = x + torch.where(feeds, earlier, torch.zeros_like(earlier))
        return x

    def decode_token(self, x: torch.Tensor, buffers: Sequence[tuple[torch.Tensor, torch.Tensor]], slot: torch.Tensor,
                     position: torch.Tensor) -> torch.Tensor:
        """Hidden state (b, d) of one embedded position x: (b, 1, d) in fixed shapes, against a StaticKVCache's
        buffers (written in place at `slot`); position: its absolute position (rotary time)."""
        return self.transformer.decode_static(x, buffers, slot, position)[:, -1]

    def static_cache(self, batch: int, capacity: int, dtype: torch.dtype, device: torch.device) -> StaticKVCache:
        """An empty StaticKVCache of `capacity` positions for a batch of `batch` sequences."""
        return self.transformer.static_cache(batch, capacity, dtype, device)

    def forward(self, tokens: torch.Tensor, cond: Conditions) -> torch.Tensor:
        """Next-image-token logits, aligned with their targets: tokens (b, t, n) → (b, t, n, V).

        logits[:, t, i] is read at the position just before z_{t,i} (eq. 1); text and action
        positions produce no output, so they can never be targets.
        """
        h = self.decode(self.embed(tokens, cond))
        h = rearrange(h, "b (t s) d -> b t s d", s=self.step_len)[:, :, self.m - 1 : self.m + self.n - 1]
        return self.head(h)


def next_token_loss(net: WorldModel, tokens: torch.Tensor, cond: Conditions) -> torch.Tensor:
    """Mean cross-entropy (nats/token) of eq. 1 over image tokens only. tokens: (b, t, n) int64 (GAIA-1 §2.3)."""
    logits = net(tokens, cond)
    return nn.functional.cross_entropy(rearrange(logits, "b t n v -> (b t n) v"), tokens.flatten())
