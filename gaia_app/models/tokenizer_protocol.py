"""The tokenizer protocol: what every consumer of a GAIA-1 image tokenizer may use (DESIGN.md §3), so that another
tokenizer (FSQ, a larger codebook, more tokens per frame) plugs in by its config alone.

Legend: b batch, H W image size, h = H/D, w = W/D token grid (D = `downsampling`), K codebook size, d code dim.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Protocol, runtime_checkable

import torch


@runtime_checkable
class DiscreteTokenizer(Protocol):
    """An image tokenizer seen from outside: ids in, ids out, and the code vectors behind the ids.

    codebook_size: K, ids are in [0, K); downsampling: D, the image size over the token grid.
    encode: images (b, 3, H, W) in [-1, 1] → ids (b, h, w) int64 (GAIA-1 §2.2);
    decode: ids (b, h, w) → images (b, 3, H, W), unclamped;
    code_vectors: (K, d) the vector of each id (token maps: PCA of these to RGB, GAIA-1 Fig. 3);
    parameters: its tensors (their device and hash: where to send images, which cache it made).
    """

    codebook_size: int
    downsampling: int

    def encode(self, images: torch.Tensor) -> torch.Tensor: ...

    def decode(self, tokens: torch.Tensor) -> torch.Tensor: ...

    def code_vectors(self) -> torch.Tensor: ...

    def parameters(self, recurse: bool = True) -> Iterator[torch.nn.Parameter]: ...
