"""Frozen pretrained networks behind one interface, loaded from local files only (DESIGN.md §6).

- `load_vision_teacher(kind="dino_vits16", checkpoint=...)` → VisionTeacher (DINO patch features;
  kinds in `DINO_ARCHS`: dino_vits16, dino_vitb16, dinov2_vits14, dinov2_vitb14)
- `load_perceptual(kind="vgg16", checkpoint=...)` → PerceptualDistance (LPIPS-style VGG distance)

Both return networks with frozen weights in eval mode. A missing file raises FileNotFoundError
naming the config key, the path and the `<key>=none` switch; a state dict that does not fit
raises StateDictMismatchError listing the missing and unexpected keys.
"""

from gaia_app.encoders.checkpoints import StateDictMismatchError
from gaia_app.encoders.perceptual import PerceptualDistance, load_perceptual
from gaia_app.encoders.vision import DINO_ARCHS, VisionTeacher, distillation_loss, load_vision_teacher

__all__ = [
    "DINO_ARCHS",
    "PerceptualDistance",
    "StateDictMismatchError",
    "VisionTeacher",
    "distillation_loss",
    "load_perceptual",
    "load_vision_teacher",
]
