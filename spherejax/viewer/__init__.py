"""Looking at what was measured: spherejax's outputs in napari (install the `viewer` extra).

napari is the Python ecosystem's n-dimensional image viewer; this package is spherejax's plugin
for it (manifest spherejax/napari.yaml, plugin name "spherejax") and what `spherejax view` runs.

Modules:
  capture      a corrected output set, its raw cube and calibration: a pixel's readout and a
               region's measurement, without Qt (`CorrectedCapture`);
  layers       the napari reader: reflectance (lazy), preview and quality mask as layers;
  widget       the dock widget: spectrum, L*a*b*, quality bits, ΔE00, region statistics, export;
  outputs      the files it writes: regions' CSV and CGATS as `spherejax measure` writes them,
               the screenshot PNG;
  window       a viewer with the widget docked, `readout`, the window as PNG;
  offscreen    Qt and OpenGL off screen, with an Xvfb of its own where there is no display.

Public: `readout(viewer, (row, col))` -> dict (reflectance (31,), lab (3,), quality int, and
u_lab (3,) where the calibration's noise model and the raw cube are given) and `open_viewer`.
`capture`, `outputs` and `offscreen` import neither Qt nor napari; the others need the extra.
"""

from __future__ import annotations


def __getattr__(name):
    # Lazy: `spherejax.viewer.capture` stays importable without Qt; napari loads on first use.
    if name in ("readout", "open_viewer", "dock_readout", "screenshot_png"):
        from . import window

        return getattr(window, name)
    raise AttributeError(f"module 'spherejax.viewer' has no attribute {name!r}")


__all__ = ["dock_readout", "open_viewer", "readout", "screenshot_png"]
