"""GAIA-2 video tokenizer: continuous space-time latents from an asymmetric transformer autoencoder (GAIA-2 report,
tokenizer).

Legend:
    b batch, v cameras, T frames, t = T / τ latent steps (τ temporal downsampling, paper 8),
    H W frame size, h = H / s, w = W / s latent grid (s spatial downsampling, paper 32),
    C latent channels (paper 64), d transformer width, r conv-stage downsampling, p = s / r patch side.

Frames are float in [-1, 1]. Cameras are encoded independently (views folded into the batch); relating
the views is the latent world model's job.

Architecture (choices where the report is silent, all configurable):
- Encoder: a small convolutional stage per frame (downsampling r), a tubelet embedding of τ frames ×
  p×p positions into one token, a space-time factorised transformer over the latent steps of a chunk,
  and a linear head to the mean and log-variance of C channels (a diagonal Gaussian per token).
- Decoder (larger, "asymmetric"): a linear stem, a space-time factorised transformer whose temporal
  attention spans the chunk of latent steps it reconstructs (paper: 3 steps → 24 frames), a linear
  un-tubelet back to τ frames × p×p positions and a convolutional stage up to full resolution.
Positions are sine-cosine tables, so one network runs at any resolution divisible by s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from einops import rearrange
from torch import nn

from gaia_app.nn.conv import ConvDecoder, ConvEncoder, ResBlock
from gaia_app.nn.distributions import DiagonalGaussian
from gaia_app.nn.spacetime import SpaceTimeBlock, SpaceTimeTransformer, spacetime_positions


@dataclass
class VideoTokenizerOutput:
    """reconstruction: (b, v, T, 3, H, W); posterior over (b, v, t, C, h, w); latents: its sample (or mode)."""

    reconstruction: torch.Tensor
    posterior: DiagonalGaussian
    latents: torch.Tensor


class VideoEncoder(nn.Module):
    """(B, T, 3, H, W) frames → posterior parameters (B, t, 2C, h, w). B = b·v."""

    def __init__(self, spatial: int, temporal: int, latent_channels: int, conv_channels: int, conv_mults: Sequence[int],
                 conv_blocks: int, dim: int, depth: int, heads: int, mlp_ratio: float, checkpointing: bool):
        super().__init__()
        self.conv = ConvEncoder(3, conv_channels * conv_mults[-1], conv_channels, conv_mults, conv_blocks,
                                checkpointing) if conv_mults else None
        reduction = 2 ** (len(conv_mults) - 1) if conv_mults else 1
        patch = spatial // reduction
        in_channels = conv_channels * conv_mults[-1] if conv_mults else 3
        self.tubelet = nn.Conv3d(in_channels, dim, kernel_size=(temporal, patch, patch),
                                 stride=(temporal, patch, patch))
        self.transformer = SpaceTimeTransformer(dim, depth, heads, mlp_ratio, checkpointing=checkpointing)
        self.head = nn.Linear(dim, 2 * latent_channels)

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        b = frames.shape[0]
        x = rearrange(frames, "b T c H W -> (b T) c H W")
        if self.conv is not None:
            x = self.conv(x)
        x = self.tubelet(rearrange(x, "(b T) c H W -> b c T H W", b=b))  # b d t h w
        t, h, w = x.shape[-3:]
        tokens = rearrange(x, "b d t h w -> b t (h w) d")
        tokens = tokens + spacetime_positions(t, h, w, tokens.shape[-1], tokens.device).to(tokens.dtype)
        moments = self.head(self.transformer(tokens))
        return rearrange(moments, "b t (h w) c -> b t c h w", h=h)


class VideoDecoder(nn.Module):
    """(B, t, C, h, w) latents → (B, t·τ, 3, H, W) frames, temporal attention across the t steps given.

    With `refiner_channels` > 0 a full-resolution residual conv stage (not in GAIA-2) follows the tubelet head: a
    second linear head writes `refiner_features` channels per pixel, and the stage adds a correction computed from
    them and the tubelet RGB. Its output layer starts at zero, so a decoder with a refiner loaded from one without it
    decodes the same frames until it trains (docs/tokenizer.md, "Road users").
    """

    def __init__(self, spatial: int, temporal: int, latent_channels: int, conv_channels: int, conv_mults: Sequence[int],
                 conv_blocks: int, dim: int, depth: int, heads: int, mlp_ratio: float, checkpointing: bool,
                 refiner_channels: int = 0, refiner_blocks: int = 2, refiner_features: int = 8):
        super().__init__()
        reduction = 2 ** (len(conv_mults) - 1) if conv_mults else 1
        self.temporal, self.patch = temporal, spatial // reduction
        self.out_channels = conv_channels * conv_mults[-1] if conv_mults else 3
        self.stem = nn.Linear(latent_channels, dim)
        self.transformer = SpaceTimeTransformer(dim, depth, heads, mlp_ratio, checkpointing=checkpointing)
        self.untubelet = nn.Linear(dim, temporal * self.patch * self.patch * self.out_channels)
        self.conv = (ConvDecoder(self.out_channels, 3, conv_channels, conv_mults, conv_blocks, checkpointing)
                     if conv_mults else None)
        self.detail, self.refiner = None, None
        if refiner_channels:
            if conv_mults:
                raise ValueError("refiner_channels needs conv_mults=[] (the refiner follows the tubelet head; a conv "
                                 "stage already decodes at full resolution)")
            self.detail = nn.Linear(dim, temporal * self.patch * self.patch * refiner_features)
            self.refiner = ConvDecoder(3 + refiner_features, 3, refiner_channels, (1,), refiner_blocks, checkpointing)
            nn.init.zeros_(self.refiner.out[-1].weight)
            nn.init.zeros_(self.refiner.out[-1].bias)

    def forward(self, latents: torch.Tensor) -> torch.Tensor:
        b, t, _, h, w = latents.shape
        tokens = self.stem(rearrange(latents, "b t c h w -> b t (h w) c"))
        tokens = tokens + spacetime_positions(t, h, w, tokens.shape[-1], tokens.device).to(tokens.dtype)
        features = self.transformer(tokens)
        x = self.to_pixels(self.untubelet(features), h)
        if self.conv is not None:
            x = self.conv(x)
        if self.refiner is not None:
            x = x + self.refiner(torch.cat([x, self.to_pixels(self.detail(features), h)], dim=1))
        return rearrange(x, "(b T) c H W -> b T c H W", b=b)

    def to_pixels(self, tubelets: torch.Tensor, h: int) -> torch.Tensor:
        """(b, t, h·w, τ·p·p·c) per-token values → (b·t·τ, c, h·p, w·p) frames."""
        return rearrange(tubelets, "b t (h w) (tau p q c) -> (b t tau) c (h p) (w q)", h=h, tau=self.temporal,
                         p=self.patch, q=self.patch)

    @property
    def fresh_modules(self) -> tuple[str, ...]:
        """Submodules that start as an identity (a zero correction): weights without them still load."""
        return ("detail", "refiner") if self.refiner is not None else ()

    @property
    def last_layer(self) -> nn.Parameter:
        """Weight of the layer that writes pixels, where the GAN gradient is balanced against reconstruction."""
        if self.refiner is not None:
            return self.refiner.out[-1].weight
        return self.conv.out[-1].weight if self.conv is not None else self.untubelet.weight


class VideoTokenizer(nn.Module):
    """Continuous video autoencoder: (b, v, T, 3, H, W) ↔ Gaussian latents (b, v, T/τ, C, H/s, W/s) (GAIA-2 report,
    tokenizer).

    Args:
        spatial_downsampling: s (paper 32: 448×960 → 14×30).
        temporal_downsampling: τ (paper 8: 8 frames → 1 latent step).
        latent_channels: C (paper 64).
        chunk_latents: latent steps encoded and decoded together (paper: the decoder reconstructs
            3 steps = 24 frames with temporal attention). Longer inputs are split into such chunks.
        conv_channels, conv_mults, conv_blocks: convolutional stage around the transformers
            (r = 2^(len(conv_mults) − 1); s must divide by r); [] for a pure transformer on pixel tubelets.
        encoder_dim/depth/heads, decoder_dim/depth/heads: the asymmetric transformers (paper 85M / 200M).
        decoder_conv_channels: width of the decoder's conv stage (None: conv_channels).
        refiner_channels, refiner_blocks, refiner_features: the decoder's full-resolution residual refiner (not in
            GAIA-2; 0 channels: none; needs conv_mults=[]), see VideoDecoder.
        mlp_ratio: MLP hidden width over d.
        distill_dim: f, channels of the DINOv2 teacher; adds the trained 1×1 projection of the latent
            mean used by the distillation loss (GAIA-2 report, tokenizer). 0: none.
        checkpointing: activation checkpointing of the transformer blocks.
    """

    block_types: tuple[type[nn.Module], ...] = (SpaceTimeBlock, ResBlock)

    def __init__(
        self,
        spatial_downsampling: int = 32,
        temporal_downsampling: int = 8,
        latent_channels: int = 64,
        chunk_latents: int = 3,
        conv_channels: int = 64,
        conv_mults: Sequence[int] = (1, 2, 4),
        conv_blocks: int = 1,
        encoder_dim: int = 768,
        encoder_depth: int = 8,
        encoder_heads: int = 12,
        decoder_dim: int = 1024,
        decoder_depth: int = 12,
        decoder_heads: int = 16,
        decoder_conv_channels: int | None = None,
        refiner_channels: int = 0,
        refiner_blocks: int = 2,
        refiner_features: int = 8,
        mlp_ratio: float = 4.0,
        distill_dim: int = 0,
        checkpointing: bool = False,
    ):
        super().__init__()
        conv_mults = tuple(conv_mults)
        reduction = 2 ** (len(conv_mults) - 1) if conv_mults else 1
        if spatial_downsampling % reduction:
            raise ValueError(f"spatial_downsampling={spatial_downsampling} must divide by the conv stage's "
                             f"downsampling 2^(len(conv_mults) - 1) = {reduction}")
        self.spatial, self.temporal = spatial_downsampling, temporal_downsampling
        self.latent_channels, self.chunk_latents = latent_channels, chunk_latents
        self.encoder = VideoEncoder(spatial_downsampling, temporal_downsampling, latent_channels, conv_channels,
                                    conv_mults, conv_blocks, encoder_dim, encoder_depth, encoder_heads, mlp_ratio,
                                    checkpointing)
        self.decoder = VideoDecoder(spatial_downsampling, temporal_downsampling, latent_channels,
                                    decoder_conv_channels or conv_channels, conv_mults, conv_blocks, decoder_dim,
                                    decoder_depth, decoder_heads, mlp_ratio, checkpointing, refiner_channels,
                                    refiner_blocks, refiner_features)
        self.distill_dim = distill_dim
        self.distill_head = nn.Conv2d(latent_channels, distill_dim, 1) if distill_dim else None

    # ---- shape rules ---------------------------------------------------------------------

    def check_video(self, video: torch.Tensor) -> None:
        """Raise ValueError unless video is (b, v, T, 3, H, W) with T divisible by τ and H, W by s."""
        s, tau = self.spatial, self.temporal
        if video.ndim != 6 or video.shape[3] != 3:
            raise ValueError(f"VideoTokenizer expects video (b, v, T, 3, H, W); got {tuple(video.shape)}")
        frames, height, width = video.shape[2], video.shape[-2], video.shape[-1]
        if frames % tau:
            raise ValueError(f"VideoTokenizer: T={frames} frames is not a multiple of the temporal downsampling "
                             f"τ={tau}; give whole latent steps (e.g. the first {frames // tau * tau} frames)")
        if height % s or width % s:
            raise ValueError(f"VideoTokenizer: frames {height}×{width} are not multiples of the spatial "
                             f"downsampling s={s}; resize or crop to e.g. {height // s * s}×{width // s * s}")

    def latent_shape(self, frames: int, height: int, width: int) -> tuple[int, int, int, int]:
        """(t, C, h, w) of the latents of T frames of H×W."""
        return frames // self.temporal, self.latent_channels, height // self.spatial, width // self.spatial

    def chunks(self, steps: int) -> list[slice]:
        """Latent-step slices of at most `chunk_latents` steps covering 0..steps."""
        size = self.chunk_latents
        return [slice(i, min(i + size, steps)) for i in range(0, steps, size)]

    # ---- encode / decode -----------------------------------------------------------------

    def encode(self, video: torch.Tensor) -> DiagonalGaussian:
        """video (b, v, T, 3, H, W) → posterior over latents (b, v, T/τ, C, h, w), chunk by chunk."""
        self.check_video(video)
        b = video.shape[0]
        frames = rearrange(video, "b v T c H W -> (b v) T c H W")
        tau = self.temporal
        moments = torch.cat([self.encoder(frames[:, s.start * tau : s.stop * tau])
                             for s in self.chunks(frames.shape[1] // tau)], dim=1)
        mean, logvar = moments.chunk(2, dim=2)
        unfold = "(b v) t c h w -> b v t c h w"
        return DiagonalGaussian(rearrange(mean, unfold, b=b), rearrange(logvar, unfold, b=b))

    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        """latents (b, v, t, C, h, w) → video (b, v, t·τ, 3, H, W), unclamped; chunks of `chunk_latents` steps."""
        if latents.ndim != 6 or latents.shape[3] != self.latent_channels:
            raise ValueError(f"VideoTokenizer.decode expects latents (b, v, t, C={self.latent_channels}, h, w); "
                             f"got {tuple(latents.shape)}")
        b = latents.shape[0]
        folded = rearrange(latents, "b v t c h w -> (b v) t c h w")
        video = torch.cat([self.decoder(folded[:, s]) for s in self.chunks(folded.shape[1])], dim=1)
        return rearrange(video, "(b v) T c H W -> b v T c H W", b=b)

    def forward(self, video: torch.Tensor, sample: bool = True) -> VideoTokenizerOutput:
        """Encode, draw latents (posterior sample when `sample`, else its mode), decode."""
        posterior = self.encode(video)
        latents = posterior.sample() if sample else posterior.mode()
        return VideoTokenizerOutput(self.decode(latents), posterior, latents)

    def distill(self, latents: torch.Tensor) -> torch.Tensor:
        """Latents (b, v, t, C, h, w) → (b·v·t, f, h, w) in the DINOv2 teacher's feature space (GAIA-2 report,
        tokenizer)."""
        if self.distill_head is None:
            raise ValueError("VideoTokenizer was built with distill_dim=0: set the net's distill_dim to the teacher's "
                             "feature dim")
        return self.distill_head(rearrange(latents, "b v t c h w -> (b v t) c h w"))

    @property
    def last_layer(self) -> nn.Parameter:
        return self.decoder.last_layer

    @property
    def fresh_modules(self) -> tuple[str, ...]:
        """Modules (dotted names) that start as an identity: weights saved without them initialise the rest."""
        return tuple(f"decoder.{name}" for name in self.decoder.fresh_modules)

    def compression(self) -> float:
        """Input values per latent value: (τ·s²·3) / C (paper: 8·32²·3 / 64 = 384)."""
        return self.temporal * self.spatial**2 * 3 / self.latent_channels

    def storage_bits_per_pixel(self, bits_per_value: int = 16) -> float:
        """Bits per frame pixel to store the latent means at `bits_per_value` (16: bf16)."""
        return self.latent_channels * bits_per_value / (self.temporal * self.spatial**2)


def widen_latent_channels(weights: dict[str, torch.Tensor], net: VideoTokenizer,
                          read_new: bool = False) -> dict[str, torch.Tensor]:
    """Weights of a tokenizer with C₀ latent channels → weights that load into `net`, with C ≥ C₀ (not in GAIA-2; the
    road-users study, docs/tokenizer.md). The first C₀ channels keep their encoder rows (mean and log-variance) and
    their decoder and distillation columns; the new channels keep `net`'s own encoder rows and start unread (zero
    columns: the widened tokenizer decodes what the narrow one did until it trains), or with `read_new` keep `net`'s
    own columns too, so the decoder reads them from the first step."""
    narrow = weights["encoder.head.weight"].shape[0] // 2
    wide = net.latent_channels
    if narrow > wide:
        raise ValueError(f"widen_latent_channels: the weights have {narrow} latent channels, more than the net's "
                         f"{wide}")
    if narrow == wide:
        return weights
    own, out = net.state_dict(), dict(weights)
    for name in ("encoder.head.weight", "encoder.head.bias"):
        rows = own[name].clone()
        rows[:narrow], rows[wide : wide + narrow] = weights[name][:narrow], weights[name][narrow:]
        out[name] = rows
    for name in ("decoder.stem.weight", "distill_head.weight"):
        if name in weights:
            columns = own[name].clone() if read_new else torch.zeros_like(own[name])
            columns[:, :narrow] = weights[name]
            out[name] = columns
    return out


def kl_bits_per_pixel(posterior: DiagonalGaussian, frames: int, height: int, width: int) -> float:
    """The posterior's KL to N(0, I) in bits per frame pixel: the rate of the latent channel
    (bits-back coding), comparable across tokenizers with the GAIA-1 tokenizer's log2(K) bits per token."""
    kl_nats = posterior.kl().sum() / posterior.mean.shape[0]
    views = posterior.mean.shape[1]
    return float(kl_nats / math.log(2) / (views * frames * height * width))
