"""Media helpers: pixel conversion, grids, token colour maps, and what they log."""

from __future__ import annotations

import numpy as np
import pytest
import rerun as rr
import torch
from rerun.chunk import RrdReader

from gaia_app.viz import media


def test_to_hwc_uint8_range_and_layouts():
    chw = torch.tensor([-1.0, 0.0, 1.0]).reshape(3, 1, 1).expand(3, 2, 2)
    out = media.to_hwc_uint8(chw)
    assert out.shape == (2, 2, 3) and out.dtype == np.uint8
    assert out[0, 0].tolist() == [0, 128, 255]  # -1 -> 0 and 1 -> 255 exactly; 0 -> 127.5 rounds to even 128
    assert np.array_equal(media.to_hwc_uint8(chw.permute(1, 2, 0).numpy()), out)  # (h, w, c) input
    u8 = np.arange(12, dtype=np.uint8).reshape(2, 2, 3)
    assert np.array_equal(media.to_hwc_uint8(u8), u8)
    assert media.to_hwc_uint8(torch.zeros(1, 2, 2)).shape == (2, 2, 3)  # grey -> RGB
    assert media.to_hwc_uint8(chw.to(torch.bfloat16))[0, 0].tolist() == [0, 128, 255]
    with pytest.raises(ValueError):
        media.to_hwc_uint8(torch.zeros(5, 2, 2))


def test_image_grid_layout():
    imgs = torch.stack([torch.full((3, 2, 2), v) for v in (-1.0, 1.0, -1.0)])  # black, white, black
    grid = media.image_grid(imgs, ncols=2, pad=1)
    assert grid.shape == (2 * 2 + 1, 2 * 2 + 1, 3)
    assert grid[0, 3].tolist() == [255, 255, 255]  # second tile, first row
    assert grid[2].max() == 0  # padding row


def test_video_grid_shape():
    vid = torch.zeros(2, 5, 3, 4, 6)
    assert media.video_grid(vid, ncols=2).shape == (5, 3, 4, 2 * 6 + 1)


def test_pca_palette_deterministic_distinct():
    codebook = torch.randn(16, 8, generator=torch.Generator().manual_seed(0))
    pal = media.pca_palette(codebook)
    assert pal.shape == (16, 3) and pal.dtype == np.uint8
    assert np.array_equal(pal, media.pca_palette(codebook.clone()))
    assert np.array_equal(pal, media.pca_palette(codebook.double().numpy()))
    assert len({tuple(c) for c in pal}) == 16  # distinct codes, distinct colours
    assert pal.min(axis=0).tolist() == [0, 0, 0] and pal.max(axis=0).tolist() == [255, 255, 255]
    tokens = torch.tensor([[0, 1], [1, 15]])
    rgb = media.token_map_rgb(tokens, codebook)
    assert np.array_equal(rgb[0, 1], rgb[1, 0]) and not np.array_equal(rgb[0, 0], rgb[1, 1])


def test_pca_palette_low_dim_codebook():
    pal = media.pca_palette(torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0]]))
    assert pal.shape == (3, 3) and pal[:, 2].max() == 0  # d=2: third channel unused


def test_pca_palette_separates_clusters():
    """Codes close in embedding space get close colours (the point of GAIA-1 Fig. 3)."""
    g = torch.Generator().manual_seed(1)
    centres = torch.tensor([[5.0, 0, 0, 0], [-5.0, 0, 0, 0]])
    codebook = (centres[:, None] + 0.1 * torch.randn(2, 4, 4, generator=g)).reshape(8, 4)
    pal = media.pca_palette(codebook).astype(int)
    within = np.abs(pal[0] - pal[1]).sum()
    across = np.abs(pal[0] - pal[4]).sum()
    assert across > 4 * within


def test_hash_colors_deterministic_distinct():
    ids = np.arange(1024)
    a, b = media.hash_colors(ids), media.hash_colors(torch.arange(1024))
    assert np.array_equal(a, b) and a.shape == (1024, 3)
    assert len({tuple(c) for c in a}) == 1024


def test_token_map_rejects_out_of_range_ids():
    with pytest.raises(ValueError):
        media.token_map_rgb(torch.tensor([[16]]), torch.randn(16, 4))


def test_log_functions_write_expected_rows(tmp_path):
    path = tmp_path / "m.rrd"
    rec = rr.RecordingStream("test", recording_id="media")
    rec.save(str(path))
    rec.set_time("step", sequence=0)
    media.log_images(rec, "/img", torch.zeros(3, 3, 4, 4), jpeg_quality=80)
    media.log_images(rec, "/one", torch.zeros(3, 4, 4))
    media.log_video(rec, "/vid", torch.zeros(5, 3, 4, 4), start=10)
    media.log_token_map(rec, "/tok", torch.zeros(2, 4, 4, dtype=torch.long), torch.randn(8, 4))
    rec.flush()
    rec.disconnect()

    rows, frames = {}, {}
    for ch in RrdReader(str(path)).stream().collect().stream().to_chunks():
        rows[ch.entity_path] = rows.get(ch.entity_path, 0) + ch.num_rows
        if "frame" in ch.timeline_names:
            frames.setdefault(ch.entity_path, []).extend(ch.to_record_batch().column("frame").to_pylist())
        if ch.entity_path == "/img":
            assert "EncodedImage:media_type" in ch.to_record_batch().schema.names
    assert rows["/img"] == rows["/one"] == rows["/tok"] == 1
    assert rows["/vid"] == 5 and sorted(frames["/vid"]) == list(range(10, 15))
    assert set(frames) == {"/vid"}  # the frame timeline is cleared after the video
