"""benchmarks/bench_cpu_bf16_video_tokenizer.py: each arm runs the precision it names, and the project's attention is
back in place after the arm that swaps it."""

from __future__ import annotations

from unittest import mock

import torch

import gaia_app.nn.spacetime as spacetime
from gaia_app.models.gaia2.video_tokenizer import VideoTokenizer
from tests.conftest import load_benchmark

SMALL = dict(spatial_downsampling=8, temporal_downsampling=4, latent_channels=4, chunk_latents=2, conv_channels=8,
             conv_mults=(), encoder_dim=32, encoder_depth=1, encoder_heads=2, decoder_dim=32, decoder_depth=1,
             decoder_heads=2)


def test_arms_attend_in_the_dtype_they_name_and_restore_the_project_attention() -> None:
    bench = load_benchmark("bench_cpu_bf16_video_tokenizer")
    video = torch.rand(1, 1, 4, 3, 16, 16) * 2 - 1
    project = spacetime.attention
    for arm, dtype in (("float32", torch.float32), ("bfloat16", torch.float32), ("bfloat16_sdpa", torch.bfloat16)):
        torch.manual_seed(0)
        seen: list[torch.dtype] = []
        real_sdpa = torch.nn.functional.scaled_dot_product_attention

        def spy(q, k, v, **kwargs):
            seen.append(q.dtype)
            return real_sdpa(q, k, v, **kwargs)

        with mock.patch.object(torch.nn.functional, "scaled_dot_product_attention", spy):
            seconds, loss = bench.make_step(VideoTokenizer(**SMALL), arm, video)()
        assert seconds > 0 and torch.isfinite(torch.tensor(loss))
        assert seen and set(seen) == {dtype}, arm
        assert spacetime.attention is project
