"""GAIA-1 image tokenizer: shapes, quantiser semantics, round trip, and that it learns."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from gaia_app.models.gaia1.tokenizer import ImageTokenizer
from gaia_app.nn.quantize import FactorizedVectorQuantizer


def tiny(**kw) -> ImageTokenizer:
    torch.manual_seed(0)
    args = dict(channels=8, channel_mults=(1, 2, 2), blocks_per_stage=1, latent_dim=16, codebook_size=32, code_dim=8)
    return ImageTokenizer(**{**args, **kw})


def test_token_grid_follows_downsampling() -> None:
    net = tiny()
    assert net.downsampling == 4
    x = torch.rand(2, 3, 32, 48) * 2 - 1
    out = net(x)
    assert out.tokens.shape == (2, 8, 12) and out.tokens.dtype == torch.int64
    assert out.reconstruction.shape == x.shape
    assert int(out.tokens.max()) < 32


def test_paper_downsampling_and_bits() -> None:
    net = ImageTokenizer(channels=4, channel_mults=(1, 1, 1, 1, 1), blocks_per_stage=1, latent_dim=8, codebook_size=8192)
    assert net.downsampling == 16
    # GAIA-1 §4.1: 288×512 → 18×32 = 576 tokens of 13 bits
    assert net.bits_per_image(288, 512) == pytest.approx(576 * 13)


def test_bad_image_size_is_named() -> None:
    with pytest.raises(ValueError, match="divisible by D=4"):
        tiny()(torch.zeros(1, 3, 30, 48))


def test_quantizer_picks_nearest_normalized_code() -> None:
    torch.manual_seed(0)
    vq = FactorizedVectorQuantizer(dim=4, codebook_size=16, code_dim=4)
    feats = torch.randn(2, 4, 3, 3)
    out = vq(feats)
    z = F.normalize(vq.project_in(feats), dim=1).permute(0, 2, 3, 1).reshape(-1, 4)
    dists = torch.cdist(z, vq.normalized_codebook())
    assert torch.equal(out.tokens.flatten(), dists.argmin(-1))


def test_embed_of_tokens_equals_quantized_features() -> None:
    net = tiny()
    x = torch.rand(1, 3, 16, 16) * 2 - 1
    q = net.quantize(x)
    assert torch.allclose(net.embed(q.tokens), q.quantized, atol=1e-5)
    assert torch.allclose(net.decode(q.tokens), net(x).reconstruction, atol=1e-5)


def test_straight_through_gradient_reaches_encoder() -> None:
    net = tiny()
    out = net(torch.rand(1, 3, 16, 16))
    out.reconstruction.mean().backward()
    assert net.encoder.stem.weight.grad is not None and net.encoder.stem.weight.grad.abs().sum() > 0


def test_dead_codes_are_restarted_from_features() -> None:
    net = tiny()
    feats = net.encoder(torch.rand(2, 3, 16, 16))
    usage = torch.zeros(32, dtype=torch.long)
    usage[:4] = 10
    before = net.quantizer.codebook.weight[:4].clone()
    assert net.quantizer.restart_dead_codes(feats, usage) == 28
    assert torch.equal(net.quantizer.codebook.weight[:4], before)


def test_tokenizer_overfits_a_batch() -> None:
    """The reconstruction loss on one fixed batch falls by at least 4× in 150 steps."""
    net = tiny(codebook_size=64)
    torch.manual_seed(1)
    x = (torch.rand(4, 3, 1, 1) * 2 - 1).expand(4, 3, 16, 16) + 0.1 * torch.randn(4, 3, 16, 16)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(150):
        out = net(x)
        loss = F.mse_loss(out.reconstruction, x) + out.codebook_loss + out.commitment_loss
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(F.mse_loss(out.reconstruction, x).item())
    assert losses[-1] < losses[0] / 4, (losses[0], losses[-1])
