"""Vision Transformer with the parameter names of the official DINO and DINOv2 `vision_transformer.py`.

Legend: b batch, n = gh·gw patches, d embed dim, gh gw patch grid, p patch size.

Names match facebookresearch/dino, so an official `dino_vits16` / `dino_vitb16` backbone state dict
loads strictly: `cls_token`, `pos_embed`, `patch_embed.proj.{weight,bias}`,
`blocks.N.{norm1,attn.qkv,attn.proj,norm2,mlp.fc1,mlp.fc2}.{weight,bias}`, `norm.{weight,bias}`.
With `layer_scale=True, mask_token=True` the layout is facebookresearch/dinov2's (`dinov2_vits14`,
`dinov2_vitb14`: hub models built with `block_chunks=0`, `init_values=1.0`): the same keys plus
`mask_token` (1, d) and `blocks.N.ls1.gamma`, `blocks.N.ls2.gamma` (d,).
Used as the frozen DINO teacher of GAIA-1 §2.2 (ref. [30]); no timm, no torchvision.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn


class PatchEmbed(nn.Module):
    """Non-overlapping p×p patches → tokens: (b, 3, H, W) → (b, n, d)."""

    def __init__(self, patch_size: int, embed_dim: int, in_channels: int = 3):
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(in_channels, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return rearrange(self.proj(x), "b d gh gw -> b (gh gw) d")


class Attention(nn.Module):
    """Multi-head self-attention with a fused qkv projection: (b, n, d) → (b, n, d)."""

    def __init__(self, dim: int, num_heads: int, qkv_bias: bool = True):
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, 3 * dim, bias=qkv_bias)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        q, k, v = rearrange(self.qkv(x), "b n (three h e) -> three b h n e", three=3, h=self.num_heads)
        y = F.scaled_dot_product_attention(q, k, v)  # scale 1/sqrt(e), as DINO
        return self.proj(rearrange(y, "b h n e -> b n (h e)"))


class Mlp(nn.Module):
    """Two-layer GELU MLP: (b, n, d) → (b, n, d)."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class LayerScale(nn.Module):
    """Learned per-channel scale of a residual branch (CaiT; DINOv2's `ls1` / `ls2`): (..., d) → (..., d)."""

    def __init__(self, dim: int, init_value: float = 1.0):
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), init_value))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Block(nn.Module):
    """Pre-norm transformer block: (b, n, d) → (b, n, d).

    x + ls1(attn(norm1(x))), then + ls2(mlp(norm2(x))); without layer scale (DINO v1) ls1 and ls2 are
    parameter-free identities, so the state dict has no `ls*` keys.
    """

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, qkv_bias: bool, norm_eps: float,
                 layer_scale: bool = False):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=norm_eps)
        self.attn = Attention(dim, num_heads, qkv_bias)
        self.ls1 = LayerScale(dim) if layer_scale else nn.Identity()
        self.norm2 = nn.LayerNorm(dim, eps=norm_eps)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))
        self.ls2 = LayerScale(dim) if layer_scale else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class VisionTransformer(nn.Module):
    """ViT backbone with a cls token (DINO's layout; ViT-S/16: d=384, depth 12, 6 heads; ViT-B/16: 768, 12, 12).

    Args:
        image_size: training resolution, fixes the stored positional grid (224 → 14×14 at p=16;
            DINOv2: 518 → 37×37 at p=14); other resolutions interpolate it (bicubic), as DINO does.
        patch_size, embed_dim, depth, num_heads, mlp_ratio, qkv_bias: architecture.
        norm_eps: LayerNorm epsilon (1e-6 in DINO and DINOv2).
        layer_scale: LayerScale `ls1` / `ls2` on every residual branch (DINOv2; gammas start at 1).
        mask_token: hold DINOv2's `mask_token` (1, d). It replaces masked patches in DINOv2 training
            only; the forward pass here never uses it, it exists so official checkpoints load exactly.
    """

    def __init__(
        self,
        image_size: int = 224,
        patch_size: int = 16,
        embed_dim: int = 384,
        depth: int = 12,
        num_heads: int = 6,
        mlp_ratio: float = 4.0,
        qkv_bias: bool = True,
        norm_eps: float = 1e-6,
        layer_scale: bool = False,
        mask_token: bool = False,
    ):
        super().__init__()
        self.patch_size = patch_size
        self.embed_dim = embed_dim
        self.base_grid = image_size // patch_size
        self.patch_embed = PatchEmbed(patch_size, embed_dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + self.base_grid**2, embed_dim))
        self.mask_token = nn.Parameter(torch.zeros(1, embed_dim)) if mask_token else None
        self.blocks = nn.ModuleList(
            Block(embed_dim, num_heads, mlp_ratio, qkv_bias, norm_eps, layer_scale) for _ in range(depth)
        )
        self.norm = nn.LayerNorm(embed_dim, eps=norm_eps)
        self.initialize_weights()

    def initialize_weights(self) -> None:
        """Truncated-normal(0.02) embeddings and linear weights, zero biases (DINO/timm init)."""
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.trunc_normal_(self.cls_token, std=0.02)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                nn.init.zeros_(m.bias)

    def positional_embedding(self, grid_h: int, grid_w: int) -> torch.Tensor:
        """(1, 1 + grid_h·grid_w, d): the stored grid, bicubically resized when the patch grid differs."""
        if (grid_h, grid_w) == (self.base_grid, self.base_grid):
            return self.pos_embed
        cls_pos, patch_pos = self.pos_embed[:, :1], self.pos_embed[:, 1:]
        grid = rearrange(patch_pos, "1 (gh gw) d -> 1 d gh gw", gh=self.base_grid)
        grid = F.interpolate(grid, size=(grid_h, grid_w), mode="bicubic", align_corners=False)
        return torch.cat([cls_pos, rearrange(grid, "1 d gh gw -> 1 (gh gw) d")], dim=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (b, 3, H, W), H and W multiples of p → normalised tokens (b, 1 + n, d), cls first."""
        grid_h, grid_w = x.shape[-2] // self.patch_size, x.shape[-1] // self.patch_size
        tokens = self.patch_embed(x)
        tokens = torch.cat([self.cls_token.expand(len(x), -1, -1), tokens], dim=1)
        tokens = tokens + self.positional_embedding(grid_h, grid_w)
        for block in self.blocks:
            tokens = block(tokens)
        return self.norm(tokens)

    def patch_features(self, x: torch.Tensor) -> torch.Tensor:
        """x: (b, 3, H, W) → last-layer patch features as a map (b, d, H/p, W/p), cls dropped."""
        grid_h = x.shape[-2] // self.patch_size
        return rearrange(self.forward(x)[:, 1:], "b (gh gw) d -> b d gh gw", gh=grid_h)
