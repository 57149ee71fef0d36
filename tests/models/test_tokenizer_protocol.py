"""The tokenizer protocol (models/tokenizer_protocol.py): the shipped tokenizer satisfies it, and a tokenizer that is
not an ImageTokenizer runs through the token pipelines unchanged (a tokenizer swap is a config change)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.models.gaia1.tokenizer import ImageTokenizer
from gaia_app.models.tokenizer_protocol import DiscreteTokenizer
from gaia_app.pipelines.gaia1_tokenizer import TokenCachePipeline, TokenizerReconstructionPipeline


class GreyLevels(nn.Module):
    """A toy tokenizer: each 4 × 4 cell's mean brightness, quantised to 8 grey levels."""

    codebook_size, downsampling = 8, 4

    def __init__(self) -> None:
        super().__init__()
        self.levels = nn.Parameter(torch.linspace(-1, 1, self.codebook_size), requires_grad=False)

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        grey = F.avg_pool2d(images.mean(dim=1, keepdim=True), self.downsampling)[:, 0]  # (b, h, w)
        return (grey[..., None] - self.levels).abs().argmin(dim=-1)

    def decode(self, tokens: torch.Tensor) -> torch.Tensor:
        grey = self.levels[tokens][:, None].expand(-1, 3, -1, -1)
        return F.interpolate(grey, scale_factor=self.downsampling, mode="nearest")

    def code_vectors(self) -> torch.Tensor:
        return self.levels[:, None].expand(-1, 3)


def test_the_image_tokenizer_satisfies_the_protocol() -> None:
    tokenizer = ImageTokenizer(channels=8, channel_mults=(1, 2), blocks_per_stage=1, latent_dim=8, codebook_size=16,
                               code_dim=4)
    assert isinstance(tokenizer, DiscreteTokenizer)
    assert tokenizer.code_vectors().shape == (16, 4)
    assert isinstance(GreyLevels(), DiscreteTokenizer) and not isinstance(nn.Linear(2, 2), DiscreteTokenizer)


def test_another_tokenizer_runs_through_the_token_pipelines() -> None:
    clip = SyntheticClipDataset(num_clips=1, seed=5, height=32, width=48, clip_len=3)[0]
    toy = GreyLevels()
    segments = TokenCachePipeline(toy, 32, 48).__call__(clip).segments
    assert segments[0].tokens.shape == (3, 8, 12) and segments[0].tokens.max() < toy.codebook_size
    video = torch.from_numpy(clip.frames).float() / 127.5 - 1  # (v, t, 3, H, W)
    out = TokenizerReconstructionPipeline(toy)(video)
    assert out.tokens.shape == (1, 3, 8, 12) and out.reconstruction.shape == video.shape
    assert out.psnr.mean() > 10  # grey cells still follow the scene's brightness
