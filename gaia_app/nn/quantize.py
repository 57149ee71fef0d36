"""Vector quantisation with a factorised, L2-normalised codebook.

Legend: b batch, d feature channels, e code dim, h w grid, k codebook entries.

GAIA-1 §2.2: nearest-neighbour look-up in a learnable embedding table (VQ-VAE, ref. [28]) with the
linear projection to a low-dimensional code space and L2 normalisation of ViT-VQGAN (ref. [34]),
which the paper found to raise vocabulary usage.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn


@dataclass
class QuantizerOutput:
    """quantized: (b, d, h, w) straight-through features; tokens: (b, h, w) int64;
    codebook_loss / commitment_loss: scalars (VQ-VAE embedding and commitment terms)."""

    quantized: torch.Tensor
    tokens: torch.Tensor
    codebook_loss: torch.Tensor
    commitment_loss: torch.Tensor


class FactorizedVectorQuantizer(nn.Module):
    """Projects d-dim features to an e-dim code space, L2-normalises, snaps to the nearest code.

    Args:
        dim: channels d of the encoder features.
        codebook_size: K entries (paper 8192).
        code_dim: e, the low-dimensional look-up space (ViT-VQGAN uses 32).
        beta: commitment weight of VQ-VAE (0.25 as in ref. [28]).
    """

    def __init__(self, dim: int, codebook_size: int, code_dim: int = 32, beta: float = 0.25):
        super().__init__()
        self.codebook_size = codebook_size
        self.beta = beta
        self.project_in = nn.Conv2d(dim, code_dim, 1)
        self.project_out = nn.Conv2d(code_dim, dim, 1)
        self.codebook = nn.Embedding(codebook_size, code_dim)
        nn.init.normal_(self.codebook.weight)

    def normalized_codebook(self) -> torch.Tensor:
        """(k, e) unit-norm code vectors."""
        return F.normalize(self.codebook.weight, dim=-1)

    def forward(self, features: torch.Tensor) -> QuantizerOutput:
        """features: (b, d, h, w) → QuantizerOutput."""
        z = F.normalize(self.project_in(features), dim=1)  # (b, e, h, w)
        flat = rearrange(z, "b e h w -> (b h w) e")
        codes = self.normalized_codebook()
        # on the unit sphere, nearest in L2 == largest dot product
        tokens = (flat @ codes.t()).argmax(dim=-1)
        q = codes[tokens]
        codebook_loss = F.mse_loss(q, flat.detach())
        commitment_loss = self.beta * F.mse_loss(flat, q.detach())
        q = flat + (q - flat).detach()  # straight-through estimator
        b, _, h, w = z.shape
        q = rearrange(q, "(b h w) e -> b e h w", b=b, h=h, w=w)
        return QuantizerOutput(
            quantized=self.project_out(q),
            tokens=rearrange(tokens, "(b h w) -> b h w", b=b, h=h, w=w),
            codebook_loss=codebook_loss,
            commitment_loss=commitment_loss,
        )

    def embed(self, tokens: torch.Tensor) -> torch.Tensor:
        """tokens (b, h, w) int64 → decoder-ready features (b, d, h, w)."""
        q = rearrange(self.normalized_codebook()[tokens], "b h w e -> b e h w")
        return self.project_out(q)

    @torch.no_grad()
    def restart_dead_codes(self, features: torch.Tensor, usage: torch.Tensor) -> int:
        """Re-seed unused codes from random encoder outputs so they can win again.

        features: (b, d, h, w) recent encoder outputs; usage: (k,) counts since the last restart.
        Returns how many codes were restarted. (Remedy for codebook collapse, cf. ref. [34].)
        """
        dead = (usage == 0).nonzero(as_tuple=True)[0]
        if len(dead) == 0:
            return 0
        z = rearrange(F.normalize(self.project_in(features), dim=1), "b e h w -> (b h w) e")
        pick = torch.randint(0, len(z), (len(dead),), device=z.device)
        self.codebook.weight[dead] = z[pick].to(self.codebook.weight.dtype)
        return int(len(dead))
