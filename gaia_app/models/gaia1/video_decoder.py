"""GAIA-1 video decoder: a 3D U-Net with factorised space and time layers for video diffusion (GAIA-1 §2.4).

Legend:
    b batch, t frames (≤ T', the clip length), n = b·t frames processed as images, c channels,
    H W image size, h w token grid (H/D, W/D; D the tokenizer's downsampling), d token-embedding
    width, e diffusion-time embedding width, s = b·h·w sequences of the temporal attention,
    a attention heads, k head width.

Following Ho et al. (GAIA-1 ref. [38]) every spatial layer (3×3 convs, GroupNorm, spatial attention)
sees one frame at a time, (b t) c h w, and only the temporal attention layers, (b h w) t c, mix
frames. With `temporal=False` those layers are skipped and every frame is an independent image
(GAIA-1 §2.4: "We disable temporal layers when training on images"). Their output projections
start at zero, so a fresh decoder is exactly an image model.

Each frame is conditioned on its own image tokens (embedded, brought to every U-Net resolution and
added in each residual block), on clean context pixels where `context_mask` holds (GAIA-1 Fig. 4
tasks) and on the diffusion step. Optionally (`render_tokens=True`) each frame also receives its tokens
rendered to pixels by the frozen tokenizer's image decoder as 3 more input channels, blanked where
tokens are masked: GAIA-1 does not say how the decoder embeds tokens, and a small decoder trained
briefly learns a 512-entry embedding from scratch far too slowly to read the tokens (docs/video_decoder.md).
The net predicts v (GAIA-1 §2.4, ref. [39]); the objective and
the samplers live in `gaia_app.diffusion`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from einops import rearrange, repeat
from torch import nn
from torch.utils.checkpoint import checkpoint

from gaia_app.nn.conv import downsample, group_norm, upsample

IN_CHANNELS = 7  # per frame: x_t (3) · masked clean context (3) · context mask (1)
RENDERED_CHANNELS = 3  # with render_tokens: the tokens decoded frame by frame, blanked where masked


def timestep_embedding(time: torch.Tensor, dim: int, max_period: float = 10_000.0) -> torch.Tensor:
    """Sinusoidal embedding of diffusion steps (Transformer / DDPM): (b,) → (b, dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=time.device, dtype=torch.float32) / half)
    angles = time.float()[:, None] * freqs[None]
    emb = torch.cat([torch.cos(angles), torch.sin(angles)], dim=-1)
    return F.pad(emb, (0, dim % 2))


