"""PatchGAN discriminator and the GAN terms of the tokenizer's reconstruction loss (GAIA-1 §2.2, ref. [33]).

Legend: b batch, c channels, H W image size, h w logit grid.

The discriminator scores overlapping patches (pix2pix's PatchGAN, as in VQGAN); the losses are
VQGAN's hinge losses, and `adaptive_gan_weight` is VQGAN's balance of the GAN gradient against the
reconstruction gradient at the decoder's last layer.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from gaia_app.nn.conv import group_norm


def dcgan_init(module: nn.Module) -> None:
    """N(0, 0.02) convolutions and N(1, 0.02) norm scales (DCGAN/pix2pix init)."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.Conv3d)):
            nn.init.normal_(m.weight, 0.0, 0.02)
        elif isinstance(m, nn.GroupNorm):
            nn.init.normal_(m.weight, 1.0, 0.02)
            nn.init.zeros_(m.bias)


class PatchDiscriminator(nn.Module):
    """Fully convolutional real/fake classifier: (b, 3, H, W) → logits (b, 1, h, w), one per patch.

    Each of `num_layers` stride-2 4×4 convolutions halves the resolution and doubles the width (capped
    at 8× `channels`); a stride-1 conv and a 1-channel head follow. 3 layers see 70×70 patches.
    GroupNorm instead of pix2pix's BatchNorm: no running statistics, independent of the per-device
    batch (GAIA-1 trains with 5 images per GPU), nothing to synchronise under DDP.

    Args:
        channels: width of the first layer (64 in pix2pix/VQGAN).
        num_layers: stride-2 layers.
        in_channels: image channels.
    """

    def __init__(self, channels: int = 64, num_layers: int = 3, in_channels: int = 3):
        super().__init__()
        widths = [channels * min(2**i, 8) for i in range(num_layers + 1)]
        layers: list[nn.Module] = [nn.Conv2d(in_channels, widths[0], 4, stride=2, padding=1), nn.LeakyReLU(0.2)]
        for i in range(1, num_layers + 1):
            stride = 2 if i < num_layers else 1
            layers += [nn.Conv2d(widths[i - 1], widths[i], 4, stride=stride, padding=1, bias=False),
                       group_norm(widths[i]), nn.LeakyReLU(0.2)]
        layers.append(nn.Conv2d(widths[-1], 1, 4, stride=1, padding=1))
        self.layers = nn.Sequential(*layers)
        self.initialize_weights()

    def initialize_weights(self) -> None:
        dcgan_init(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (b, 3, H, W) in [-1, 1] → (b, 1, h, w) logits."""
        return self.layers(x)


def hinge_discriminator_loss(real_logits: torch.Tensor, fake_logits: torch.Tensor) -> torch.Tensor:
    """Scalar ½·(mean relu(1 − D(x)) + mean relu(1 + D(x̂))): zero once real > 1 and fake < −1."""
    return 0.5 * (F.relu(1.0 - real_logits).mean() + F.relu(1.0 + fake_logits).mean())


def hinge_generator_loss(fake_logits: torch.Tensor) -> torch.Tensor:
    """Scalar −mean D(x̂): the generator raises the discriminator's score of its reconstructions."""
    return -fake_logits.mean()


def adaptive_gan_weight(
    reconstruction_loss: torch.Tensor,
    gan_loss: torch.Tensor,
    last_layer: torch.Tensor,
    max_weight: float = 1e4,
    eps: float = 1e-4,
) -> torch.Tensor:
    """VQGAN's ‖∇_L rec‖ / (‖∇_L gan‖ + eps), clamped to [0, max_weight], detached (a weight, not a loss).

    L is the decoder's last layer, so the GAN gradient reaching the decoder is rescaled to the size of
    the reconstruction gradient: neither term swamps the other whatever their raw scales. Both graphs
    are kept (retain_graph) for the backward pass that follows.
    """
    rec_grad = torch.autograd.grad(reconstruction_loss, last_layer, retain_graph=True)[0]
    gan_grad = torch.autograd.grad(gan_loss, last_layer, retain_graph=True)[0]
    weight = rec_grad.norm() / (gan_grad.norm() + eps)
    return weight.clamp(0.0, max_weight).detach()


class PatchDiscriminator3d(nn.Module):
    """Spatio-temporal PatchGAN for video: (b, 3, t, H, W) → logits (b, 1, t', h, w), one per space-time patch.

    The GAN stage of the GAIA-2 tokenizer fine-tunes the decoder against "a 3D convolutional
    discriminator" (GAIA-2 report, tokenizer): 3-D kernels see motion, so flicker between decoded frames is
    penalised, not only per-frame blur. Layout of PatchDiscriminator with 4×4×4 kernels; the first
    `temporal_layers` stride-2 layers also halve time, the others stride (1, 2, 2).

    Args:
        channels, num_layers, in_channels: as PatchDiscriminator.
        temporal_layers: how many of the stride-2 layers downsample time too.
    """

    def __init__(self, channels: int = 64, num_layers: int = 3, in_channels: int = 3, temporal_layers: int = 1):
        super().__init__()
        widths = [channels * min(2**i, 8) for i in range(num_layers + 1)]

        def stride(i: int) -> tuple[int, int, int]:
            if i >= num_layers:
                return (1, 1, 1)
            return (2 if i < temporal_layers else 1, 2, 2)

        layers: list[nn.Module] = [nn.Conv3d(in_channels, widths[0], 4, stride=stride(0), padding=(2, 1, 1)),
                                   nn.LeakyReLU(0.2)]
        for i in range(1, num_layers + 1):
            layers += [nn.Conv3d(widths[i - 1], widths[i], (3, 4, 4), stride=stride(i), padding=1, bias=False),
                       group_norm(widths[i]), nn.LeakyReLU(0.2)]
        layers.append(nn.Conv3d(widths[-1], 1, (3, 4, 4), stride=1, padding=1))
        self.layers = nn.Sequential(*layers)
        self.initialize_weights()

    def initialize_weights(self) -> None:
        dcgan_init(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (b, 3, t, H, W) in [-1, 1] → (b, 1, t', h, w) logits."""
        if x.ndim != 5:
            raise ValueError(f"PatchDiscriminator3d expects videos (b, c, t, H, W), got {tuple(x.shape)}")
        return self.layers(x)
