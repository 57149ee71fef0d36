"""GAIA-1 video decoder end to end on tiny settings: multi-task training with EMA, checkpoint, §5.2 decoding."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from gaia_app.diffusion.noise_schedule import CosineNoiseSchedule
from gaia_app.diffusion.samplers import DDIMSampler, ImageVideoBlend
from gaia_app.lit.checkpoint import load_module
from gaia_app.models.gaia1.video_decoder import VideoDecoder
from gaia_app.pipelines.gaia1_video_decoder import VideoDecodingPipeline
from gaia_app.tasks.train import train
from tests.conftest import compose_config

pytestmark = pytest.mark.usefixtures("one_thread")

TINY_NET = ["model.net.channels=8", "model.net.channel_mults=[1,2,2]", "model.net.attention_levels=[2]",
            "model.net.token_dim=8", "model.net.heads=2", "model.net.vocab_size=512",
            "model.net.token_grid=[16,28]", "model.net.image_size=[64,112]"]


@pytest.fixture(scope="module")
def tokenizer_ckpt(tiny_tokenizer_ckpt: Path) -> Path:
    return tiny_tokenizer_ckpt


@pytest.fixture(scope="module")
def decoder_run(tokenizer_ckpt: Path, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("decoder")
    overrides = ["experiment=gaia1/video_decoder_tiny", "trainer=tiny", "trainer.max_steps=2",
                 "trainer.val_check_interval=2", "trainer.limit_val_batches=1",
                 f"model.tokenizer_ckpt={tokenizer_ckpt}", "data.source.num_clips=4", "data.val_source.num_clips=2",
                 "extras.print_config=false", "logger=none", "callbacks=model_checkpoint", *TINY_NET]
    out = train(compose_config("train", overrides, run))
    assert out["trainer"].global_step == 2
    return run


def test_training_keeps_an_ema_and_checkpoints_reload(decoder_run: Path) -> None:
    module = load_module(decoder_run / "checkpoints" / "last.ckpt")
    state = torch.load(decoder_run / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    assert any(k.startswith("ema.") for k in state) and not any(k.startswith("frozen") for k in state)
    live = dict(module.decoder.named_parameters())
    averaged = dict(module.ema_decoder.named_parameters())
    assert any(not torch.equal(live[k], averaged[k]) for k in live)  # the average lags the trained weights
    assert module.ema.n_averaged.item() == 2


def test_validation_logs_every_task(decoder_run: Path) -> None:
    module = load_module(decoder_run / "checkpoints" / "last.ckpt")
    batch = {"video": torch.rand(1, 1, 25, 3, 64, 112) * 2 - 1}
    logged = {}
    module.log = lambda name, value, **kw: logged.__setitem__(name, float(value))
    module.validation_step(batch, 0)
    assert {f"val/loss_{t}" for t in ("image", "video", "forward", "backward", "interpolation")} < logged.keys()
    media = module.media(batch)
    assert media["val/decoder/decoded"].shape == (1, 7, 3, 64, 112)
    assert media["val/decoder/denoising_steps"].shape == (1, module.media_steps, 3, 64, 112)
    real, generated = module.evaluation_pair(batch)  # what callbacks=[...,evaluation] scores
    assert real.shape == generated.shape == (1, 7, 3, 64, 112)
    torch.testing.assert_close(generated[:1], media["val/decoder/decoded"][:1])  # same seed, same decoding


def tiny_pipeline(rendering: bool = False, **kw) -> VideoDecodingPipeline:
    torch.manual_seed(0)
    net = VideoDecoder(vocab_size=16, token_grid=(2, 4), image_size=(8, 16), frames=7, channels=8, channel_mults=(1, 2),
                       attention_levels=(1,), heads=2, token_dim=8, render_tokens=rendering).eval()
    schedule = CosineNoiseSchedule()
    return VideoDecodingPipeline(net, schedule, DDIMSampler(schedule, steps=3), frames=7, context=2, **kw)


@pytest.mark.parametrize("n", [5, 9])
def test_full_decode_gives_n_then_2n_minus_1_then_4n_minus_3_frames(n: int) -> None:
    pipe = tiny_pipeline(blend=ImageVideoBlend())
    tokens = torch.randint(0, 16, (2, n, 2, 4))
    video = pipe(tokens, upsample=2, generator=torch.Generator().manual_seed(0))
    assert video.base.shape == (2, n, 3, 8, 16)
    assert video.double.shape[1] == 2 * n - 1 and video.quadruple.shape[1] == 4 * n - 3
    # upsampling keeps the frames it starts from
    assert torch.equal(video.double[:, ::2], video.base) and torch.equal(video.quadruple[:, ::2], video.double)
    assert video.quadruple.abs().max() <= 1


def test_decoding_is_deterministic_with_a_seed_and_backward_differs_from_forward() -> None:
    tokens = torch.randint(0, 16, (1, 9, 2, 4))
    backward = tiny_pipeline()
    a = backward.decode(tokens, torch.Generator().manual_seed(1))
    b = backward.decode(tokens, torch.Generator().manual_seed(1))
    assert torch.equal(a, b)
    forward = tiny_pipeline(backward=False).decode(tokens, torch.Generator().manual_seed(1))
    assert not torch.equal(a, forward)


def test_window_copies_context_frames_through() -> None:
    pipe = tiny_pipeline()
    context = torch.rand(1, 7, 3, 8, 16) * 2 - 1
    mask = torch.tensor([[True, True, False, False, False, False, False]])
    out = pipe.window(torch.randint(0, 16, (1, 7, 2, 4)), ~mask, context, mask, torch.Generator().manual_seed(0))
    assert torch.equal(out[:, :2], context[:, :2]) and not torch.equal(out[:, 2:], context[:, 2:])



def test_decoder_with_rendered_tokens_needs_and_uses_a_renderer() -> None:
    """A decoder built with render_tokens gets each window's tokens rendered by the given function."""
    with pytest.raises(ValueError, match="render_tokens=True: pass render_tokens="):
        tiny_pipeline(rendering=True)
    seen = []

    def render(tokens: torch.Tensor) -> torch.Tensor:  # (b, t, 2, 4) → (b, t, 3, 8, 16): one grey level per token
        seen.append(tuple(tokens.shape))
        grey = tokens.float()[:, :, None] / 8 - 1
        return grey.repeat_interleave(4, -1).repeat_interleave(4, -2).expand(-1, -1, 3, -1, -1)

    tokens = torch.randint(0, 16, (1, 9, 2, 4))
    video = tiny_pipeline(rendering=True, render_tokens=render)(tokens, upsample=1)
    assert video.base.shape == (1, 9, 3, 8, 16) and video.double.shape == (1, 17, 3, 8, 16)
    # the backward windows of 9 frames: the last 7, then the first 7 (2 new frames, 5 decoded before as context)
    assert seen[:2] == [(1, 7, 2, 4), (1, 7, 2, 4)]


