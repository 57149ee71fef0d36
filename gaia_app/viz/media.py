"""Pure helpers that turn image, video and token tensors into Rerun archetypes.

Legend: b batch, t time (frames), c channels, h height, w width, K codebook size, d code dim.
Pixels follow the project convention: float in [-1, 1] (or uint8 in [0, 255]).
No Lightning here: the callback and the pipelines both call these functions.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import rerun as rr
import torch

ArrayLike = torch.Tensor | np.ndarray


def _to_numpy(x: ArrayLike) -> np.ndarray:
    """Detach a tensor (any device, bf16 included) or pass a numpy array through."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu()
        # numpy has no bfloat16 / half support worth relying on
        return (x.float() if x.is_floating_point() else x).numpy()
    return np.asarray(x)


def to_hwc_uint8(x: ArrayLike, channels_first: bool | None = None) -> np.ndarray:
    """Convert one image to an RGB uint8 array.

    x: (c, h, w) or (h, w, c) or (h, w); float in [-1, 1] or uint8 in [0, 255]; c in {1, 3}.
    channels_first: force the layout; by default (c, h, w) wins when the first dim is 1 or 3
        (the torch convention of this project), else (h, w, c).
    Returns (h, w, 3) uint8; -1 maps to 0 and 1 to 255 exactly.
    """
    a = _to_numpy(x)
    if a.ndim == 2:
        a = a[None]
        channels_first = True
    if a.ndim != 3:
        raise ValueError(f"expected an image (c, h, w) or (h, w, c), got shape {a.shape}")
    if channels_first is None:
        channels_first = a.shape[0] in (1, 3) or a.shape[-1] not in (1, 3)
    if channels_first:
        a = a.transpose(1, 2, 0)
    if a.shape[-1] not in (1, 3):
        raise ValueError(f"expected 1 or 3 channels, got image of shape {a.shape} (h, w, c)")
    if np.issubdtype(a.dtype, np.floating):
        a = np.rint((np.clip(a, -1.0, 1.0) + 1.0) * 127.5)
    a = np.clip(a, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(np.repeat(a, 3, axis=-1) if a.shape[-1] == 1 else a)


def image_grid(images: ArrayLike, ncols: int | None = None, pad: int = 1) -> np.ndarray:
    """Tile a batch of images into one RGB image, row-major, black padding between tiles.

    images: (b, c, h, w) float in [-1, 1] or uint8.
    ncols: tiles per row (default: ceil(sqrt(b))).
    Returns (rows*h + (rows-1)*pad, ncols*w + (ncols-1)*pad, 3) uint8.
    """
    tiles = [to_hwc_uint8(img, channels_first=True) for img in images]
    if not tiles:
        raise ValueError("image_grid needs at least one image")
    b, (h, w, _) = len(tiles), tiles[0].shape
    ncols = min(ncols or math.ceil(math.sqrt(b)), b)
    nrows = math.ceil(b / ncols)
    grid = np.zeros((nrows * (h + pad) - pad, ncols * (w + pad) - pad, 3), np.uint8)
    for i, tile in enumerate(tiles):
        r, c = divmod(i, ncols)
        grid[r * (h + pad) : r * (h + pad) + h, c * (w + pad) : c * (w + pad) + w] = tile
    return grid


def video_grid(videos: ArrayLike, ncols: int | None = None, pad: int = 1) -> np.ndarray:
    """Tile several videos frame by frame, so they play side by side.

    videos: (b, t, c, h, w) float in [-1, 1] or uint8.
    Returns (t, 3, H, W) uint8, one image_grid per frame, ready for log_video.
    """
    frames = [image_grid(videos[:, i], ncols, pad) for i in range(videos.shape[1])]
    return np.stack(frames).transpose(0, 3, 1, 2)


def rgb_archetype(rgb: np.ndarray, jpeg_quality: int | None = None) -> rr.Image | rr.EncodedImage:
    """Wrap an (h, w, 3) uint8 image as rr.Image, or as a JPEG rr.EncodedImage to keep the .rrd small."""
    if jpeg_quality is None:
        return rr.Image(rgb)
    # cv2 (a declared dependency) rather than rr.Image.compress, which needs Pillow
    ok, jpg = cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:
        raise RuntimeError(f"JPEG encoding failed for an image of shape {rgb.shape}")
    return rr.EncodedImage(contents=jpg.tobytes(), media_type="image/jpeg")


def log_images(
    rec: rr.RecordingStream,
    path: str,
    images: ArrayLike,
    jpeg_quality: int | None = None,
    ncols: int | None = None,
) -> None:
    """Log one image, or a batch as a grid, at `path` on the stream's current time.

    images: (b, c, h, w) batch, or one image (c, h, w) / (h, w, c) / (h, w);
        float in [-1, 1] or uint8.
    """
    is_batch = getattr(images, "ndim", 0) == 4
    rgb = image_grid(images, ncols) if is_batch else to_hwc_uint8(images)
    rec.log(path, rgb_archetype(rgb, jpeg_quality))


def log_video(
    rec: rr.RecordingStream,
    path: str,
    video: ArrayLike,
    timeline: str = "frame",
    start: int = 0,
    jpeg_quality: int | None = None,
) -> None:
    """Log a video as one image per frame on the `timeline` sequence (frames start..start+t-1).

    video: (t, c, h, w) float in [-1, 1] or uint8.
    Other timelines (e.g. `step`) keep their current value; `timeline` is cleared afterwards
    so that later logs on this stream do not pick up the last frame index.
    """
    for i, frame in enumerate(video):
        rec.set_time(timeline, sequence=start + i)
        rec.log(path, rgb_archetype(to_hwc_uint8(frame, channels_first=True), jpeg_quality))
    rec.disable_timeline(timeline)


def pca_palette(codebook: ArrayLike) -> np.ndarray:
    """Colour each code by its first three principal components (GAIA-1 Fig. 3).

    codebook: (K, d) float code embeddings.
    Returns (K, 3) uint8; each component is min-max scaled over the codebook.
    Deterministic: SVD on CPU in float64, and each axis' sign fixed so that its largest
    loading is positive (SVD alone leaves the sign arbitrary).
    """
    e = torch.as_tensor(_to_numpy(codebook), dtype=torch.float64)
    e = e - e.mean(dim=0, keepdim=True)
    _, _, vh = torch.linalg.svd(e, full_matrices=False)  # vh: (min(K, d), d)
    axes = vh[:3]
    signs = torch.sign(axes.gather(1, axes.abs().argmax(dim=1, keepdim=True)))
    proj = e @ (axes * signs).T  # (K, <=3)
    proj = torch.nn.functional.pad(proj, (0, 3 - proj.shape[1]))  # d < 3: unused channels stay 0
    lo, hi = proj.min(dim=0).values, proj.max(dim=0).values
    scaled = (proj - lo) / torch.where(hi > lo, hi - lo, torch.ones_like(hi))
    return (scaled * 255).round().to(torch.uint8).numpy()


def hash_colors(tokens: ArrayLike) -> np.ndarray:
    """Deterministic pseudo-random colour per token id (splitmix64 bits), for maps without a codebook.

    tokens: (...) int. Returns (..., 3) uint8.
    """
    x = _to_numpy(tokens).astype(np.uint64) + np.uint64(1)
    with np.errstate(over="ignore"):  # the mixing relies on uint64 wrap-around
        x = x * np.uint64(0x9E3779B97F4A7C15)
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        x = x ^ (x >> np.uint64(31))
    rgb = np.stack([(x >> np.uint64(s)) & np.uint64(0xFF) for s in (0, 8, 16)], axis=-1)
    return rgb.astype(np.uint8)


def token_map_rgb(tokens: ArrayLike, codebook: ArrayLike | None = None) -> np.ndarray:
    """Colour a token map: PCA of code embeddings when a codebook is given, else a hash colour.

    tokens: (..., h, w) int in [0, K). codebook: (K, d) float, optional.
    Returns (..., h, w, 3) uint8.
    """
    ids = _to_numpy(tokens).astype(np.int64)
    if codebook is None:
        return hash_colors(ids)
    palette = pca_palette(codebook)
    if ids.size and (ids.min() < 0 or ids.max() >= len(palette)):
        raise ValueError(f"token ids must lie in [0, {len(palette)}), got [{ids.min()}, {ids.max()}]")
    return palette[ids]


def log_token_map(
    rec: rr.RecordingStream,
    path: str,
    tokens: ArrayLike,
    codebook: ArrayLike | None = None,
    ncols: int | None = None,
) -> None:
    """Log a token map (or a batch as a grid) as a colour image at `path` (GAIA-1 Fig. 3).

    tokens: (h, w) or (b, h, w) int. codebook: (K, d) float, optional (see token_map_rgb).
    Lossless on purpose: JPEG would blur the one-pixel-per-token boundaries.
    """
    rgb = token_map_rgb(tokens, codebook)
    if rgb.ndim == 4:
        rgb = image_grid(rgb.transpose(0, 3, 1, 2), ncols)  # (b, h, w, 3) -> (b, 3, h, w)
    rec.log(path, rr.Image(rgb))