def resize(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(n, c, h, w) → (n, c, *size): nearest-neighbour up (one token covers a D×D patch), area average down."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    if size[0] >= x.shape[-2] and size[1] >= x.shape[-1]:
        return F.interpolate(x, size=size, mode="nearest")
    return F.adaptive_avg_pool2d(x, size)


class ConditionedResBlock(nn.Module):
    """Per-frame residual block with diffusion-time scale/shift and additive token conditioning.

    x: (n, c_in, h, w), time: (n, e), tokens: (n, d, h', w') at any grid → (n, c_out, h, w).
    The 1×1 token projection runs on the token grid and is then resized to (h, w); a 1×1 conv commutes
    with nearest upsampling and with area averaging, so this equals projecting the resized map, at
    the cost of the token grid rather than of the full frame.
    """

    def __init__(self, in_channels: int, out_channels: int, time_dim: int, token_dim: int, dropout: float = 0.0):
        super().__init__()
        self.norm1 = group_norm(in_channels)
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, padding=1)
        self.token_proj = nn.Conv2d(token_dim, out_channels, 1)
        self.time_proj = nn.Linear(time_dim, 2 * out_channels)
        self.norm2 = group_norm(out_channels)
        self.dropout = nn.Dropout(dropout)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, padding=1)
        self.skip = nn.Conv2d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()

    def forward(self, x: torch.Tensor, time: torch.Tensor, tokens: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = h + resize(self.token_proj(tokens), h.shape[-2:])
        scale, shift = rearrange(self.time_proj(F.silu(time)), "n (two c) -> two n c 1 1", two=2)
        h = self.norm2(h) * (1 + scale) + shift  # ADM's scale-shift norm: the step modulates every block
        h = self.conv2(self.dropout(F.silu(h)))
        return self.skip(x) + h


class SpatialAttention(nn.Module):
    """Residual self-attention over the h·w positions of each frame: (n, c, h, w) → (n, c, h, w)."""

    def __init__(self, channels: int, heads: int):
        super().__init__()
        self.heads = heads
        self.norm = group_norm(channels)
        self.qkv = nn.Conv2d(channels, 3 * channels, 1)
        self.out = nn.Conv2d(channels, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        q, k, v = rearrange(self.qkv(self.norm(x)), "n (three a k) h w -> three n a (h w) k", three=3, a=self.heads)
        y = F.scaled_dot_product_attention(q, k, v)
        return x + self.out(rearrange(y, "n a (h w) k -> n (a k) h w", h=x.shape[-2]))


class TemporalAttention(nn.Module):
    """Residual, bidirectional self-attention over frames at each spatial position (Ho et al. [38]).

    x: (b·t, c, h, w) → (b·t, c, h, w). LayerNorm over c normalises each (frame, position) alone, so
    nothing but the attention itself mixes frames; a learned embedding of the frame index (≤ T')
    tells frames apart. The output projection is zero at init (see VideoDecoder.initialize_weights).
    """

    def __init__(self, channels: int, heads: int, frames: int):
        super().__init__()
        self.heads = heads
        self.norm = nn.LayerNorm(channels)
        self.position = nn.Parameter(torch.zeros(frames, channels))
        self.qkv = nn.Linear(channels, 3 * channels)
        self.out = nn.Linear(channels, channels)

    def forward(self, x: torch.Tensor, frames: int) -> torch.Tensor:
        height, width = x.shape[-2:]
        seq = rearrange(x, "(b t) c h w -> (b h w) t c", t=frames)
        qkv = self.qkv(self.norm(seq) + self.position[:frames])
        q, k, v = rearrange(qkv, "s t (three a k) -> three s a t k", three=3, a=self.heads)
        # t ≤ T' is tiny and s = b·h·w is huge: a plain softmax over a t×t matrix is cheap and avoids
        # the batch-size limits of fused SDPA kernels on GPU
        weights = torch.einsum("saik,sajk->saij", q, k * q.shape[-1] ** -0.5).softmax(dim=-1)
        y = rearrange(torch.einsum("saij,sajk->saik", weights, v), "s a t k -> s t (a k)")
        return x + rearrange(self.out(y), "(b h w) t c -> (b t) c h w", h=height, w=width)


class SpaceTimeBlock(nn.Module):
    """ResBlock → [spatial attention] → temporal attention: the repeated unit of the 3D U-Net.

    x: (b·t, c_in, h, w) → (b·t, c_out, h, w); time: (b·t, e); tokens: (b·t, d, h', w').
    `temporal=False` skips the temporal attention (image mode).
    """

    def __init__(self, in_channels: int, out_channels: int, time_dim: int, token_dim: int, heads: int,
                 frames: int, spatial_attention: bool, dropout: float = 0.0):
        super().__init__()
        self.res = ConditionedResBlock(in_channels, out_channels, time_dim, token_dim, dropout)
        self.spatial = SpatialAttention(out_channels, heads) if spatial_attention else None
        self.temporal = TemporalAttention(out_channels, heads, frames)

    def forward(self, x: torch.Tensor, time: torch.Tensor, tokens: torch.Tensor, frames: int,
                temporal: bool = True) -> torch.Tensor:
        x = self.res(x, time, tokens)
        if self.spatial is not None:
            x = self.spatial(x)
        return self.temporal(x, frames) if temporal else x


class Stage(nn.Module):
    """One U-Net resolution: a list of SpaceTimeBlocks, then an optional down/up-sampling conv."""

    def __init__(self, blocks: list[SpaceTimeBlock], resample: nn.Module | None):
        super().__init__()
        self.blocks = nn.ModuleList(blocks)
        self.resample = resample


@dataclass
class ResidualFrame:
    """The variable a (residual) decoder diffuses: x = (frames − base) / scale, per pixel.

    base: (b, t, 3, H, W) the rendered tokens where given, else 0; scale: (b, t, 1, H, W) residual_scale where
    tokens are given, else 1. The identity (base 0, scale 1) for a decoder that diffuses frames.
    """

    base: torch.Tensor
    scale: torch.Tensor

    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        """Frames (b, t, 3, H, W) in [−1, 1] → the diffused variable."""
        return (frames - self.base) / self.scale

    def decode(self, x: torch.Tensor) -> torch.Tensor:
        """Inverse of `encode`."""
        return x * self.scale + self.base

    def clip(self, x: torch.Tensor) -> torch.Tensor:
        """x clipped so that its frames lie in [−1, 1] (the per-pixel bounds of the diffused variable)."""
        return self.encode(self.decode(x).clamp(-1.0, 1.0))


class VideoDecoder(nn.Module):
    """3D U-Net predicting v for a noised clip from image tokens and clean context frames (GAIA-1 §2.4).

    Args:
        vocab_size: V, the tokenizer's codebook size; row V of the token embedding is the learned
            "no token" embedding (frames whose `token_mask` is False).
        token_grid: (h, w) at `image_size`; with it fixes the tokenizer's downsampling D = H/h, so
            other image sizes expect an (H/D, W/D) token grid.
        image_size: (H, W) the decoder is trained at (GAIA-1 §4.3: 288×512).
        frames: T', the most frames per clip (GAIA-1 §4.3: 7); sizes the temporal position embedding.
        channels: base width; level i has channels·channel_mults[i], and all but the last halve H and W.
        res_blocks: SpaceTimeBlocks per level on the way down (one more on the way up, ADM-style).
        attention_levels: levels (indices into channel_mults) with spatial self-attention; temporal
            attention runs after every residual block at every level.
        heads: attention heads (spatial and temporal). token_dim: d. dropout: in the residual blocks.
        checkpointing: recompute each SpaceTimeBlock's activations in backward (GAIA-1 §4.3).
        render_tokens: also take `rendered` (the tokenizer's frame-by-frame decoding of the tokens) as
            input channels; forward then requires it.
        residual: diffuse the residual over the rendered tokens, (x₀ − base) / residual_scale with base = the
            rendered frame where tokens are given, instead of x₀ (needs render_tokens); pixels without tokens
            (interpolation, dropped tokens) stay x₀ (`residual_frame`). The decoder then starts from the tokenizer's
            own picture and learns what frame-by-frame decoding gets wrong (temporal consistency) instead of the
            whole token → image mapping.
        residual_scale: s, the residual's divisor. The tokenizer's residual is ~4× smaller than the frames (std
            0.11 vs 0.43 for the reference tokenizer on the synthetic world): unscaled, the diffused signal drowns
            in the unit noise at all but the last steps and every error of x̂₀ lands in the pixels at full size.
            s = 0.25 gives residual and raw pixels one scale (docs/video_decoder.md); 1 leaves it unscaled.
    """

    block_types = (SpaceTimeBlock,)

    def __init__(self, vocab_size: int, token_grid: Sequence[int], image_size: Sequence[int], frames: int,
                 channels: int = 64, channel_mults: Sequence[int] = (1, 2, 4), res_blocks: int = 1,
                 attention_levels: Sequence[int] = (2,), heads: int = 4, token_dim: int = 64,
                 dropout: float = 0.0, checkpointing: bool = False, render_tokens: bool = False,
                 residual: bool = False, residual_scale: float = 1.0):
        super().__init__()
        if residual_scale <= 0:
            raise ValueError(f"VideoDecoder: residual_scale must be > 0, got {residual_scale}")
        if residual and not render_tokens:
            raise ValueError("VideoDecoder: residual=True diffuses the residual over the rendered tokens; "
                             "set render_tokens=True")
        self.vocab_size, self.frames, self.channels, self.checkpointing = vocab_size, frames, channels, checkpointing
        self.render_tokens, self.residual, self.residual_scale = render_tokens, residual, residual_scale
        self.token_grid, self.image_size = tuple(token_grid), tuple(image_size)
        self.downsampling = self._token_downsampling()
        self.unet_factor = 2 ** (len(channel_mults) - 1)
        widths = [channels * m for m in channel_mults]
        self._check_widths(widths, heads, attention_levels)
        time_dim = 4 * channels
        self.time_mlp = nn.Sequential(nn.Linear(channels, time_dim), nn.SiLU(), nn.Linear(time_dim, time_dim))
        self.token_embedding = nn.Embedding(vocab_size + 1, token_dim)  # last row: no token
        self.stem = nn.Conv2d(IN_CHANNELS + RENDERED_CHANNELS * render_tokens, channels, 3, padding=1)

        def block(c_in: int, c_out: int, attend: bool) -> SpaceTimeBlock:
            return SpaceTimeBlock(c_in, c_out, time_dim, token_dim, heads, frames, attend, dropout)

        skips, width = [channels], channels
        self.down = nn.ModuleList()
        for level, out in enumerate(widths):
            blocks = [block(width if i == 0 else out, out, level in attention_levels) for i in range(res_blocks)]
            width = out
            last = level == len(widths) - 1
            self.down.append(Stage(blocks, None if last else downsample(width)))
            skips += [width] * (res_blocks + (not last))
        self.mid = nn.ModuleList([block(width, width, True), block(width, width, False)])
        self.up = nn.ModuleList()
        for level, out in reversed(list(enumerate(widths))):
            blocks = []
            for _ in range(res_blocks + 1):
                blocks.append(block(width + skips.pop(), out, level in attention_levels))
                width = out
            self.up.append(Stage(blocks, upsample(width) if level > 0 else None))
        self.out = nn.Sequential(group_norm(width), nn.SiLU(), nn.Conv2d(width, 3, 3, padding=1))
        self.initialize_weights()

    def _token_downsampling(self) -> tuple[int, int]:
        """(D_h, D_w) = image_size / token_grid, both whole numbers."""
        (gh, gw), (height, width) = self.token_grid, self.image_size
        if height % gh or width % gw:
            raise ValueError(f"VideoDecoder: image_size {self.image_size} is not a whole multiple of token_grid "
                             f"{self.token_grid}; the tokenizer maps H×W to (H/D)×(W/D)")
        return height // gh, width // gw

    @staticmethod
    def _check_widths(widths: list[int], heads: int, attention_levels: Sequence[int]) -> None:
        if any(w % heads for w in widths):
            raise ValueError(f"VideoDecoder: every level width {widths} must divide by heads={heads}")
        if any(not 0 <= level < len(widths) for level in attention_levels):
            raise ValueError(f"VideoDecoder: attention_levels {list(attention_levels)} must index channel_mults "
                             f"(0..{len(widths) - 1})")

    def initialize_weights(self) -> None:
        """Zero every residual branch's last layer (ADM) and the temporal output projections (image model at init).

        Zero temporal projections make each temporal attention an identity, so a fresh decoder equals
        its image mode; training on videos then grows the temporal mixing from there (Ho et al. [38]).
        """
        for module in self.modules():
            if isinstance(module, ConditionedResBlock):
                nn.init.zeros_(module.conv2.weight)
                nn.init.zeros_(module.conv2.bias)
            elif isinstance(module, (SpatialAttention, TemporalAttention)):
                nn.init.zeros_(module.out.weight)
                nn.init.zeros_(module.out.bias)
            if isinstance(module, TemporalAttention):
                nn.init.normal_(module.position, std=0.02)
        nn.init.normal_(self.token_embedding.weight, std=0.02)

    def temporal_layers(self) -> list[TemporalAttention]:
        """Every temporal attention layer (the ones `temporal=False` skips)."""
        return [m for m in self.modules() if isinstance(m, TemporalAttention)]

    def expected_token_grid(self, height: int, width: int) -> tuple[int, int]:
        """Token grid (h, w) of an H×W frame: (H / D_h, W / D_w)."""
        return height // self.downsampling[0], width // self.downsampling[1]

    def _check_inputs(self, x_t: torch.Tensor, time: torch.Tensor, tokens: torch.Tensor, token_mask: torch.Tensor,
                      context: torch.Tensor, context_mask: torch.Tensor, rendered: torch.Tensor | None) -> None:
        """Raise a ValueError naming the offending shape and the one expected."""
        if x_t.ndim != 5 or x_t.shape[2] != 3:
            raise ValueError(f"VideoDecoder: x_t must be (b, t, 3, H, W); got {tuple(x_t.shape)}")
        b, t, _, height, width = x_t.shape
        if not 1 <= t <= self.frames:
            raise ValueError(f"VideoDecoder: x_t has t={t} frames; expected 1 ≤ t ≤ frames={self.frames}")
        dh, dw = self.downsampling
        factor = math.lcm(self.unet_factor, dh, dw)
        if height % self.unet_factor or width % self.unet_factor or height % dh or width % dw:
            raise ValueError(f"VideoDecoder: frames are {height}×{width}; H and W must divide by the U-Net's "
                             f"2^(levels-1)={self.unet_factor} and the token downsampling D={dh}×{dw} "
                             f"(multiples of {factor})")
        grid = self.expected_token_grid(height, width)
        # token_mask per frame (b, t) or per token (b, t, h, w): the §2.4 token dropout masks single tokens
        mask_shape = (b, t) if token_mask.ndim == 2 else (b, t, *grid)
        expected = {"time": (b,), "tokens": (b, t, *grid), "token_mask": mask_shape, "context": tuple(x_t.shape),
                    "context_mask": (b, t)}
        given = {"time": time, "tokens": tokens, "token_mask": token_mask, "context": context,
                 "context_mask": context_mask}
        if self.render_tokens:
            if rendered is None:
                raise ValueError("VideoDecoder: built with render_tokens=True, so forward needs `rendered` "
                                 "(b, t, 3, H, W), "
                                 "the tokenizer's frame-by-frame decoding of the tokens")
            expected["rendered"], given["rendered"] = tuple(x_t.shape), rendered
        elif rendered is not None:
            raise ValueError("VideoDecoder: got `rendered` but was built with render_tokens=False")
        for name, shape in expected.items():
            if tuple(given[name].shape) != shape:
                raise ValueError(f"VideoDecoder: {name} has shape {tuple(given[name].shape)}; expected {shape} "
                                 f"for x_t {tuple(x_t.shape)} (token grid {grid} = H/{dh} × W/{dw})")

    def embed_tokens(self, tokens: torch.Tensor, token_mask: torch.Tensor) -> torch.Tensor:
        """tokens (b, t, h, w) int64, token_mask (b, t) or (b, t, h, w) bool → (b·t, d, h, w); masked frames or
        tokens get the no-token row."""
        no_token = torch.full_like(tokens, self.vocab_size)
        keep = token_mask[:, :, None, None] if token_mask.ndim == 2 else token_mask
        tokens = torch.where(keep, tokens, no_token)  # their values are never read
        return rearrange(self.token_embedding(tokens), "b t h w d -> (b t) d h w")

    def stem_input(self, x_t: torch.Tensor, context: torch.Tensor, context_mask: torch.Tensor,
                   rendered: torch.Tensor | None = None, token_mask: torch.Tensor | None = None) -> torch.Tensor:
        """Per-frame input [x_t, context·mask, mask(, rendered·token mask)]: (b, t, 3, H, W) ×2, (b, t)
        → (b·t, 7, H, W), or (b·t, 10, H, W) with `rendered` (b, t, 3, H, W) and token_mask (b, t) / (b, t, h, w)."""
        mask = context_mask[:, :, None, None, None].to(x_t.dtype)
        clean = torch.where(mask.bool(), context, torch.zeros_like(context))  # zeros, even where context is NaN
        parts = [x_t, clean, mask.expand(-1, -1, 1, *x_t.shape[-2:])]
        if rendered is not None and token_mask is not None:
            parts.append(torch.where(self.pixel_token_mask(token_mask, x_t.shape[-2:]), rendered,
                                     torch.zeros_like(rendered)))
        return rearrange(torch.cat(parts, dim=2), "b t c h w -> (b t) c h w")

    def residual_frame(self, rendered: torch.Tensor | None, token_mask: torch.Tensor,
                       like: torch.Tensor) -> ResidualFrame:
        """What the decoder diffuses for frames shaped like `like` (b, t, 3, H, W): the residual over the rendered
        tokens, divided by residual_scale, where tokens are given (token_mask (b, t) or (b, t, h, w)); the frame
        itself elsewhere, and everywhere unless `residual`."""
        if not self.residual:
            return ResidualFrame(torch.zeros_like(like), torch.ones_like(like[:, :, :1]))
        given = self.pixel_token_mask(token_mask, like.shape[-2:])
        scale = torch.where(given, torch.full_like(given, self.residual_scale, dtype=like.dtype),
                            torch.ones_like(given, dtype=like.dtype))
        return ResidualFrame(torch.where(given, rendered, torch.zeros_like(rendered)), scale)

    def pixel_token_mask(self, token_mask: torch.Tensor, size: Sequence[int]) -> torch.Tensor:
        """token_mask (b, t) or (b, t, h, w) → (b, t, 1, H, W): each token covers its D×D patch."""
        if token_mask.ndim == 2:
            return token_mask[:, :, None, None, None].expand(-1, -1, 1, *size)
        dh, dw = self.downsampling
        return repeat(token_mask, "b t h w -> b t 1 (h dh) (w dw)", dh=dh, dw=dw)

    def _block(self, block: SpaceTimeBlock, h: torch.Tensor, time: torch.Tensor, tokens: torch.Tensor,
               frames: int, temporal: bool) -> torch.Tensor:
        if self.checkpointing and self.training:
            return checkpoint(block, h, time, tokens, frames, temporal, use_reentrant=False)
        return block(h, time, tokens, frames, temporal)

    def forward(self, x_t: torch.Tensor, time: torch.Tensor, tokens: torch.Tensor, token_mask: torch.Tensor,
                context: torch.Tensor, context_mask: torch.Tensor, temporal: bool = True,
                rendered: torch.Tensor | None = None) -> torch.Tensor:
        """v-prediction for a noised clip (GAIA-1 §2.4, eq. 2).

        x_t: (b, t, 3, H, W) noised frames; time: (b,) diffusion steps; tokens: (b, t, h, w) int64;
        token_mask: (b, t) bool, False → no tokens for that frame (interpolation, token dropout);
        context: (b, t, 3, H, W) clean frames, read only where context_mask (b, t) is True;
        temporal: False skips the temporal layers, so frames are independent images;
        rendered: (b, t, 3, H, W) the tokens decoded by the tokenizer, required iff render_tokens.
        Returns v: (b, t, 3, H, W).
        """
        self._check_inputs(x_t, time, tokens, token_mask, context, context_mask, rendered)
        frames = x_t.shape[1]
        emb = repeat(self.time_mlp(timestep_embedding(time, self.channels)), "b e -> (b t) e", t=frames)
        tok = self.embed_tokens(tokens, token_mask)
        h = self.stem(self.stem_input(x_t, context, context_mask, rendered, token_mask))  # (b·t, c, H, W)
        skips = [h]
        for stage in self.down:
            for block in stage.blocks:
                h = self._block(block, h, emb, tok, frames, temporal)
                skips.append(h)
            if stage.resample is not None:
                h = stage.resample(h)
                skips.append(h)
        for block in self.mid:
            h = self._block(block, h, emb, tok, frames, temporal)
        for stage in self.up:
            for block in stage.blocks:
                h = self._block(block, torch.cat([h, skips.pop()], dim=1), emb, tok, frames, temporal)
            if stage.resample is not None:
                h = stage.resample(h)
        return rearrange(self.out(h), "(b t) c h w -> b t c h w", t=frames)
