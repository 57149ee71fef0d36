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

TINY_NET = ["model.net.channels=8", "model.net.channel_mults=[1,2]", "model.net.attention_levels=[1]",
            "model.net.token_dim=8", "model.net.heads=2", "model.net.vocab_size=512",
            "model.net.token_grid=[16,28]", "model.net.image_size=[64,112]"]


@pytest.fixture(scope="module")
def tokenizer_ckpt(tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("tokenizer")
    train(compose_config("train", ["experiment=gaia1/tokenizer_tiny", "trainer=tiny", "trainer.max_steps=1",
                                   "data=synthetic_frames_tiny", "extras.print_config=false", "logger=none",
                                   "callbacks=model_checkpoint"], run))
    return run / "checkpoints" / "last.ckpt"


@pytest.fixture(scope="module")
def decoder_run(tokenizer_ckpt: Path, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("decoder")
    overrides = ["experiment=gaia1/video_decoder_tiny", "trainer=tiny", "trainer.max_steps=3", "trainer.val_check_interval=3",
                 f"model.tokenizer_ckpt={tokenizer_ckpt}", "data.source.num_clips=4", "data.val_source.num_clips=2",
                 "extras.print_config=false", "logger=none", "callbacks=model_checkpoint", *TINY_NET]
    out = train(compose_config("train", overrides, run))
    assert out["trainer"].global_step == 3
    return run


def test_training_keeps_an_ema_and_checkpoints_reload(decoder_run: Path) -> None:
    module = load_module(decoder_run / "checkpoints" / "last.ckpt")
    state = torch.load(decoder_run / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    assert any(k.startswith("ema.") for k in state) and not any(k.startswith("frozen") for k in state)
    live = dict(module.decoder.named_parameters())
    averaged = dict(module.ema_decoder.named_parameters())
    assert any(not torch.equal(live[k], averaged[k]) for k in live)  # the average lags the trained weights
    assert module.ema.n_averaged.item() == 3


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
    assert seen[:2] == [(1, 7, 2, 4), (1, 4, 2, 4)]  # the backward windows of 9 frames: last 7, then 2 + 2 context
