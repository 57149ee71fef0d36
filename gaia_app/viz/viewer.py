"""Start a local Rerun viewer process that listens on loopback only, unless told otherwise.

The `rerun` binary binds its gRPC server to 0.0.0.0 by default, and the SDK's `rr.spawn` has no way to change
that: a live training view would be reachable from the whole network. `spawn_viewer` starts the binary itself,
with `--bind` (127.0.0.1 by default, `logger.rerun.bind` in the configs) and the flags `rr.spawn` passes.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

LOOPBACK = "127.0.0.1"
ALL_INTERFACES = ("0.0.0.0", "::")


class ViewerUnavailable(RuntimeError):
    """A Rerun viewer could not start here (no executable, no graphics adapter, port taken)."""


def viewer_executable() -> str:
    """The `rerun` CLI of this environment (next to the interpreter), else the one on PATH."""
    beside = Path(sys.executable).parent / "rerun"
    found = str(beside) if beside.exists() else shutil.which("rerun")
    if found is None:
        raise ViewerUnavailable("no `rerun` executable next to the Python interpreter or on PATH "
                                "(it comes with `pip install rerun-sdk`)")
    return found


def viewer_args(port: int, bind: str = LOOPBACK, headless: bool = False, hide_welcome_screen: bool = False,
                memory_limit: str = "75%", server_memory_limit: str = "1GiB") -> list[str]:
    """The command line of a viewer serving gRPC on bind:port."""
    check_port(port)
    args = [viewer_executable(), "--port", str(int(port)), "--bind", bind, "--memory-limit", memory_limit,
            "--server-memory-limit", server_memory_limit, "--expect-data-soon"]
    return args + (["--headless"] if headless else []) + (["--hide-welcome-screen"] if hide_welcome_screen else [])


def check_port(port: object, setting: str = "viewer port") -> int:
    """A TCP port number in [1, 65535], or a ValueError naming the setting (not a later "viewer exited" error)."""
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise ValueError(f"{setting} {port!r}: expected a TCP port number in [1, 65535]")
    return port


def connect_host(bind: str) -> str:
    """Where a client on this machine reaches a viewer bound to `bind`."""
    return LOOPBACK if bind in ALL_INTERFACES else bind


def port_open(host: str, port: int, timeout: float = 0.5) -> bool:
    """True when something accepts TCP connections on host:port."""
    check_port(port)
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])  # + an empty SETTINGS


def speaks_grpc(host: str, port: int, timeout: float = 1.0) -> bool:
    """True when the listener on host:port answers an HTTP/2 connection preface with a SETTINGS frame, as a Rerun
    viewer's gRPC server does; a web server, a database or anything else on the port answers otherwise (or not at
    all), and logging to it would fail mid-run."""
    check_port(port)
    try:
        with socket.create_connection((host, port), timeout=timeout) as connection:
            connection.sendall(HTTP2_PREFACE)
            reply = connection.recv(9)
    except OSError:
        return False
    return len(reply) >= 4 and reply[3] == 4  # frame header: 3 bytes length, then the type (4 = SETTINGS)


def spawn_viewer(port: int, bind: str = LOOPBACK, headless: bool = False, hide_welcome_screen: bool = False,
                 wait_s: float = 20.0) -> subprocess.Popen:
    """Start `rerun` serving on bind:port and wait until it accepts connections; ViewerUnavailable when it exits
    or does not answer within `wait_s`. The viewer outlives this process (a live training view) unless stopped with
    `stop_viewer`: the `rerun` command is a Python launcher that runs the viewer binary as its child, so the viewer
    gets its own process group, which `stop_viewer` ends whole (killing the launcher alone leaves the viewer on)."""
    process = subprocess.Popen(viewer_args(port, bind, headless, hide_welcome_screen),
                               env={**os.environ, "RERUN_APP_ONLY": "true"}, stdin=subprocess.DEVNULL,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        if port_open(connect_host(bind), port):
            return process
        if process.poll() is not None:
            raise ViewerUnavailable(f"the Rerun viewer exited at start (code {process.returncode}); without a GPU "
                                    "it needs Mesa's software Vulkan driver: apt-get install mesa-vulkan-drivers")
        time.sleep(0.2)
    stop_viewer(process)
    raise ViewerUnavailable(f"the Rerun viewer did not listen on {bind}:{port} within {wait_s:g} s")


def stop_viewer(process: subprocess.Popen) -> None:
    """End a viewer started by `spawn_viewer`: its launcher and the viewer binary under it."""
    try:
        os.killpg(process.pid, signal.SIGKILL)
    except ProcessLookupError:  # already gone
        pass
    process.wait(timeout=10)
