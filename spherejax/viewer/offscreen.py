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
It stops when the process ends, however it ends: util-linux's `setpriv --pdeathsig TERM` starts
it (where there is setpriv, as on every Linux with util-linux 2.33 or later), so the kernel sends
it SIGTERM when this process is gone; Xvfb then removes its lock file and socket itself. (Not a
preexec_fn calling prctl: that forks through Python's at-fork hooks, which JAX, multithreaded by
then, warns against. Not Xvfb's -terminate: Qt connects and disconnects before it draws, and the
server would be gone by then.) Without setpriv the server outlives the process.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import select
import shutil
import signal
import time

#: Seconds to wait for Xvfb to say which display it took.
START_TIMEOUT_S = 20.0
#: The virtual screen: room for the viewer's window and its dock widget.
SCREEN = "1920x1200x24"


class NoDisplay(OSError):
    """No X server can be had for OpenGL off screen (one line: what is missing, what to do)."""


def _start_xvfb() -> tuple[int, str]:
    """(the Xvfb process's id, its DISPLAY), started on a free display number it picks.

    By posix_spawn, not subprocess.Popen: a Popen object of a server meant to outlive every
    Python object here says "subprocess N is still running" at the interpreter's exit."""
    program = shutil.which("Xvfb")
    if program is None:
        raise NoDisplay(
            "no display for OpenGL off screen: $DISPLAY is unset and Xvfb is not installed "
            "(expected an X display, or Xvfb on PATH: Debian/Ubuntu apt-get install xvfb)"
        )
    read_end, write_end = os.pipe()
    setpriv = shutil.which("setpriv")
    stop_with_us = [setpriv, "--pdeathsig", "TERM"] if setpriv else []
    argv = [*stop_with_us, program, "-displayfd", str(write_end), "-screen", "0", SCREEN, "-nolisten", "tcp"]
    try:
        os.set_inheritable(write_end, True)
        with open(os.devnull, "rb") as null_in, open(os.devnull, "wb") as null_out:
            pid = os.posix_spawn(argv[0], argv, os.environ, setsid=True,  # a Ctrl-C is ours, not the server's
                                 file_actions=[(os.POSIX_SPAWN_DUP2, null_in.fileno(), 0),
                                               (os.POSIX_SPAWN_DUP2, null_out.fileno(), 1),
                                               (os.POSIX_SPAWN_DUP2, null_out.fileno(), 2),
                                               (os.POSIX_SPAWN_CLOSE, read_end)])
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
        _stop(pid)
        raise NoDisplay(f"Xvfb ({program}) did not start (expected it to report a display number within "
                        f"{START_TIMEOUT_S:g} s)")
    return pid, f":{int(text)}"


def _stop(pid: int) -> None:
    """Stop a server that did not start (SIGTERM, then SIGKILL if it hangs) and reap it."""
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGTERM)
    for _ in range(100):
        done, _ = os.waitpid(pid, os.WNOHANG)
        if done:
            return
        time.sleep(0.1)
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)


_SERVER: int | None = None  # the Xvfb's process id


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
