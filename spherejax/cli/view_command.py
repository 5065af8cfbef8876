"""`spherejax view`: an output of `correct` in napari with the readout docked (spherejax.viewer),
in a window, or rendered off screen into a PNG (--screenshot)."""

from __future__ import annotations

import importlib.util
import os
import pathlib
import warnings

from .. import interrupt
from .shared import argument_text

#: What is missing without the viewer extra, and how to get it.
NEEDS_EXTRA = ("view: the viewer extra is not installed (napari and PyQt5; expected them installed: "
               "pip install 'spherejax[viewer]')")


def _pixel(value: str | None) -> tuple[int, int] | None:
    """--pixel ROW,COL -> (row, col); ValueError naming the value."""
    if value is None:
        return None
    value = argument_text(value, "--pixel")
    parts = [part.strip() for part in value.split(",")]
    try:
        row, col = (int(part) for part in parts)
    except ValueError:
        raise ValueError(f"--pixel {value!r}: expected ROW,COL, two integers (0-based, row first)") from None
    if row < 0 or col < 0:
        raise ValueError(f"--pixel {value!r}: expected ROW,COL of 0 or more")
    return row, col


def _inputs(args) -> dict:
    return {"PATH": pathlib.Path(args.path), "the calibration (-c)": args.calibration and pathlib.Path(args.calibration),
            "the raw cube (--raw)": args.raw and pathlib.Path(args.raw)}


def _check_x11_platform() -> None:
    """Before a window on X11 (Qt's xcb platform, PyQt5's wheel): its plugin loads, or one line
    says which system library is missing. Qt itself would abort the process (SIGABRT, a core
    dump and a page of text) when the plugin cannot load: PyQt5's wheel bundles Qt but not
    every xcb library (Debian 12 without a desktop lacks libxcb-icccm4, libxcb-keysyms1 and
    libxcb-xinerama0)."""
    import ctypes

    if os.environ.get("QT_QPA_PLATFORM", "xcb") != "xcb" or not os.environ.get("DISPLAY"):
        return
    spec = importlib.util.find_spec("PyQt5")
    if spec is None or not spec.submodule_search_locations:
        return
    plugin = pathlib.Path(spec.submodule_search_locations[0], "Qt5", "plugins", "platforms", "libqxcb.so")
    if not plugin.is_file():
        return
    try:
        ctypes.CDLL(str(plugin))
    except OSError as error:
        missing = str(error).split(":")[0].strip()
        raise ValueError(
            f"view: Qt's X11 platform cannot load: {missing} is missing (expected the xcb libraries "
            "of a desktop; Debian/Ubuntu: apt-get install libxcb-icccm4 libxcb-keysyms1 libxcb-xinerama0 "
            "libxcb-image0 libxcb-render-util0 libxkbcommon-x11-0), or use --screenshot FILE.png"
        ) from None


def cmd_view(args) -> int:
    from ..viewer import outputs
    from ..viewer.offscreen import use_offscreen

    # Everything the arguments alone decide is refused before any file is read.
    pixel = _pixel(args.pixel)
    if args.raw is not None and args.calibration is None:
        raise ValueError("--raw: needs -c CAL, the calibration the output was corrected with")
    if args.pixel is not None and args.screenshot is None:
        raise ValueError("--pixel: goes with --screenshot FILE.png (in a window, click the pixel)")
    if not pathlib.Path(args.path).exists():
        raise ValueError(f"{args.path}: no such file or folder (expected an output of spherejax correct, or its folder)")
    if args.screenshot is not None:
        outputs.check_screenshot_path(args.screenshot, inputs=_inputs(args))
    if importlib.util.find_spec("napari") is None or importlib.util.find_spec("qtpy") is None:
        raise ValueError(NEEDS_EXTRA)
    if args.screenshot is not None:
        use_offscreen()  # before Qt is imported: the platform and binding are chosen then
    elif not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise ValueError("view: no display to open a window on ($DISPLAY is unset): run it on a "
                         "desktop, or render the window into a file with --screenshot FILE.png")
    else:
        _check_x11_platform()

    from ..viewer import window

    # napari's, on the Qt 5 binding the extra installs: not the user's to act on.
    warnings.filterwarnings("ignore", message="System theme detection requires a Qt6 backend", category=UserWarning)
    viewer = window.open_viewer(args.path, calibration=args.calibration, raw=args.raw, show=args.screenshot is None)
    try:
        if pixel is not None:
            try:
                window.readout(viewer, pixel, illuminant=args.illuminant)
            except ValueError as error:
                raise ValueError(f"--pixel {args.pixel!r}: {str(error).split(': ', 1)[-1]}") from None
        elif args.illuminant is not None:
            window.widget_of(viewer).illuminant.setCurrentText(args.illuminant)
        if args.screenshot is None:
            _run_until_closed_or_stopped()
            return 0
        interrupt.check()
        png = window.screenshot_png(viewer)
        # A stop asked for while the file is put in place waits until it is there, whole.
        with interrupt.stop_requests():
            written = outputs.write_screenshot(args.screenshot, png, inputs=_inputs(args))
    finally:
        viewer.close()
    if not args.quiet:
        print(f"written: {written}")
    return 0


def _run_until_closed_or_stopped() -> None:
    """Qt's event loop until the window closes or a stop is asked for (SIGINT, SIGTERM, SIGHUP:
    `interrupt` records it; Qt's loop would not let Python see it, so a timer looks every
    0.2 s and quits the loop, and the command exits 128 + the signal as every command does)."""
    import napari
    from qtpy.QtCore import QTimer
    from qtpy.QtWidgets import QApplication

    from .. import console

    app = QApplication.instance()
    console.log.debug("view: the window is open; closing it, Ctrl-C or SIGTERM ends the command")
    timer = QTimer()
    timer.timeout.connect(lambda: app.quit() if interrupt.requested() is not None else None)
    timer.start(200)
    try:
        napari.run()
    finally:
        timer.stop()
    interrupt.check()


__all__ = ["cmd_view"]
