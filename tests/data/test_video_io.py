"""Video I/O: H.264 round trip, windows, atomic writes, and loud failures on bad files."""

from __future__ import annotations

import av
import numpy as np
import pytest
from av.video.frame import PictureType

from gaia_app.data.video_io import (
    VideoReadError,
    VideoWriteError,
    count_intact_packets,
    iter_frames,
    read_video,
    video_info,
    write_video,
)


@pytest.fixture
def frames(frames_factory) -> np.ndarray:
    return frames_factory(t=20, h=48, w=64, seed=1)


def test_round_trip_is_h264_within_codec_tolerance(tmp_path, frames):
    path = write_video(tmp_path / "v.mp4", frames, fps=6.25)
    decoded, fps = read_video(path)
    assert decoded.shape == frames.shape and decoded.dtype == np.uint8
    assert fps == pytest.approx(6.25)
    assert np.abs(decoded.astype(int) - frames).mean() < 4
    info = video_info(path)
    assert (info.num_frames, info.width, info.height, info.codec) == (20, 64, 48, "h264")
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264" and stream.codec_context.pix_fmt == "yuv420p"
        assert PictureType.B not in {f.pict_type for f in container.decode(stream)}


def test_rgb_order_is_kept(tmp_path):
    red = np.zeros((4, 32, 32, 3), np.uint8)
    red[..., 0] = 220
    decoded, _ = read_video(write_video(tmp_path / "red.mp4", red, 25))
    assert decoded[..., 0].mean() > 200 and decoded[..., 2].mean() < 20


def test_window_equals_slice_of_full_decode(tmp_path, frames):
    path = write_video(tmp_path / "v.mp4", iter(frames), fps=25)  # an iterable streams too
    full, _ = read_video(path)
    window, _ = read_video(path, start=7, max_frames=5)
    np.testing.assert_array_equal(window, full[7:12])
    tail, _ = read_video(path, start=17, max_frames=10)  # clipped at the end, not an error
    assert len(tail) == 3
    assert len(list(iter_frames(path, start=15))) == 5
    with pytest.raises(VideoReadError, match="start frame 20"):
        read_video(path, start=20)


def test_odd_size_is_refused_and_nothing_is_left_behind(tmp_path, frames):
    with pytest.raises(VideoWriteError, match="must be even"):
        write_video(tmp_path / "odd.mp4", frames[:, :47], fps=10)
    with pytest.raises(VideoWriteError, match="no frames"):
        write_video(tmp_path / "empty.mp4", [], fps=10)
    with pytest.raises(VideoWriteError, match="uint8"):
        write_video(tmp_path / "float.mp4", frames.astype(np.float32), fps=10)
    assert list(tmp_path.iterdir()) == []  # no target, no temporary file


def test_overwriting_a_video_is_atomic(tmp_path, frames):
    path = write_video(tmp_path / "v.mp4", frames, fps=10)
    write_video(path, frames[:5], fps=10)
    assert video_info(path).num_frames == 5 and [p.name for p in tmp_path.iterdir()] == ["v.mp4"]


def test_truncated_file_raises_naming_it(tmp_path, frames):
    path = write_video(tmp_path / "v.mp4", frames, fps=10)
    data = path.read_bytes()
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    assert count_intact_packets(cut) < video_info(cut).num_frames  # the header still claims every frame
    with pytest.raises(VideoReadError, match="cut.mp4"):
        read_video(cut)
    stub = tmp_path / "stub.mp4"
    stub.write_bytes(data[:100])
    with pytest.raises(VideoReadError, match="stub.mp4: cannot open"):
        read_video(stub)


def test_missing_file(tmp_path):
    with pytest.raises(VideoReadError, match="nope.mp4: video file not found"):
        read_video(tmp_path / "nope.mp4")
