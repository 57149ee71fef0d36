"""Text encoders for GAIA-1 conditioning (GAIA-1 §2.1): captions → (b, t, m, e) token features.

Legend:
    b batch, t time steps, m text tokens per step, e encoder width.

`LearnedTextEncoder` is a trainable word-embedding table over a small fixed vocabulary: no
download, so tests and the tiny experiments run anywhere. Its output goes through the world
model's trained linear layer like any pretrained encoder's (MiniLM, T5).
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import torch
from torch import nn

DEFAULT_WORDS = ("left", "right", "straight", "turn", "stop", "slow", "fast", "accelerate", "brake", "car", "bus",
                 "truck", "bike", "pedestrian", "road", "lane", "junction", "traffic", "light", "red", "green",
                 "rain", "sun", "night", "day", "snow", "fog", "urban", "rural", "highway", "parked", "ahead")


class LearnedTextEncoder(nn.Module):
    """Words of a fixed vocabulary → trainable embeddings; index 0 pads, 1 is any unknown word.

    Args:
        dim: e. tokens: m, words kept per caption (padded or truncated). words: the vocabulary.
    """

    def __init__(self, dim: int = 64, tokens: int = 4, words: Sequence[str] = DEFAULT_WORDS):
        super().__init__()
        self.tokens = tokens
        self.index = {w: i + 2 for i, w in enumerate(words)}
        self.embedding = nn.Embedding(len(words) + 2, dim, padding_idx=0)

    def ids(self, caption: str | None) -> list[int]:
        """m word ids of one caption (None: all padding)."""
        words = re.findall(r"[a-z]+", (caption or "").lower())[: self.tokens]
        ids = [self.index.get(w, 1) for w in words]
        return ids + [0] * (self.tokens - len(ids))

    def forward(self, captions: Sequence[Sequence[str | None]]) -> torch.Tensor:
        """b lists of t captions → (b, t, m, e)."""
        ids = torch.tensor([[self.ids(c) for c in steps] for steps in captions], device=self.embedding.weight.device)
        return self.embedding(ids)
