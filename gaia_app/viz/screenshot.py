"""Screenshots of a Rerun recording in a headless viewer (for the README gallery and its test).

The headless viewer needs a graphics adapter: on a machine without a GPU, Mesa's software Vulkan driver
(Debian/Ubuntu package `mesa-vulkan-drivers`) is enough; with only OpenGL llvmpipe the viewer exits at start.
"""

from __future__ import annotations

import socket
import time
from pathlib import Path

from gaia_app.utils.run_dir import atomic_write_bytes
from gaia_app.viz.viewer import LOOPBACK, ViewerUnavailable, spawn_viewer, stop_viewer


def _free_port() -> int:
    with socket.socket() as s:
        s.bind((LOOPBACK, 0))
        return s.getsockname()[1]


def spawn_headless():
    """A headless viewer process on a free loopback port, and a client of it (its `url` takes a GrpcSink)."""
    from rerun.experimental import ViewerClient  # experimental API: import where used

    port = _free_port()
    process = spawn_viewer(port, headless=True, hide_welcome_screen=True)
    try:
        return ViewerClient(f"rerun+http://{LOOPBACK}:{port}/proxy"), process
    except (RuntimeError, TimeoutError, OSError) as err:
        stop_viewer(process)
        raise ViewerUnavailable(f"the headless Rerun viewer did not answer ({err}); without a GPU it needs "
                                "Mesa's software Vulkan driver: apt-get install mesa-vulkan-drivers") from err


def screenshot_recording(rrd: str | Path, png: str | Path, frame: int | None = None, max_size: int = 1280,
                         settle_s: float = 3.0) -> Path:
    """Open `rrd` in a headless viewer with its own blueprint, pause at `frame` on the `frame` timeline (the
    last frame when None), and write the viewer as a PNG (longest side `max_size` px) to `png`, atomically.

    Chunks stream into the viewer on demand, so after seeking it screenshots until the picture stops changing
    (at most `2 * settle_s`).
    Raises ViewerUnavailable when no headless viewer can run here, FileNotFoundError for a missing `rrd`.
    """
    rrd = Path(rrd)
    if not rrd.is_file():
        raise FileNotFoundError(f"no Rerun recording at {rrd}")
    viewer, process = spawn_headless()
    try:
        try:
            opened = viewer.open(str(rrd.resolve()))
        except ConnectionError as err:  # spawned, then died: no usable Vulkan driver on this machine
            raise _stopped_answering(err) from err
        if not opened.store_ids:
            raise RuntimeError(f"the Rerun viewer opened no recording from {rrd}")
        timeline = _frame_timeline(viewer, rrd)
        viewer.set_time("frame", sequence=timeline.end if frame is None else frame, play_state="paused")
        return _capture(viewer, png, max_size, settle_s)
    finally:  # the client only connected: the viewer process is ours to stop
        stop_viewer(process)


def capture_live(viewer, process, png: str | Path, max_size: int = 1280, settle_s: float = 3.0) -> Path:
    """Write what a headless viewer fed live (spawn_headless) shows now as a PNG, atomically, then stop it."""
    try:
        return _capture(viewer, png, max_size, settle_s)
    finally:
        stop_viewer(process)


def _capture(viewer, png: str | Path, max_size: int, settle_s: float, poll_s: float = 0.25,
             stable_shots: int = 3) -> Path:
    """Screenshot until `stable_shots` in a row agree (the chunks in view have arrived and been painted), at most
    `2 * settle_s` after the first paint; then write the last one. The first paint fetches the chunks in view and
    never counts, so a blank first paint is not taken for a settled one; a viewer that has what it needs settles in
    about 1.5 s instead of waiting the whole time."""
    try:
        viewer.take_screenshot(max_size=max_size)  # fetches the chunks in view
        deadline, same = time.monotonic() + 2 * settle_s, 0
        time.sleep(poll_s)
        shot = viewer.take_screenshot(max_size=max_size)
        while same < stable_shots - 1 and time.monotonic() < deadline:
            time.sleep(poll_s)
            previous, shot = shot, viewer.take_screenshot(max_size=max_size)
            same = same + 1 if shot == previous else 0
    except ConnectionError as err:  # spawned, then died while painting: no usable Vulkan driver here
        raise _stopped_answering(err) from err
    atomic_write_bytes(png, shot)
    return Path(png)


def _stopped_answering(err: Exception) -> ViewerUnavailable:
    return ViewerUnavailable(f"the headless Rerun viewer stopped answering ({err}); without a GPU it needs "
                             "Mesa's software Vulkan driver: apt-get install mesa-vulkan-drivers")


def _frame_timeline(viewer, rrd: Path):
    """The `frame` timeline of the active recording, or a clear error naming the file."""
    state = viewer.get_state()
    for recording in state.recordings:
        if recording.store_id == state.active_recording:
            for timeline in recording.timelines:
                if timeline.name == "frame":
                    return timeline
    raise ValueError(f"{rrd} has no `frame` timeline (expected a generate.py rollout recording)")
