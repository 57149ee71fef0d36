"""CausalSelfAttention.decode_static (gaia_app/nn/attention.py): one token at a time against a static cache equals the
causal forward over the whole sequence, for grouped-query heads, in float32 and bfloat16 (issue 51's decode step)."""

from __future__ import annotations

import pytest
import torch

from gaia_app.nn.attention import CausalSelfAttention


@pytest.mark.parametrize(("heads", "kv_heads"), [(4, 4), (4, 2), (4, 1)], ids=["mha", "gqa", "mqa"])
@pytest.mark.parametrize(("dtype", "tolerance"), [(torch.float32, 1e-5), (torch.bfloat16, 2e-2)],
                         ids=["float32", "bfloat16"])
def test_static_decoding_token_by_token_equals_the_causal_forward(heads: int, kv_heads: int, dtype: torch.dtype,
                                                                  tolerance: float) -> None:
    torch.manual_seed(0)
    attention = CausalSelfAttention(64, heads, kv_heads).to(dtype).eval()
    x = torch.randn(2, 12, 64, dtype=dtype)
    capacity, head_dim = 16, 64 // heads  # 4 slots never written: masked, not read
    keys = torch.full((2, kv_heads, capacity, head_dim), 7.0, dtype=dtype)  # garbage in the unwritten slots
    values = torch.full_like(keys, -7.0)
    with torch.no_grad():
        whole = attention(x)
        steps = [attention.decode_static(x[:, i:i + 1], keys, values, torch.tensor(i)) for i in range(12)]
    torch.testing.assert_close(torch.cat(steps, dim=1).float(), whole.float(), atol=tolerance, rtol=tolerance)
