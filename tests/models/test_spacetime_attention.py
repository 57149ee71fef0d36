"""`gaia_app.nn.spacetime.attention`: under CPU bfloat16 autocast SDPA runs in float32 and hands back bfloat16, so the
GAIA-2 nets keep the linear layers' bfloat16 speed without SDPA's slower bfloat16 CPU kernel."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from gaia_app.nn.spacetime import CrossAttention, SelfAttention, attention


def heads(seed: int, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return tuple(torch.randn(2, 3, 17, 8, generator=g).to(dtype) for _ in range(3))


def test_float32_inputs_are_plain_sdpa() -> None:
    q, k, v = heads(0)
    torch.testing.assert_close(attention(q, k, v), F.scaled_dot_product_attention(q, k, v), rtol=0, atol=0)


def test_bfloat16_inputs_are_computed_in_float32_and_returned_in_bfloat16() -> None:
    q, k, v = heads(1, torch.bfloat16)
    out = attention(q, k, v)
    assert out.dtype == torch.bfloat16
    exact = F.scaled_dot_product_attention(q.float(), k.float(), v.float())
    # float32 arithmetic, one rounding at the end: within half a bfloat16 step of the float32 result
    torch.testing.assert_close(out.float(), exact.to(torch.bfloat16).float(), rtol=0, atol=0)


def test_masks_pass_through() -> None:
    q, k, v = heads(2, torch.bfloat16)
    mask = torch.zeros(2, 1, 1, 17, dtype=torch.bool)
    mask[..., :5] = True
    out = attention(q, k, v, attn_mask=mask)
    exact = F.scaled_dot_product_attention(q.float(), k.float(), v.float(), attn_mask=mask)
    torch.testing.assert_close(out.float(), exact.to(torch.bfloat16).float(), rtol=0, atol=0)


def test_modules_under_cpu_autocast_keep_bfloat16_activations_and_float32_agreement() -> None:
    torch.manual_seed(0)
    self_attn, cross = SelfAttention(32, 4), CrossAttention(32, 16, 4)
    x, context = torch.randn(2, 9, 32), torch.randn(2, 5, 16)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y, z = self_attn(x), cross(x, context)
    assert y.dtype == z.dtype == torch.bfloat16
    torch.testing.assert_close(y.float(), self_attn(x), rtol=0.05, atol=0.05)
    torch.testing.assert_close(z.float(), cross(x, context), rtol=0.05, atol=0.05)
