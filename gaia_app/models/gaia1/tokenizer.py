"""GAIA-1 image tokenizer: a discrete, fully convolutional autoencoder (GAIA-1 §2.2, §4.1).

Legend:
    b batch, c = 3 RGB channels, H W image size, h = H/D, w = W/D token grid, D downsampling,
    d feature channels, k codebook size, f distillation (DINO teacher) feature dim.

Images are float in [-1, 1]. Only the encoder (`encode`) is part of the final GAIA-1 model; the
decoder exists to train it (§2.2) and to preview tokens.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from gaia_app.nn.conv import ConvDecoder, ConvEncoder, ResBlock
from gaia_app.nn.quantize import FactorizedVectorQuantizer, QuantizerOutput


@dataclass
class TokenizerOutput:
    """reconstruction: (b, 3, H, W); quantized: (b, d, h, w) features also used for DINO
    distillation; tokens: (b, h, w) int64; codebook_loss, commitment_loss: scalars."""

    reconstruction: torch.Tensor
    quantized: torch.Tensor
    tokens: torch.Tensor
    codebook_loss: torch.Tensor
    commitment_loss: torch.Tensor


class ImageTokenizer(nn.Module):
    """Discrete U-Net-style autoencoder: image → D×-downsampled grid of tokens from a K-entry codebook.

    Args:
        channels: base width of encoder and decoder.
        channel_mults: per-stage width multipliers; D = 2 ** (len(channel_mults) - 1) (paper D = 16 → 5 stages).
        blocks_per_stage: residual blocks per stage.
        latent_dim: d, channels at the token grid.
        codebook_size: K (paper 8192).
        code_dim: dimension of the factorised look-up space (ViT-VQGAN, ref. [34]).
        commitment_beta: VQ-VAE commitment weight.
        distill_dim: f, channels of the DINO teacher's features (384 for ViT-S/16, 768 for ViT-B/16);
            adds the trained 1×1 projection of the quantised features used by the distillation loss
            (GAIA-1 §2.2). 0: no projection.
        factorized: True (paper): ViT-VQGAN's projected, L2-normalised look-up; False: plain VQ
            (ablation, `model.net.factorized=false`).
        checkpointing: recompute the encoder's and decoder's stages in backward (activation checkpointing).
    """

    block_types: tuple[type[nn.Module], ...] = (ResBlock,)

    def __init__(
        self,
        channels: int = 64,
        channel_mults: Sequence[int] = (1, 1, 2, 2, 4),
        blocks_per_stage: int = 2,
        latent_dim: int = 256,
        codebook_size: int = 8192,
        code_dim: int = 32,
        commitment_beta: float = 0.25,
        distill_dim: int = 0,
        factorized: bool = True,
        checkpointing: bool = False,
    ):
        super().__init__()
        self.downsampling = 2 ** (len(channel_mults) - 1)
        self.codebook_size = codebook_size
        self.encoder = ConvEncoder(3, latent_dim, channels, channel_mults, blocks_per_stage, checkpointing)
        self.quantizer = FactorizedVectorQuantizer(latent_dim, codebook_size, code_dim, commitment_beta, factorized)
        self.decoder = ConvDecoder(latent_dim, 3, channels, channel_mults, blocks_per_stage, checkpointing)
        self.distill_dim = distill_dim
        self.distill_head = nn.Conv2d(latent_dim, distill_dim, 1) if distill_dim else None

    def _check_size(self, x: torch.Tensor) -> None:
        d = self.downsampling
        if x.ndim != 4 or x.shape[1] != 3 or x.shape[-2] % d or x.shape[-1] % d:
            raise ValueError(f"ImageTokenizer expects images (b, 3, H, W) with H and W divisible by D={d}; "
                             f"got {tuple(x.shape)}")

    def quantize(self, x: torch.Tensor) -> QuantizerOutput:
        """x: (b, 3, H, W) in [-1, 1] → QuantizerOutput on the (h, w) grid."""
        self._check_size(x)
        return self.quantizer(self.encoder(x))

    def forward(self, x: torch.Tensor) -> TokenizerOutput:
        """x: (b, 3, H, W) in [-1, 1] → reconstruction and quantisation terms."""
        q = self.quantize(x)
        return TokenizerOutput(self.decoder(q.quantized), q.quantized, q.tokens, q.codebook_loss, q.commitment_loss)

    @torch.no_grad()
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """x: (b, 3, H, W) in [-1, 1] → tokens (b, h, w) int64."""
        return self.quantize(x).tokens

    def embed(self, tokens: torch.Tensor) -> torch.Tensor:
        """tokens (b, h, w) → quantised features (b, d, h, w), for downstream models."""
        return self.quantizer.embed(tokens)

    def decode(self, tokens: torch.Tensor) -> torch.Tensor:
        """tokens (b, h, w) int64 → images (b, 3, H, W), unclamped."""
        return self.decoder(self.embed(tokens))

    def code_vectors(self) -> torch.Tensor:
        """(k, d) the code vector of every token id (models/tokenizer_protocol.py)."""
        return self.quantizer.codebook.weight.detach()

    def distill(self, quantized: torch.Tensor) -> torch.Tensor:
        """Quantised features (b, d, h, w) → (b, f, h, w) in the DINO teacher's feature space (GAIA-1 §2.2)."""
        if self.distill_head is None:
            raise ValueError("ImageTokenizer was built with distill_dim=0: "
                             "set the net's distill_dim to the teacher's feature dim")
        return self.distill_head(quantized)

    @property
    def last_layer(self) -> nn.Parameter:
        """Weight of the decoder's output convolution, where the GAN loss is balanced against reconstruction."""
        return self.decoder.out[-1].weight

    def bits_per_image(self, height: int, width: int) -> float:
        """Bits needed for one image's tokens (paper §4.1 compression ratio denominator)."""
        n = (height // self.downsampling) * (width // self.downsampling)
        return n * math.log2(self.codebook_size)
