"""Frozen DINO / DINOv2 teacher for the tokenizer's inductive-bias loss (GAIA-1 §2.2, ref. [30]), local weights only.

Legend: b batch, d teacher feature dim, H W image size, gh gw teacher patch grid, h w token grid.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import torch
import torch.nn.functional as F

from gaia_app.encoders.checkpoints import StateDict, freeze, load_exact, read_state_dict
from gaia_app.encoders.images import FrozenImageNetwork
from gaia_app.nn.vit import VisionTransformer


@dataclass(frozen=True)
class ViTArch:
    """Architecture of a DINO backbone (facebookresearch/dino or /dinov2 `vit_small` / `vit_base`).

    image_size is the training resolution (the positional grid a checkpoint without `pos_embed` would
    have); layer_scale and mask_token select the DINOv2 layout (see gaia_app.nn.vit).
    """

    embed_dim: int
    depth: int
    num_heads: int
    patch_size: int = 16
    image_size: int = 224
    layer_scale: bool = False
    mask_token: bool = False


_DINOV2 = dict(patch_size=14, image_size=518, layer_scale=True, mask_token=True)

DINO_ARCHS = {
    "dino_vits16": ViTArch(embed_dim=384, depth=12, num_heads=6),
    "dino_vitb16": ViTArch(embed_dim=768, depth=12, num_heads=12),
    "dinov2_vits14": ViTArch(embed_dim=384, depth=12, num_heads=6, **_DINOV2),
    "dinov2_vitb14": ViTArch(embed_dim=768, depth=12, num_heads=12, **_DINOV2),
}


class VisionTeacher(FrozenImageNetwork):
    """Frozen ViT giving the patch-feature map that the tokenizer's quantised features are distilled to.

    Images are resized (bilinear) to the nearest multiple of the patch size, so 288×512 with p = 16
    gives the 18×32 token grid of GAIA-1 §4.1 directly; DINOv2 (p = 14) sees 294×518 → 21×37, which
    `distillation_loss` resizes to the token grid.
    """

    def __init__(self, vit: VisionTransformer):
        super().__init__()
        self.vit = vit
        self.feature_dim = vit.embed_dim

    @torch.no_grad()
    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """image: (b, 3, H, W) in [-1, 1] → patch features (b, d, gh, gw)."""
        return self.vit.patch_features(self._prepare(image))

    @torch.no_grad()
    def embed(self, image: torch.Tensor) -> torch.Tensor:
        """image: (b, 3, H, W) in [-1, 1] → the class-token embedding (b, d), DINO's whole-image feature
        (the one Fréchet DINO Distance compares, GAIA-2 §6)."""
        return self.vit(self._prepare(image))[:, 0]

    def _prepare(self, image: torch.Tensor) -> torch.Tensor:
        """ImageNet-normalised and resized (bilinear) to the nearest multiple of the patch size."""
        p = self.vit.patch_size
        x = self.normalize(image)
        size = (max(p, round(x.shape[-2] / p) * p), max(p, round(x.shape[-1] / p) * p))
        if size != tuple(x.shape[-2:]):
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
        return x


def distillation_loss(student: torch.Tensor, teacher: torch.Tensor) -> torch.Tensor:
    """Scalar mean (1 − cos) between student (b, d, h, w) and teacher (b, d, gh, gw) feature vectors.

    The teacher map is resized (bilinear) to the student's token grid first (GAIA-1 §2.2: the
    quantised features "are encouraged to match the image features of a pre-trained DINO model
    with a cosine similarity loss").
    """
    if student.shape[1] != teacher.shape[1]:
        raise ValueError(f"distillation_loss: student has {student.shape[1]} channels, teacher {teacher.shape[1]}")
    if teacher.shape[-2:] != student.shape[-2:]:
        teacher = F.interpolate(teacher, size=student.shape[-2:], mode="bilinear", align_corners=False)
    return (1.0 - F.cosine_similarity(student, teacher.to(student.dtype), dim=1)).mean()


def dino_backbone_state_dict(state: StateDict) -> StateDict:
    """Official hub checkpoints are the bare backbone. Weights exported from a DINO training run carry
    `module.` / `backbone.` prefixes and the DINO projection head: strip the prefixes, drop the head."""
    out = {}
    for key, value in state.items():
        for prefix in ("module.", "backbone."):
            key = key.removeprefix(prefix)
        if not key.startswith("head."):
            out[key] = value
    return out


def dino_arch(kind: str, config_key: str, **overrides: int | None) -> ViTArch:
    """The preset for `kind`, with any non-None overrides (small test networks of the same layout)."""
    if kind not in DINO_ARCHS:
        raise ValueError(f"{config_key}.kind={kind!r}: known teachers are {sorted(DINO_ARCHS)}; "
                         f"{config_key}=none switches the loss off")
    return replace(DINO_ARCHS[kind], **{k: v for k, v in overrides.items() if v is not None})


def load_vision_teacher(
    kind: str = "dino_vits16",
    checkpoint: str | Path = "",
    config_key: str = "model.dino",
    embed_dim: int | None = None,
    depth: int | None = None,
    num_heads: int | None = None,
) -> VisionTeacher:
    """Build the teacher `kind` and load its weights from the local `checkpoint`; frozen, eval mode.

    kind: dino_vits16 / dino_vitb16 (DINO v1) or dinov2_vits14 / dinov2_vitb14 (DINOv2, no registers).
    The positional grid is read from the checkpoint's `pos_embed` (224-pixel training → 14×14 at
    p = 16; DINOv2's 518 pixels → 37×37 at p = 14). embed_dim / depth / num_heads override the preset,
    for small networks of the same layout.
    Raises FileNotFoundError (missing file) or StateDictMismatchError (wrong keys or shapes).
    """
    arch = dino_arch(kind, config_key, embed_dim=embed_dim, depth=depth, num_heads=num_heads)
    state = dino_backbone_state_dict(read_state_dict(checkpoint, config_key))
    vit = VisionTransformer(
        image_size=stored_grid(state, arch.image_size // arch.patch_size) * arch.patch_size,
        patch_size=arch.patch_size, embed_dim=arch.embed_dim, depth=arch.depth, num_heads=arch.num_heads,
        layer_scale=arch.layer_scale, mask_token=arch.mask_token,
    )
    load_exact(vit, state, f"{config_key}.checkpoint '{checkpoint}' (kind {kind})")
    return freeze(VisionTeacher(vit).float())


def stored_grid(state: StateDict, default: int = 14) -> int:
    """Side of the square positional grid stored in `pos_embed` (1, 1 + g², d); `default` if absent."""
    pos = state.get("pos_embed")
    if pos is None or pos.ndim != 3:
        return default
    return max(1, round((pos.shape[1] - 1) ** 0.5))