def grey_render(tokens: torch.Tensor) -> torch.Tensor:
    """(b, t, 2, 4) tokens → (b, t, 3, 8, 16): one grey level per token, a stand-in for the tokenizer's decoder."""
    grey = tokens.float()[:, :, None] / 8 - 1
    return grey.repeat_interleave(4, -1).repeat_interleave(4, -2).expand(-1, -1, 3, -1, -1)


def residual_net(scale: float) -> VideoDecoder:
    return VideoDecoder(vocab_size=16, token_grid=(2, 4), image_size=(8, 16), frames=7, channels=8,
                        channel_mults=(1, 2),
                        attention_levels=(1,), heads=2, token_dim=8, render_tokens=True, residual=True,
                        residual_scale=scale).eval()


def test_residual_frame_scales_only_where_tokens_are_given_and_round_trips() -> None:
    net = residual_net(0.25)
    frames = torch.rand(2, 7, 3, 8, 16) * 2 - 1
    rendered = grey_render(torch.randint(0, 16, (2, 7, 2, 4)))
    token_mask = torch.ones(2, 7, 2, 4, dtype=torch.bool)
    token_mask[:, 3, 0, 0] = False  # one dropped token: its 4×4 patch is diffused as pixels
    frame = net.residual_frame(rendered, token_mask, frames)
    x = frame.encode(frames)
    assert torch.allclose(frame.decode(x), frames, atol=1e-6)
    assert torch.allclose(x[:, 3, :, :4, :4], frames[:, 3, :, :4, :4])
    assert torch.allclose(x[:, 0], (frames[:, 0] - rendered[:, 0]) / 0.25, atol=1e-5)
    too_far = frame.decode(frame.clip(x + 10.0))  # clipping bounds the frames, not the diffused variable
    assert too_far.max() <= 1 + 1e-5 and too_far.min() >= -1 - 1e-5
    with pytest.raises(ValueError, match="residual_scale must be > 0"):
        residual_net(0.0)


@pytest.mark.parametrize("scale", [1.0, 0.25])
@pytest.mark.parametrize("steps", [1, 5])
def test_a_decoder_predicting_a_zero_residual_returns_its_rendered_input(scale: float, steps: int) -> None:
    """The sampler ends at the clean sample and the residual maps back exactly: a residual decoder whose x̂₀ is
    0 at every step decodes to the rendered tokens, whatever the scale and the number of steps."""
    net = residual_net(scale)
    schedule = CosineNoiseSchedule()

    def zero_residual(x_t, time, *args, **kwargs):  # v such that x̂₀ = α x_t − σ v = 0
        alpha, sigma = schedule.alpha_sigma(time)
        return alpha[:, None, None, None, None] * x_t / sigma[:, None, None, None, None]

    net.forward = zero_residual
    tokens = torch.randint(0, 16, (1, 9, 2, 4))
    pipe = VideoDecodingPipeline(net, schedule, DDIMSampler(schedule, steps=steps), render_tokens=grey_render)
    decoded = pipe.decode(tokens, torch.Generator().manual_seed(0))
    assert torch.allclose(decoded, grey_render(tokens), atol=1e-4)


