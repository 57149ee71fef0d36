"""Image reconstruction metrics (pure torch). Images are float in [-1, 1], shape (b, c, h, w)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def psnr(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB per image, (b,), on the [0, 1] scale (peak 1)."""
    mse = ((x.clamp(-1, 1) - y.clamp(-1, 1)) / 2).pow(2).flatten(1).mean(1)
    return 10 * torch.log10(1.0 / mse.clamp_min(1e-10))


def _gaussian_window(size: int, sigma: float, channels: int, device, dtype) -> torch.Tensor:
    coords = torch.arange(size, device=device, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(coords**2) / (2 * sigma**2))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).expand(channels, 1, size, size).contiguous()


def ssim(x: torch.Tensor, y: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Structural similarity (Wang et al. 2004) per image, (b,), on the [0, 1] scale.

    Gaussian 11×11 window, σ = 1.5, K1 = 0.01, K2 = 0.03, valid convolution; the window shrinks
    to the image size for tiny images.
    """
    x = (x.clamp(-1, 1) + 1) / 2
    y = (y.clamp(-1, 1) + 1) / 2
    window = min(window, x.shape[-1], x.shape[-2])
    w = _gaussian_window(window, sigma, x.shape[1], x.device, x.dtype)
    blur = lambda t: F.conv2d(t, w, groups=x.shape[1])  # noqa: E731
    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x**2
    var_y = blur(y * y) - mu_y**2
    cov = blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return s.flatten(1).mean(1)


def codebook_perplexity(tokens: torch.Tensor, codebook_size: int) -> torch.Tensor:
    """exp(entropy) of the token histogram: 1 = one code used, K = uniform use."""
    counts = torch.bincount(tokens.flatten(), minlength=codebook_size).float()
    p = counts / counts.sum()
    entropy = -(p[p > 0] * p[p > 0].log()).sum()
    return entropy.exp()


def temporal_flicker(video: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Mean |Δvideo − Δreference| over consecutive-frame differences: (b, t, c, h, w) twice → (b,).

    Zero when the decoded video changes from frame to frame exactly as the reference does, whatever
    its per-frame error; frame-by-frame decoding that jitters around the truth scores high
    (the reason for GAIA-1's video decoder, §2.4). Needs t ≥ 2; same value range as the inputs.
    """
    if video.shape != reference.shape or video.ndim != 5 or video.shape[1] < 2:
        raise ValueError(f"temporal_flicker needs two (b, t ≥ 2, c, h, w) videos of one shape, got "
                         f"{tuple(video.shape)} and {tuple(reference.shape)}")
    change = video.diff(dim=1) - reference.diff(dim=1)
    return change.abs().flatten(1).mean(1)
