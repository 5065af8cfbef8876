"""The viewer as a whole: a napari window with an output's layers and the readout widget
(`open_viewer`), what the widget shows for a pixel (`readout`), and the window as a PNG
(`screenshot_png`, what `spherejax view --screenshot` writes).
"""

from __future__ import annotations

import io as _bytes_io

import numpy as np

from .capture import CorrectedCapture
from .layers import read_layers
from .outputs import SCREENSHOT_SOFTWARE
from .widget import ReadoutWidget, capture_of, widget_of

#: The window's size for screenshots, pixels: the canvas beside the dock widget.
SCREENSHOT_SIZE = (1400, 860)


def dock_readout(viewer) -> ReadoutWidget:
    """Dock the readout widget in `viewer` (once: a second call returns the first)."""
    widget = widget_of(viewer)
    if widget is None:
        widget = ReadoutWidget(viewer)
        viewer.window.add_dock_widget(widget, name="spherejax readout", area="right")
    return widget


def open_viewer(path, *, calibration=None, raw=None, show: bool = True, viewer=None):
    """A napari viewer showing the spherejax output(s) at `path`, with the readout docked.

    Args:
      path: an output set or a `correct` OUT folder (`layers.output_sets`).
      calibration, raw: the calibration file and raw cube of the output, for uncertainties
        (`capture.CorrectedCapture`); optional.
      show: show the window (False: for scripts and tests).
      viewer: a napari.Viewer to add to, or None for a new one.
    """
    import napari

    layers = read_layers(path, calibration=calibration, raw=raw)
    if not layers:
        raise ValueError(f"{path}: holds no output of spherejax correct (expected N.reflectance.exr or .hdr, or a "
                         "folder of them)")
    if viewer is None:
        viewer = napari.Viewer(title=f"spherejax: {path}", show=show)
    added = [getattr(viewer, f"add_{kind}")(data, **kwargs) for data, kwargs, kind in layers]
    dock_readout(viewer)
    # The image selected, not the regions layer: a click reads a pixel out instead of drawing.
    viewer.layers.selection.active = next((layer for layer in added if layer.visible), added[0])
    return viewer


def readout(viewer, pixel, *, illuminant: str | None = None, uncertainty: bool = True) -> dict:
    """What the viewer's readout shows for `pixel` = (row, col), as a dict
    (`capture.CorrectedCapture.pixel`): reflectance (31,), lab (3,), quality (int),
    quality_names, illuminant, and u_lab (3,) / u_reflectance (31,) where known; delta_e and
    delta_e_u against the widget's reference where one is set.

    With the readout docked (`open_viewer`), the widget shows the pixel too and its illuminant
    is the default; a viewer that opened an output through the plugin's reader alone
    (`viewer.open(path, plugin="spherejax")`) is read from its layers.
    """
    row, col = (int(x) for x in pixel)
    widget = widget_of(viewer)
    if widget is not None:
        if illuminant is not None:
            widget.illuminant.setCurrentText(illuminant)
        return widget.show_pixel(row, col, uncertainty=uncertainty)
    capture: CorrectedCapture | None = capture_of(viewer)
    if capture is None:
        raise ValueError("the viewer holds no spherejax output (expected one opened with plugin='spherejax')")
    return capture.pixel(row, col, illuminant=illuminant, uncertainty=uncertainty)


def screenshot_png(viewer, *, size=SCREENSHOT_SIZE) -> bytes:
    """The whole window (canvas and dock widget) as PNG bytes (RGB), marked as spherejax's (tEXt
    Software = `SCREENSHOT_SOFTWARE`). Off screen, the viewer must not have been shown."""
    from PIL import Image, PngImagePlugin
    from qtpy.QtWidgets import QApplication

    viewer.window.resize(*size)
    for _ in range(3):  # layout, then the canvas's and the plot's paint events
        QApplication.processEvents()
    # The window grabbed as a whole: Qt draws the canvas's OpenGL into it. (canvas_only=True
    # renders the canvas on its own, which comes out blank on Qt's offscreen platform, as a
    # window shown there does: `spherejax view --screenshot` keeps it hidden.)
    pixels = np.asarray(viewer.screenshot(canvas_only=False, flash=False))
    info = PngImagePlugin.PngInfo()
    info.add_text("Software", SCREENSHOT_SOFTWARE)
    out = _bytes_io.BytesIO()
    Image.fromarray(pixels[..., :3].astype(np.uint8), "RGB").save(out, format="PNG", pnginfo=info)
    return out.getvalue()


__all__ = ["dock_readout", "open_viewer", "readout", "screenshot_png", "widget_of"]
