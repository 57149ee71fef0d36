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
    net = ImageTokenizer(channels=4, channel_mults=(1, 1, 1, 1, 1), blocks_per_stage=1, latent_dim=8,
                         codebook_size=8192)
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


def test_plain_vq_ablation_picks_nearest_raw_code() -> None:
    """factorized=False: no projection, no normalisation, Euclidean nearest neighbour (plain VQ-VAE)."""
    torch.manual_seed(0)
    vq = FactorizedVectorQuantizer(dim=4, codebook_size=16, code_dim=2, factorized=False)
    assert vq.codebook.weight.shape == (16, 4) and not any(p is vq.codebook.weight for p in vq.project_in.parameters())
    feats = torch.randn(2, 4, 3, 3) * 3
    out = vq(feats)
    dists = torch.cdist(feats.permute(0, 2, 3, 1).reshape(-1, 4), vq.codebook.weight)
    assert torch.equal(out.tokens.flatten(), dists.argmin(-1))
    assert torch.allclose(vq.embed(out.tokens), out.quantized, atol=1e-5)
    net = tiny(factorized=False)
    x = torch.rand(1, 3, 16, 16) * 2 - 1
    assert torch.allclose(net.decode(net.encode(x)), net(x).reconstruction, atol=1e-5)


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


def test_distill_head_projects_quantized_features_to_teacher_dim() -> None:
    net = tiny(distill_dim=24)
    out = net(torch.rand(2, 3, 16, 16) * 2 - 1)
    assert net.distill(out.quantized).shape == (2, 24, 4, 4)
    with pytest.raises(ValueError, match="distill_dim=0"):
        tiny().distill(out.quantized)


def test_last_layer_is_the_decoder_output_convolution() -> None:
    net = tiny()
    assert net.last_layer is net.decoder.out[-1].weight
    assert net.last_layer.shape[0] == 3  # RGB out


# ---- GAN parts of the reconstruction loss (GAIA-1 §2.2, ref. [33]) --------------------------------


def test_patch_discriminator_scores_overlapping_patches() -> None:
    from gaia_app.nn.discriminator import PatchDiscriminator

    torch.manual_seed(0)
    disc = PatchDiscriminator(channels=8, num_layers=3)
    logits = disc(torch.rand(2, 3, 64, 64) * 2 - 1)
    # three stride-2 layers then two stride-1 4×4 convs: 64 → 8 → 7 → 6
    assert logits.shape == (2, 1, 6, 6)


def test_hinge_losses() -> None:
    from gaia_app.nn.discriminator import hinge_discriminator_loss, hinge_generator_loss

    confident = hinge_discriminator_loss(torch.full((2, 1, 3, 3), 2.0), torch.full((2, 1, 3, 3), -3.0))
    assert confident.item() == 0.0  # real > 1 and fake < -1: no loss
    undecided = hinge_discriminator_loss(torch.zeros(1, 1, 2, 2), torch.zeros(1, 1, 2, 2))
    assert undecided.item() == pytest.approx(1.0)
    assert hinge_generator_loss(torch.tensor([[1.0, 3.0]])).item() == pytest.approx(-2.0)


def test_adaptive_weight_matches_hand_computation() -> None:
    """Last layer W = [1, 2] on a fixed hidden h = [3, 4], output o = W·h = 11.
    rec = (o − 10)²  → ∇_W rec = 2(o − 10)·h, norm 2·1·5 = 10;
    gan = −0.5·o     → ∇_W gan = −0.5·h,       norm 0.5·5 = 2.5;
    weight = 10 / (2.5 + 1e-4)."""
    from gaia_app.nn.discriminator import adaptive_gan_weight

    last = torch.nn.Linear(2, 1, bias=False)
    with torch.no_grad():
        last.weight.copy_(torch.tensor([[1.0, 2.0]]))
    hidden = torch.tensor([3.0, 4.0], requires_grad=True)  # stands in for the rest of the decoder
    out = last(hidden)
    rec, gan = (out - 10.0).pow(2).sum(), (-0.5 * out).sum()
    weight = adaptive_gan_weight(rec, gan, last.weight)
    assert weight.item() == pytest.approx(10.0 / (2.5 + 1e-4), rel=1e-6)
    assert not weight.requires_grad
    assert adaptive_gan_weight(rec, gan, last.weight, max_weight=2.0).item() == 2.0  # clamped
    # both graphs survive for the backward pass that follows
    (rec + weight * gan).backward()
    assert last.weight.grad is not None


def test_codes_and_looked_up_vectors_are_unit_norm() -> None:
    """ViT-VQGAN look-up (GAIA-1 §2.2): codes live on the unit sphere, whatever the raw embedding scale."""
    vq = FactorizedVectorQuantizer(dim=8, codebook_size=32, code_dim=4)
    with torch.no_grad():
        vq.codebook.weight.mul_(7.0)
    assert torch.allclose(vq.normalized_codebook().norm(dim=-1), torch.ones(32), atol=1e-6)
    tokens = vq(torch.randn(2, 8, 3, 3)).tokens
    looked_up = vq.normalized_codebook()[tokens]
    assert torch.allclose(looked_up.norm(dim=-1), torch.ones_like(looked_up[..., 0]), atol=1e-6)