class GreyTokenizer:
    """Stand-in for the frozen tokenizer: decodes each token to a flat grey patch (render = grey_render)."""

    def decode(self, tokens: torch.Tensor) -> torch.Tensor:  # (n, 2, 4) → (n, 3, 8, 16)
        return grey_render(tokens[:, None])[:, 0]

    def to(self, device) -> GreyTokenizer:
        return self


def train_on_fixed_batch(scale: float, iterations: int = 160):
    """A residual decoder trained with its own objective (video task) on one seeded batch whose true frames are the
    rendered tokens plus a smooth correction the tokens do not carry. → (net, module, tokens, rendered, truth)."""
    from functools import partial

    from gaia_app.lit.gaia1_video_decoder import VideoDecoderModule
    from gaia_app.models.gaia1.decoder_tasks import make_task

    torch.manual_seed(0)
    module = VideoDecoderModule(net=partial(residual_net, scale), optim=None)
    module.frozen["tokenizer"] = GreyTokenizer()
    net = module.decoder.train()
    tokens = torch.randint(0, 16, (2, 7, 2, 4))
    rendered = grey_render(tokens)
    y, x = torch.meshgrid(torch.linspace(0, 3.1, 8), torch.linspace(0, 6.2, 16), indexing="ij")
    truth = (rendered + 0.3 * torch.sin(x + y)).clamp(-1, 1)
    optimizer = torch.optim.AdamW(net.parameters(), lr=3e-3)
    for _ in range(iterations):
        loss = module.loss(net, truth, tokens, make_task("video", 7, 2), dropout=False)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return net.eval(), module, tokens, rendered, truth


def decoded_psnr(net, module, tokens, truth, steps: int) -> float:
    from gaia_app.eval.metrics import psnr

    pipe = VideoDecodingPipeline(net, module.schedule, DDIMSampler(module.schedule, steps=steps),
                                 render_tokens=module.render_tokens)
    return float(psnr(pipe.decode(tokens, torch.Generator().manual_seed(0)).flatten(0, 1), truth.flatten(0, 1)).mean())


@pytest.mark.slow  # a 160-step training run (issue 21); tests/models/test_video_decoder.py overfits in make test
def test_a_short_training_lifts_the_decoder_above_its_rendered_input() -> None:
    """"Learns" test (issue 21): 160 steps on a fixed batch, then decoding with DDIM 1, 5 and 20 steps lands at
    least 3 dB above the rendered tokens alone (measured: +4.5, +4.9, +3.9 dB). A decoder that regressed below its
    own input fails."""
    from gaia_app.eval.metrics import psnr

    net, module, tokens, rendered, truth = train_on_fixed_batch(scale=0.25)
    floor = float(psnr(rendered.flatten(0, 1), truth.flatten(0, 1)).mean())
    for steps in (1, 5, 20):
        assert decoded_psnr(net, module, tokens, truth, steps) >= floor + 3.0, steps


@pytest.mark.slow  # a diagnosis experiment (issue 21); the learns test above reaches every line it reaches
def test_an_unscaled_residual_falls_below_its_input_after_the_same_training() -> None:
    """The cause pinned (docs/video_decoder.md): diffused unscaled, the residual (4× smaller than the frames) drowns
    in the unit noise, and the same training decodes below the rendered tokens (measured: 13.8 dB at 1 step, 19.8 at
    20, against 20.1), where residual_scale = 0.25 decodes above them."""
    from gaia_app.eval.metrics import psnr

    net, module, tokens, rendered, truth = train_on_fixed_batch(scale=1.0)
    floor = float(psnr(rendered.flatten(0, 1), truth.flatten(0, 1)).mean())
    assert decoded_psnr(net, module, tokens, truth, 1) < floor - 3.0


def test_decoder_training_reads_the_tokenizer_of_shipped_weights() -> None:
    """model.tokenizer_ckpt=gaia1 (experiment=gaia1/reference/video_decoder): the shipped tokenizer, weights-only."""
    from gaia_app.lit.gaia1_video_decoder import load_tokenizer
    from gaia_app.models.gaia1.tokenizer import ImageTokenizer

    tokenizer = load_tokenizer("gaia1")
    assert isinstance(tokenizer, ImageTokenizer) and tokenizer.codebook_size == 1024
    with torch.no_grad():
        tokens = tokenizer.encode(torch.zeros(1, 3, 64, 112))
    assert tokens.shape == (1, 8, 14)
    with pytest.raises(FileNotFoundError, match="no_such_weights"):
        load_tokenizer("no_such_weights")
