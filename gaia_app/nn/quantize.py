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
        factorized: False gives plain VQ-VAE (ref. [28]) for the ablation: no projection (e = d),
            no L2 normalisation, nearest code in Euclidean distance.
    """

    def __init__(self, dim: int, codebook_size: int, code_dim: int = 32, beta: float = 0.25, factorized: bool = True):
        super().__init__()
        self.codebook_size, self.beta, self.factorized = codebook_size, beta, factorized
        code_dim = code_dim if factorized else dim
        self.project_in = nn.Conv2d(dim, code_dim, 1) if factorized else nn.Identity()
        self.project_out = nn.Conv2d(code_dim, dim, 1) if factorized else nn.Identity()
        self.codebook = nn.Embedding(codebook_size, code_dim)
        nn.init.normal_(self.codebook.weight)

    def normalized_codebook(self) -> torch.Tensor:
        """(k, e) code vectors: unit-norm when factorised, as stored for plain VQ."""
        return F.normalize(self.codebook.weight, dim=-1) if self.factorized else self.codebook.weight

    def to_code_space(self, features: torch.Tensor) -> torch.Tensor:
        """(b, d, h, w) → (b, e, h, w) look-up vectors (projected and unit-norm when factorised)."""
        z = self.project_in(features)
        return F.normalize(z, dim=1) if self.factorized else z

    def forward(self, features: torch.Tensor) -> QuantizerOutput:
        """features: (b, d, h, w) → QuantizerOutput."""
        z = self.to_code_space(features)  # (b, e, h, w)
        flat = rearrange(z, "b e h w -> (b h w) e")
        codes = self.normalized_codebook()
        # argmin ‖z − c‖² = argmax (z·c − ‖c‖²/2); on the unit sphere the norm term is constant
        scores = flat @ codes.t()
        if not self.factorized:
            scores = scores - 0.5 * codes.pow(2).sum(-1)
        tokens = scores.argmax(dim=-1)
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
        z = rearrange(self.to_code_space(features), "b e h w -> (b h w) e")
        pick = torch.randint(0, len(z), (len(dead),), device=z.device)
        self.codebook.weight[dead] = z[pick].to(self.codebook.weight.dtype)
        return int(len(dead))
