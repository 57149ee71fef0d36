"""GAIA-1 video decoder (§2.4): shapes, frame independence in image mode, masks, shape errors, and that it learns."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from hydra.utils import instantiate
from omegaconf import OmegaConf

from gaia_app.diffusion.noise_schedule import CosineNoiseSchedule
from gaia_app.diffusion.samplers import DDIMSampler
from gaia_app.diffusion.video_sampling import sample_window
from gaia_app.models.gaia1.video_decoder import VideoDecoder
from tests.conftest import CONF_DIR

H, W, GRID, VOCAB = 16, 24, (4, 6), 16


pytestmark = pytest.mark.usefixtures("one_thread")


def tiny(**kw) -> VideoDecoder:
    torch.manual_seed(0)
    args = dict(vocab_size=VOCAB, token_grid=GRID, image_size=(H, W), frames=7, channels=8, channel_mults=(1, 2),
                res_blocks=1, attention_levels=(1,), heads=2, token_dim=8)
    return VideoDecoder(**{**args, **kw})


def scramble(net: VideoDecoder, temporal: bool = True) -> VideoDecoder:
    """Give the zero-initialised layers random weights, so tokens, time and (if `temporal`) other frames reach the
    output."""
    temporal_params = {id(p) for layer in net.temporal_layers() for p in layer.out.parameters()}
    with torch.no_grad():
        for p in net.parameters():
            if not p.any() and (temporal or id(p) not in temporal_params):
                p.normal_(std=0.1)
    return net


def inputs(b: int = 2, t: int = 7, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return dict(
        x_t=torch.randn(b, t, 3, H, W, generator=g),
        time=torch.randint(0, 1000, (b,), generator=g),
        tokens=torch.randint(0, VOCAB, (b, t, *GRID), generator=g),
        token_mask=torch.ones(b, t, dtype=torch.bool),
        context=torch.rand(b, t, 3, H, W, generator=g) * 2 - 1,
        context_mask=torch.zeros(b, t, dtype=torch.bool),
    )


@pytest.mark.parametrize("t", [7, 1])
def test_output_shape(t: int) -> None:
    x = inputs(t=t)
    assert tiny()(**x).shape == (2, t, 3, H, W)


@torch.no_grad()
def test_fresh_decoder_is_an_image_model() -> None:
    """Zero-initialised temporal output projections: temporal layers are identities at init."""
    net = scramble(tiny(), temporal=False).eval()
    x = inputs()
    assert torch.allclose(net(**x), net(**x, temporal=False), atol=1e-6)


@torch.no_grad()
def test_image_mode_frames_are_independent() -> None:
    """temporal=False (GAIA-1 §2.4, eq. 4): perturbing frame 3 leaves every other frame exactly unchanged."""
    net = scramble(tiny()).eval()
    x = inputs()
    y = dict(x, x_t=x["x_t"].clone())
    y["x_t"][:, 3] += 1.0
    others = [0, 1, 2, 4, 5, 6]
    image_a, image_b = net(**x, temporal=False), net(**y, temporal=False)
    assert torch.equal(image_a[:, others], image_b[:, others])
    assert not torch.allclose(image_a[:, 3], image_b[:, 3])
    video_a, video_b = net(**x), net(**y)
    assert (video_a[:, others] - video_b[:, others]).abs().amax() > 1e-4  # temporal layers mix frames


@torch.no_grad()
def test_tokens_of_unmasked_frames_are_ignored() -> None:
    """token_mask False → the no-token embedding: that frame's token values change nothing anywhere."""
    net = scramble(tiny()).eval()
    x = inputs()
    x["token_mask"][:, 2] = False
    y = dict(x, tokens=x["tokens"].clone())
    y["tokens"][:, 2] = (y["tokens"][:, 2] + 1) % VOCAB
    assert torch.equal(net(**x), net(**y))
    y["tokens"][:, 1] = (y["tokens"][:, 1] + 1) % VOCAB  # control: frame 1 keeps its tokens
    assert not torch.allclose(net(**x)[:, 1], net(**y)[:, 1])


