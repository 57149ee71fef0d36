"""The headless screenshot's wait (gaia_app.viz.screenshot._capture) with a stand-in viewer: it stops once the picture
has stopped changing, never trusts the first paint, and gives up at its deadline."""

from __future__ import annotations

from pathlib import Path

from gaia_app.viz import screenshot


class PaintingViewer:
    """take_screenshot returns the next picture of `pictures`, then repeats the last one."""

    def __init__(self, pictures: list[bytes]):
        self.pictures, self.calls = pictures, 0

    def take_screenshot(self, max_size: int) -> bytes:
        self.calls += 1
        return self.pictures[min(self.calls, len(self.pictures)) - 1]


def test_capture_waits_for_the_picture_to_stop_changing(tmp_path: Path) -> None:
    viewer = PaintingViewer([b"blank", b"blank", b"half", b"full"])
    screenshot._capture(viewer, tmp_path / "shot.png", 1280, settle_s=5.0, poll_s=0.0)
    assert (tmp_path / "shot.png").read_bytes() == b"full"
    assert viewer.calls == 6  # the first paint, "blank", "half", then "full" three times in a row


def test_a_blank_first_paint_is_not_taken_for_a_settled_one(tmp_path: Path) -> None:
    viewer = PaintingViewer([b"blank", b"full"])  # a second blank paint would match the first; it never counts
    screenshot._capture(viewer, tmp_path / "shot.png", 1280, settle_s=5.0, poll_s=0.0)
    assert (tmp_path / "shot.png").read_bytes() == b"full" and viewer.calls == 4


def test_capture_gives_up_at_its_deadline_with_the_last_picture(tmp_path: Path) -> None:
    class Flickering(PaintingViewer):
        def take_screenshot(self, max_size: int) -> bytes:
            self.calls += 1
            return str(self.calls).encode()

    viewer = Flickering([])
    screenshot._capture(viewer, tmp_path / "shot.png", 1280, settle_s=0.05, poll_s=0.01)
    assert (tmp_path / "shot.png").read_bytes() == str(viewer.calls).encode() and 3 <= viewer.calls < 100
