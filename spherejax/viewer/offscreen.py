"""Rendering the viewer off screen, with no display: Qt's offscreen platform and, for napari's
OpenGL canvas, an X server of this process's own (Xvfb) where there is no display.

Qt's "offscreen" platform draws widgets into memory, but it makes OpenGL contexts only through
GLX, from the X server $DISPLAY names; with none, vispy's first GL call returns nothing and the
canvas cannot be drawn (seen with PyQt5 5.15 and PyQt6 6.11: `glGetParameter` gives None; Qt 6
moreover refuses QOpenGLWidget on the offscreen platform, which is why the viewer extra takes
PyQt5). So `use_offscreen()` sets QT_QPA_PLATFORM=offscreen and, where $DISPLAY is unset, starts
`Xvfb` (Debian: xvfb) on a display number it picks itself (-displayfd). Mesa's llvmpipe renders
the GL in software; no GPU is needed.

The server lives as long as this process, not shorter: Qt's offscreen platform keeps its GLX
connection until the QApplication is destroyed, at the interpreter's exit, and an X server gone
before then ends the process with Xlib's "XIO: fatal IO error" instead of its own exit status.
The kernel stops it when the process ends, however it ends (PR_SET_PDEATHSIG, SIGTERM: Xvfb
then removes its lock file and socket itself).
"""

from __future__ import annotations

import ctypes
import importlib.util
import os
import select
import shutil
import subprocess
import time

#: Seconds to wait for Xvfb to say which display it took.
START_TIMEOUT_S = 20.0
#: The virtual screen: room for the viewer's window and its dock widget.
SCREEN = "1920x1200x24"


class NoDisplay(OSError):
    """No X server can be had for OpenGL off screen (one line: what is missing, what to do)."""


def _start_xvfb() -> tuple[subprocess.Popen, str]:
    """(the Xvfb process, its DISPLAY), started on a free display number it picks."""
    program = shutil.which("Xvfb")
    if program is None:
        raise NoDisplay(
            "no display for OpenGL off screen: $DISPLAY is unset and Xvfb is not installed "
            "(expected an X display, or Xvfb on PATH: Debian/Ubuntu apt-get install xvfb)"
        )
    read_end, write_end = os.pipe()
    try:
        process = subprocess.Popen(
            [program, "-displayfd", str(write_end), "-screen", "0", SCREEN, "-nolisten", "tcp"],
            pass_fds=(write_end,), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            start_new_session=True,  # the terminal's Ctrl-C is ours to handle, not the server's
            preexec_fn=_stop_with_parent,
        )
    finally:
        os.close(write_end)
    text, deadline = b"", time.monotonic() + START_TIMEOUT_S
    try:
        while not text.endswith(b"\n"):
            left = deadline - time.monotonic()
            ready, _, _ = select.select([read_end], [], [], max(left, 0.0))
            chunk = os.read(read_end, 64) if ready else b""
            if not chunk:
                break
            text += chunk
    finally:
        os.close(read_end)
    if not text.strip().isdigit():
        _stop(process)
        raise NoDisplay(f"Xvfb ({program}) did not start (expected it to report a display number within "
                        f"{START_TIMEOUT_S:g} s)")
    return process, f":{int(text)}"


def _stop_with_parent() -> None:
    """In the child, before exec: SIGTERM when the process that started it ends (Linux)."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(1, 15, 0, 0, 0)  # PR_SET_PDEATHSIG = 1, SIGTERM = 15


def _stop(process: subprocess.Popen) -> None:
    """Stop the server (SIGTERM: it removes its lock file and socket), killing it if it hangs."""
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


_SERVER: subprocess.Popen | None = None


def use_offscreen() -> None:
    """Qt off screen from now on, with an X server of this process's own where $DISPLAY is
    unset (module docstring); once per process. Raises NoDisplay."""
    global _SERVER
    os.environ["QT_QPA_PLATFORM"] = "offscreen"
    if "QT_API" not in os.environ and importlib.util.find_spec("PyQt5") is not None:
        # Where a Qt 6 binding is installed too, qtpy could take it, and its canvas off screen is blank.
        os.environ["QT_API"] = "pyqt5"
    if _SERVER is None and not os.environ.get("DISPLAY"):
        _SERVER, os.environ["DISPLAY"] = _start_xvfb()


__all__ = ["NoDisplay", "START_TIMEOUT_S", "use_offscreen"]
