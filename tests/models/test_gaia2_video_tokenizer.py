"""GAIA-2 video tokenizer network (GAIA-2 report, tokenizer): shapes, compression, chunking rules, the Gaussian
posterior."""

from __future__ import annotations

import math

import pytest
import torch
from torch.distributions import Normal, kl_divergence

from gaia_app.models.gaia2.video_tokenizer import VideoTokenizer, kl_bits_per_pixel
from gaia_app.nn.distributions import DiagonalGaussian

SMALL = dict(spatial_downsampling=8, temporal_downsampling=4, latent_channels=6, chunk_latents=2, conv_channels=8,
             conv_mults=(1, 2), encoder_dim=32, encoder_depth=1, encoder_heads=2, decoder_dim=48, decoder_depth=1,
             decoder_heads=2)


@pytest.fixture(scope="module")
def small() -> VideoTokenizer:
    torch.manual_seed(0)
    return VideoTokenizer(**SMALL).eval()


def video(b: int, v: int, t: int, h: int, w: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(b, v, t, 3, h, w, generator=torch.Generator().manual_seed(seed)) * 2 - 1


@pytest.mark.parametrize("size", [(32, 64), (64, 112), (48, 160)])
@pytest.mark.parametrize("frames", [4, 8, 12])
def test_shapes_and_compression_at_several_resolutions(small: VideoTokenizer, size: tuple[int, int],
                                                       frames: int) -> None:
    h, w = size
    x = video(1, 2, frames, h, w)
    with torch.no_grad():
        out = small(x)
    assert out.latents.shape == (1, 2, frames // 4, 6, h // 8, w // 8)
    assert small.latent_shape(frames, h, w) == out.latents.shape[2:]
    assert out.reconstruction.shape == x.shape
    # values in over values out: τ·s²·3 / C
    assert x.numel() / out.latents.numel() == small.compression() == 4 * 64 * 3 / 6


def test_paper_compression_factors() -> None:
    """GAIA-2 report, tokenizer: 448×960 → 14×30 per latent step, 8 frames → 1 step, 64 channels (a narrow net, same
    factors)."""
    net = VideoTokenizer(spatial_downsampling=32, temporal_downsampling=8, latent_channels=64, conv_channels=4,
                         conv_mults=(1, 2, 2, 2), encoder_dim=16, encoder_depth=1, encoder_heads=1, decoder_dim=16,
                         decoder_depth=1, decoder_heads=1)
    assert net.latent_shape(24, 448, 960) == (3, 64, 14, 30)
    assert net.compression() == 384
    with torch.no_grad():
        posterior = net.encode(video(1, 1, 16, 64, 96))
    assert posterior.mean.shape == (1, 1, 2, 64, 2, 3)


def test_frames_not_divisible_by_tau_are_refused(small: VideoTokenizer) -> None:
    with pytest.raises(ValueError, match=r"T=6 frames is not a multiple of the temporal downsampling τ=4.*first 4"):
        small.encode(video(1, 1, 6, 32, 64))


@pytest.mark.parametrize("shape, message", [((1, 1, 4, 3, 36, 64),
                                             r"36×64 are not multiples of the spatial downsampling s=8"),
                                            ((1, 4, 3, 32, 64), r"expects video \(b, v, T, 3, H, W\)"),
                                            ((1, 1, 4, 1, 32, 64), r"expects video \(b, v, T, 3, H, W\)")])
def test_bad_shapes_name_what_was_expected(small: VideoTokenizer, shape: tuple[int, ...], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        small.encode(torch.zeros(shape))


def test_decode_refuses_wrong_latent_channels(small: VideoTokenizer) -> None:
    with pytest.raises(ValueError, match=r"C=6"):
        small.decode(torch.zeros(1, 1, 2, 5, 4, 8))


def test_long_inputs_are_coded_in_chunks_of_chunk_latents(small: VideoTokenizer) -> None:
    """5 latent steps with chunk_latents=2 → the decoder runs on 2, 2 and 1 steps; the encoder on 8, 8 and 4 frames."""
    seen: dict[str, list[int]] = {"encoder": [], "decoder": []}
    hooks = [small.encoder.register_forward_pre_hook(lambda m, a: seen["encoder"].append(a[0].shape[1])),
             small.decoder.register_forward_pre_hook(lambda m, a: seen["decoder"].append(a[0].shape[1]))]
    try:
        with torch.no_grad():
            out = small(video(1, 1, 20, 32, 64), sample=False)
    finally:
        for hook in hooks:
            hook.remove()
    assert seen == {"encoder": [8, 8, 4], "decoder": [2, 2, 1]}
    assert out.reconstruction.shape[2] == 20


def test_a_chunk_is_coded_jointly_but_chunks_independently(small: VideoTokenizer) -> None:
    """Temporal attention spans a chunk: changing frames of step 1 moves step 0's latents (same chunk), not step 2's."""
    x = video(1, 1, 12, 32, 64)
    y = x.clone()
    y[:, :, 4:8] = video(1, 1, 4, 32, 64, seed=5)
    with torch.no_grad():
        a, b = small.encode(x).mean, small.encode(y).mean
    assert not torch.allclose(a[:, :, 0], b[:, :, 0])
    assert torch.equal(a[:, :, 2], b[:, :, 2])


def test_cameras_are_encoded_independently(small: VideoTokenizer) -> None:
    """Views are folded into the batch: a 2-camera clip encodes as its cameras do one by one."""
    x = video(1, 2, 8, 32, 64)
    with torch.no_grad():
        joint = small.encode(x).mean
        separate = torch.cat([small.encode(x[:, i : i + 1]).mean for i in range(2)], dim=1)
    torch.testing.assert_close(joint, separate, atol=1e-5, rtol=1e-5)


def test_posterior_sample_versus_mode() -> None:
    mean = torch.tensor([[0.5, -1.0, 2.0]])
    logvar = torch.tensor([[0.0, math.log(0.25), math.log(4.0)]])
    q = DiagonalGaussian(mean.expand(20_000, 3), logvar.expand(20_000, 3))
    assert torch.equal(q.mode(), q.mean)
    draws = q.sample(torch.Generator().manual_seed(0))
    torch.testing.assert_close(draws.mean(0), mean[0], atol=0.05, rtol=0)
    torch.testing.assert_close(draws.std(0), torch.tensor([1.0, 0.5, 2.0]), atol=0.05, rtol=0)
    assert torch.equal(q.sample(torch.Generator().manual_seed(1)), q.sample(torch.Generator().manual_seed(1)))


def test_model_sample_is_stochastic_and_mode_is_not(small: VideoTokenizer) -> None:
    x = video(1, 1, 4, 32, 64)
    with torch.no_grad():
        modes = [small(x, sample=False).latents for _ in range(2)]
        samples = [small(x, sample=True).latents for _ in range(2)]
    assert torch.equal(modes[0], modes[1])
    assert not torch.equal(samples[0], samples[1])


def test_kl_matches_the_closed_form_of_torch_distributions() -> None:
    g = torch.Generator().manual_seed(0)
    mean, logvar = torch.randn(4, 7, generator=g), torch.randn(4, 7, generator=g)
    expected = kl_divergence(Normal(mean, torch.exp(0.5 * logvar)), Normal(torch.zeros(()), torch.ones(())))
    torch.testing.assert_close(DiagonalGaussian(mean, logvar).kl(), expected)
    assert DiagonalGaussian(torch.zeros(3), torch.zeros(3)).kl().abs().max() == 0


def test_kl_bits_per_pixel_is_the_summed_kl_in_bits_over_frame_pixels() -> None:
    g = torch.Generator().manual_seed(0)
    q = DiagonalGaussian(torch.randn(2, 3, 1, 4, 2, 2, generator=g), torch.randn(2, 3, 1, 4, 2, 2, generator=g))
    expected = q.kl().sum().item() / 2 / math.log(2) / (3 * 8 * 16 * 16)
    assert kl_bits_per_pixel(q, 8, 16, 16) == pytest.approx(expected)


def test_mismatched_posterior_parameters_are_refused() -> None:
    with pytest.raises(ValueError, match="mean .* and logvar .* differ"):
        DiagonalGaussian(torch.zeros(2, 3), torch.zeros(2, 4))


def test_pure_transformer_variant_without_conv_stage() -> None:
    net = VideoTokenizer(**{**SMALL, "conv_mults": ()})
    with torch.no_grad():
        out = net(video(1, 1, 4, 32, 64))
    assert out.reconstruction.shape == (1, 1, 4, 3, 32, 64)
    assert net.last_layer is net.decoder.untubelet.weight


def test_conv_stage_must_divide_the_spatial_downsampling() -> None:
    with pytest.raises(ValueError, match=r"spatial_downsampling=12 must divide by .* = 8"):
        VideoTokenizer(**{**SMALL, "spatial_downsampling": 12, "conv_mults": (1, 2, 2, 2)})


def test_refiner_starts_as_the_decoder_without_it() -> None:
    """The refiner's output layer is zero at init: a decoder given a refiner decodes what the same weights decode
    without one, and the refiner's layer is where the GAN gradient is balanced."""
    pure = {**SMALL, "conv_mults": ()}
    torch.manual_seed(0)
    plain = VideoTokenizer(**pure).eval()
    refined = VideoTokenizer(**pure, refiner_channels=8, refiner_blocks=1, refiner_features=4).eval()
    missing, unexpected = refined.load_state_dict(plain.state_dict(), strict=False)
    assert not unexpected and missing and all(k.startswith(refined.fresh_modules) for k in missing)
    assert refined.fresh_modules == ("decoder.detail", "decoder.refiner") and plain.fresh_modules == ()
    with torch.no_grad():
        latents = torch.randn(1, 2, 2, 6, 4, 8)
        torch.testing.assert_close(refined.decode(latents), plain.decode(latents))
    assert refined.last_layer is refined.decoder.refiner.out[-1].weight


def test_refiner_corrects_every_pixel_once_trained() -> None:
    net = VideoTokenizer(**{**SMALL, "conv_mults": ()}, refiner_channels=8, refiner_blocks=1, refiner_features=4)
    torch.nn.init.normal_(net.decoder.refiner.out[-1].weight, std=0.1)
    with torch.no_grad():
        latents = torch.randn(1, 1, 1, 6, 4, 8)
        net.decoder.refiner.out[-1].weight.zero_()
        before = net.decode(latents)
        torch.nn.init.normal_(net.decoder.refiner.out[-1].weight, std=0.1)
        after = net.decode(latents)
    assert after.shape == before.shape == (1, 1, 4, 3, 32, 64)
    assert ((after - before).abs() > 0).float().mean() > 0.99


def test_refiner_needs_the_pure_transformer_decoder() -> None:
    with pytest.raises(ValueError, match=r"refiner_channels needs conv_mults=\[\]"):
        VideoTokenizer(**SMALL, refiner_channels=8)


def test_widened_latents_decode_what_the_narrow_tokenizer_decoded() -> None:
    """widen_latent_channels (the road-users study): a C = 6 tokenizer's weights start a C = 10 one whose first six
    channels are the narrow posterior's and whose four new channels the decoder does not read yet."""
    from gaia_app.models.gaia2.video_tokenizer import widen_latent_channels

    pure = {**SMALL, "conv_mults": (), "distill_dim": 5}
    torch.manual_seed(0)
    narrow = VideoTokenizer(**pure).eval()
    wide = VideoTokenizer(**{**pure, "latent_channels": 10}).eval()
    wide.load_state_dict(widen_latent_channels(narrow.state_dict(), wide))
    clip = video(1, 1, 4, 32, 64)
    with torch.no_grad():
        small, big = narrow.encode(clip), wide.encode(clip)
        torch.testing.assert_close(big.mean[:, :, :, :6], small.mean)
        torch.testing.assert_close(big.logvar[:, :, :, :6], small.logvar)
        latents = torch.cat([small.mean, torch.randn(1, 1, 1, 4, 4, 8)], dim=3)
        torch.testing.assert_close(wide.decode(latents), narrow.decode(small.mean))
        torch.testing.assert_close(wide.distill(latents), narrow.distill(small.mean))
    same = narrow.state_dict()
    assert widen_latent_channels(same, narrow) is same  # nothing to widen
    with pytest.raises(ValueError, match="10 latent channels, more than the net's 6"):
        widen_latent_channels(wide.state_dict(), narrow)