@torch.no_grad()
def test_context_is_read_only_where_masked() -> None:
    """context_mask False → the context values (even NaN) are never read; True → they condition the frame."""
    net = scramble(tiny()).eval()
    x = inputs()
    x["context_mask"][:, 0] = True
    y = dict(x, context=x["context"].clone())
    y["context"][:, 1:] = float("nan")
    assert torch.equal(net(**x), net(**y))
    y["context"][:, 0] = 0.0
    assert not torch.allclose(net(**x)[:, 0], net(**y)[:, 0])


@torch.no_grad()
def test_output_depends_on_diffusion_step() -> None:
    net = scramble(tiny()).eval()
    x = inputs()
    assert not torch.allclose(net(**x), net(**dict(x, time=x["time"] + 100)))


def test_checkpointing_gives_the_same_gradients() -> None:
    x = inputs(b=1, t=3)
    grads = []
    for checkpointing in (False, True):
        net = scramble(tiny(checkpointing=checkpointing)).train()
        net(**x).square().mean().backward()
        grads.append(torch.cat([p.grad.flatten() for p in net.parameters()]))
    assert torch.allclose(grads[0], grads[1], atol=1e-6)


@pytest.mark.parametrize(
    "change,message",
    [
        (lambda x: dict(x, x_t=torch.zeros(2, 8, 3, H, W)), r"t=8 frames; expected 1 ≤ t ≤ frames=7"),
        (lambda x: dict(x, x_t=torch.zeros(2, 7, 3, 18, W)), r"18×24; H and W must divide"),
        (lambda x: dict(x, x_t=torch.zeros(2, 7, H, W)), r"x_t must be \(b, t, 3, H, W\); got \(2, 7, 16, 24\)"),
        (lambda x: dict(x, tokens=torch.zeros(2, 7, 6, 4, dtype=torch.long)),
         r"tokens has shape \(2, 7, 6, 4\); expected \(2, 7, 4, 6\)"),
        (lambda x: dict(x, context=torch.zeros(2, 7, 3, H, 2 * W)),
         r"context has shape \(2, 7, 3, 16, 48\); expected \(2, 7, 3, 16, 24\)"),
        (lambda x: dict(x, context_mask=torch.zeros(2, 6, dtype=torch.bool)),
         r"context_mask has shape \(2, 6\); expected \(2, 7\)"),
        (lambda x: dict(x, time=torch.zeros(1, dtype=torch.long)), r"time has shape \(1,\); expected \(2,\)"),
    ],
)
def test_shape_errors_are_named(change, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        tiny()(**change(inputs()))


@torch.no_grad()
def test_rendered_tokens_are_read_only_where_tokens_are_kept() -> None:
    """render_tokens: the rendered pixels of a dropped token's patch change nothing; a kept patch's do."""
    net = scramble(tiny(render_tokens=True)).eval()
    x = inputs()
    x["token_mask"] = torch.ones(2, 7, *GRID, dtype=torch.bool)
    x["token_mask"][:, 3, 1, 2] = False  # the patch rows 4-7, columns 8-11 (D = 4)
    x["rendered"] = torch.rand(2, 7, 3, H, W) * 2 - 1
    y = dict(x, rendered=x["rendered"].clone())
    y["rendered"][:, 3, :, 4:8, 8:12] = float("nan")
    assert torch.equal(net(**x), net(**y))
    y["rendered"][:, 3, :, 4:8, 8:12] = x["rendered"][:, 3, :, 4:8, 8:12]
    y["rendered"][:, 3, :, 0:4, 0:4] += 0.5  # a kept token's patch
    assert not torch.allclose(net(**x)[:, 3], net(**y)[:, 3])


def test_rendered_tokens_are_required_exactly_when_built_for() -> None:
    with pytest.raises(ValueError, match="render_tokens=True, so forward needs `rendered`"):
        tiny(render_tokens=True)(**inputs())
    with pytest.raises(ValueError, match="rendered has shape \\(2, 7, 3, 8, 24\\); expected \\(2, 7, 3, 16, 24\\)"):
        tiny(render_tokens=True)(**inputs(), rendered=torch.zeros(2, 7, 3, 8, W))
    with pytest.raises(ValueError, match="built with render_tokens=False"):
        tiny()(**inputs(), rendered=torch.zeros(2, 7, 3, H, W))


class ZeroResidual(VideoDecoder):
    """Predicts v so that x̂₀ = 0 in whatever space the decoder diffuses: a residual decoder then returns its base."""

    schedule = CosineNoiseSchedule()

    def forward(self, x_t, time, tokens, token_mask, context, context_mask, temporal=True, rendered=None):
        alpha, sigma = self.schedule.alpha_sigma(time)
        return alpha[:, None, None, None, None] * x_t / sigma[:, None, None, None, None]


@pytest.mark.parametrize("residual", [True, False])
def test_residual_decoder_samples_relative_to_the_rendered_tokens(residual: bool) -> None:
    """residual=True: the sampler works on frames − base (base = rendered frames where tokens are given, 0 elsewhere)
    and adds the base back; context frames are copied through unchanged either way."""
    torch.manual_seed(0)
    net = ZeroResidual(vocab_size=VOCAB, token_grid=GRID, image_size=(H, W), frames=7, channels=8, channel_mults=(1, 2),
                       attention_levels=(1,), heads=2, token_dim=8, render_tokens=True, residual=residual)
    x = inputs(b=1)
    x["token_mask"][:, 5:] = False  # the last two frames are interpolated (no tokens)
    x["context_mask"][:, 0] = True
    rendered = torch.rand(1, 7, 3, H, W) * 1.6 - 0.8
    out = sample_window(net, net.schedule, DDIMSampler(net.schedule, steps=5), x["tokens"], x["token_mask"],
                        x["context"], x["context_mask"], rendered=rendered, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(out[:, 0], x["context"][:, 0])
    expected = rendered[:, 1:5] if residual else torch.zeros_like(rendered[:, 1:5])
    torch.testing.assert_close(out[:, 1:5], expected, atol=1e-5, rtol=0)
    torch.testing.assert_close(out[:, 5:], torch.zeros_like(out[:, 5:]), atol=1e-5, rtol=0)  # no tokens: base 0


def test_residual_needs_rendered_tokens() -> None:
    with pytest.raises(ValueError, match="residual=True .* set render_tokens=True"):
        tiny(residual=True)


def test_other_image_sizes_expect_a_scaled_token_grid() -> None:
    net = tiny()
    x = dict(inputs(t=2), x_t=torch.zeros(2, 2, 3, 32, 16), context=torch.zeros(2, 2, 3, 32, 16))
    x["tokens"] = torch.zeros(2, 2, 8, 4, dtype=torch.long)  # D = 4 from image_size / token_grid
    assert net(**x).shape == (2, 2, 3, 32, 16)


def test_tiny_preset_matches_the_tiny_tokenizer() -> None:
    """Tokens from gaia1_tokenizer_tiny fit the tiny decoder: same codebook, grid = image / D."""
    decoder = OmegaConf.load(CONF_DIR / "model" / "net" / "gaia1_video_decoder_tiny.yaml")
    tokenizer = instantiate(OmegaConf.load(CONF_DIR / "model" / "net" / "gaia1_tokenizer_tiny.yaml"))()
    assert decoder.vocab_size == tokenizer.codebook_size
    assert [s // tokenizer.downsampling for s in decoder.image_size] == list(decoder.token_grid)
    with torch.device("meta"):
        net = instantiate(decoder)()
    assert net.frames == 7 and net.downsampling == (tokenizer.downsampling,) * 2


def test_learns_v_regression_on_one_batch() -> None:
    """60 Adam steps on one noised batch (cosine schedule, v target, GAIA-1 §2.4) cut the MSE ≥ 10×."""
    net = tiny(frames=3, channels=16)
    g = torch.Generator().manual_seed(0)
    b, t = 2, 3
    x0 = F.interpolate(torch.rand(b * t, 3, 4, 6, generator=g) * 2 - 1, size=(H, W), mode="bilinear")
    x0, eps = x0.view(b, t, 3, H, W), torch.randn(b, t, 3, H, W, generator=g)
    step = torch.tensor([300, 700])
    angle = (step / 1000 * math.pi / 2)[:, None, None, None, None]
    alpha, sigma = angle.cos(), angle.sin()
    x = dict(inputs(b, t), x_t=alpha * x0 + sigma * eps, time=step, context=x0)
    x["context_mask"][0, 0] = True
    target = alpha * eps - sigma * x0
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        loss = F.mse_loss(net(**x), target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] / 10, f"MSE {losses[0]:.3f} → {losses[-1]:.3f}"
