"""GAIA-1 §5.2 video decoding: window plans, frame counts N → 2N − 1 → 4N − 3, context handling."""

from __future__ import annotations

import pytest
import torch

from gaia_app.pipelines.gaia1_video_decoder import (
    VideoDecodingPipeline,
    backward_windows,
    forward_windows,
    full_length,
    interpolation_windows,
)


@pytest.mark.parametrize("n", [1, 5, 7, 8, 12, 13, 26])
def test_backward_windows_cover_every_frame_with_two_overlapping_context_frames(n: int) -> None:
    windows = backward_windows(n, frames=7, context=2)
    assert windows[0] == (max(0, n - 7), n)  # step 1: the last T' frames
    covered = torch.zeros(n, dtype=torch.bool)
    for i, (start, stop) in enumerate(windows):
        assert 0 <= start < stop <= n and stop - start <= 7
        if i:  # later windows end with exactly the 2 frames decoded just before
            assert (stop - windows[i - 1][0] == 2 and covered[stop - 2 : stop].all()
                    and not covered[start : stop - 2].any())
        covered[start:stop] = True
    assert covered.all()


def test_forward_windows_mirror_backward() -> None:
    assert forward_windows(12, 7, 2) == [(0, 7), (5, 12)]
    assert backward_windows(12, 7, 2) == [(5, 12), (0, 7)]


@pytest.mark.parametrize("order", [backward_windows, forward_windows])
@pytest.mark.parametrize("n", [7, 8, 12, 13, 14, 26])
def test_full_length_windows_hold_t_prime_frames_and_only_widen_over_decoded_ones(order, n: int) -> None:
    windows = full_length(order(n, 7, 2), n, 7)
    covered = torch.zeros(n, dtype=torch.bool)
    for i, (start, stop) in enumerate(windows):
        assert stop - start == 7 and 0 <= start and stop <= n
        if i:  # every frame beyond the window's new ones was decoded before (≥ 2 context frames)
            assert int(covered[start:stop].sum()) >= 2
        covered[start:stop] = True
    assert covered.all()
    assert full_length([(0, 4)], 3, 7) == [(0, 4)]  # too few frames to widen: decode() pads instead


@pytest.mark.parametrize("n", [3, 7, 14])
def test_decode_feeds_every_window_t_prime_frames(n: int) -> None:
    from gaia_app.models.gaia1.video_decoder import VideoDecoder

    net = VideoDecoder(vocab_size=8, token_grid=(2, 2), image_size=(8, 8), frames=7, channels=8, channel_mults=(1,),
                       attention_levels=(), heads=1, token_dim=8)
    pipe = VideoDecodingPipeline(net, schedule=None, sampler=None)
    seen = []

    def window(tokens, token_mask, context, context_mask, generator=None):
        seen.append((tokens.shape[1], int(context_mask[0].sum())))
        return torch.full_like(context, float(len(seen)))

    pipe.window = window
    tokens = torch.arange(n)[None, :, None, None].expand(1, n, 2, 2)
    frames = pipe.decode(tokens)
    assert frames.shape == (1, n, 3, 8, 8) and all(length == 7 for length, _ in seen)
    assert seen[0][1] == 0 and all(context >= 2 for _, context in seen[1:])


@pytest.mark.parametrize("n", [2, 4, 7, 13])
def test_interpolation_windows_start_and_end_on_known_frames(n: int) -> None:
    out = 2 * n - 1
    windows = interpolation_windows(out, frames=7)
    assert windows[0][0] == 0 and windows[-1][1] == out
    for (start, stop), nxt in zip(windows, windows[1:] + [None]):
        assert start % 2 == 0 and (stop - 1) % 2 == 0 and stop - start <= 7
        if nxt is not None:
            assert nxt[0] == stop - 1  # consecutive windows share one known frame


def test_temporal_flicker_sees_jitter_not_constant_error() -> None:
    from gaia_app.eval.metrics import temporal_flicker

    truth = torch.linspace(-1, 1, 5)[None, :, None, None, None].expand(2, 5, 3, 4, 4)
    offset = truth + 0.3  # wrong everywhere, but changes exactly like the truth
    jitter = truth + 0.1 * torch.tensor([1, -1, 1, -1, 1.0])[None, :, None, None, None]
    assert torch.allclose(temporal_flicker(offset, truth), torch.zeros(2), atol=1e-6)
    assert torch.allclose(temporal_flicker(jitter, truth), torch.full((2,), 0.2))
    with pytest.raises(ValueError, match="t ≥ 2"):
        temporal_flicker(truth[:, :1], truth[:, :1])
