"""The plugin's dock widget: a pixel's spectrum, L*a*b*, quality bits and ΔE00, and a region's
`measure` statistics with CSV and CGATS export.

Pixels: the cursor's pixel as it moves (values from the files only: cheap), and a click's pixel
with its propagated uncertainty where the capture has raw frames and a noise model
(`CorrectedCapture.pixel`). The plot is the reflectance (31 wavelengths) with a band of ± U
(k = 2, as `spherejax measure` reports) where the uncertainty is known, and the last measured
region's mean spectrum beside it.

Regions: a Shapes layer "regions" (added with the widget); each rectangle, polygon or ellipse
drawn there is a region, measured as `spherejax.measure` does (`CorrectedCapture.region`); the
widget shows the last one, and Export writes all of them as `spherejax measure` does
(`outputs`). Names: "region 1", "region 2", ... in drawing order.

Reference for ΔE00: L,a,b typed in, the clicked pixel, or the last region.
"""

from __future__ import annotations

import dataclasses
import pathlib
import weakref

import numpy as np
from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
from matplotlib.figure import Figure
from qtpy.QtCore import QTimer
from qtpy.QtWidgets import (
    QComboBox, QFileDialog, QFormLayout, QHBoxLayout, QLabel, QLineEdit, QPushButton, QVBoxLayout, QWidget,
)

from ..measurement_files import COVERAGE_FACTOR, RegionResult
from .capture import ILLUMINANTS, CorrectedCapture, Reference
from .layers import METADATA_KEY
from .outputs import write_region_files

#: Name of the Shapes layer whose shapes are the regions.
REGIONS_LAYER = "regions"
#: Name of the Points layer marking the pixel read out (a clicked one, or `readout`'s).
PIXEL_LAYER = "readout pixel"
#: The readout widget of each viewer (`widget_of`): id(viewer) -> weak reference to it. Set by the
#: widget itself, whoever made it (`window.dock_readout`, or napari's Plugins menu through npe2).
_WIDGETS: dict[int, weakref.ref] = {}


def widget_of(viewer) -> ReadoutWidget | None:
    """The readout widget made for `viewer` (the last one), or None."""
    ref = _WIDGETS.get(id(viewer))
    widget = None if ref is None else ref()
    return widget if widget is not None and widget.viewer is viewer else None


def capture_of(viewer) -> CorrectedCapture | None:
    """The capture the viewer's readout is of: the selected layer's, else the topmost layer's
    that has one (`layers.METADATA_KEY`); None when no layer holds a spherejax output."""
    active = viewer.layers.selection.active
    if active is not None and METADATA_KEY in active.metadata:
        return active.metadata[METADATA_KEY]
    for layer in reversed(viewer.layers):
        if METADATA_KEY in layer.metadata:
            return layer.metadata[METADATA_KEY]
    return None


def pixel_at(viewer, position) -> tuple[int, int] | None:
    """(row, col) of a world position (the last two coordinates: y, x), or None outside."""
    capture = capture_of(viewer)
    if capture is None or position is None:
        return None
    row, col = (int(np.floor(x + 0.5)) for x in tuple(position)[-2:])
    height, width = capture.shape
    return (row, col) if 0 <= row < height and 0 <= col < width else None


class ReadoutWidget(QWidget):
    """The dock widget (module docstring). `napari_viewer`: the viewer it reads."""

    def __init__(self, napari_viewer, parent=None):
        super().__init__(parent)
        # napari hands a plugin's widget a proxy of the viewer (its public API only): the viewer
        # itself is the one `widget_of` and `readout` are given.
        napari_viewer = getattr(napari_viewer, "__wrapped__", napari_viewer)
        self.viewer = napari_viewer
        _WIDGETS[id(napari_viewer)] = weakref.ref(self)
        self.current: dict | None = None  # the last pixel's readout
        self.reference: Reference | None = None
        self.regions: list[RegionResult] = []
        self._hover: tuple[int, int] | None = None

        self.title = QLabel("click a pixel, or draw a region in the 'regions' layer")
        self.title.setWordWrap(True)
        self.figure = Figure(figsize=(4.0, 2.8), dpi=100, layout="constrained")
        self.canvas = FigureCanvasQTAgg(self.figure)
        self.axes = self.figure.add_subplot()
        self.illuminant = QComboBox()
        self.illuminant.addItems(ILLUMINANTS)
        capture = capture_of(napari_viewer)
        if capture is not None and capture.file_illuminant in ILLUMINANTS:
            self.illuminant.setCurrentText(capture.file_illuminant)
        self.illuminant.currentTextChanged.connect(self._illuminant_changed)
        self.lab = QLabel("-")
        self.quality = QLabel("-")
        self.delta_e = QLabel("-")
        self.reference_text = QLineEdit()
        self.reference_text.setPlaceholderText("L,a,b")
        self.reference_text.returnPressed.connect(self._typed_reference)
        use_pixel, use_region = QPushButton("this pixel"), QPushButton("last region")
        use_pixel.clicked.connect(self.use_pixel_as_reference)
        use_region.clicked.connect(self.use_region_as_reference)
        self.region_text = QLabel("-")
        self.region_text.setWordWrap(True)
        self.status = QLabel("" if capture is None else capture.describe())
        self.status.setWordWrap(True)
        export_csv, export_cgats = QPushButton("export CSV..."), QPushButton("export CGATS...")
        export_csv.clicked.connect(lambda: self._export_dialog("csv"))
        export_cgats.clicked.connect(lambda: self._export_dialog("cgats"))

        form = QFormLayout()
        form.addRow("illuminant", self.illuminant)
        form.addRow("L*a*b*", self.lab)
        form.addRow("quality", self.quality)
        reference_row = QHBoxLayout()
        for widget in (self.reference_text, use_pixel, use_region):
            reference_row.addWidget(widget)
        form.addRow("reference", reference_row)
        form.addRow("ΔE00", self.delta_e)
        form.addRow("region", self.region_text)
        export_row = QHBoxLayout()
        export_row.addWidget(export_csv)
        export_row.addWidget(export_cgats)
        layout = QVBoxLayout(self)
        layout.addWidget(self.title)
        layout.addWidget(self.canvas)
        layout.addLayout(form)
        layout.addLayout(export_row)
        layout.addWidget(self.status)
        layout.addStretch(1)

        # The cursor's pixel is shown once the cursor rests (20 ms), not at every motion event.
        self._hover_timer = QTimer(self)
        self._hover_timer.setSingleShot(True)
        self._hover_timer.setInterval(20)
        self._hover_timer.timeout.connect(self._show_hover)
        napari_viewer.cursor.events.position.connect(self._cursor_moved)
        napari_viewer.mouse_drag_callbacks.append(self._clicked)
        self.regions_layer = self._regions_layer()
        self.regions_layer.events.data.connect(self._regions_changed)
        self._draw()

    # -- pixels -----------------------------------------------------------------------------
    def show_pixel(self, row: int, col: int, *, uncertainty: bool = True) -> dict | None:
        """Read out (row, col) and show it; returns the readout (`CorrectedCapture.pixel`)."""
        capture = capture_of(self.viewer)
        if capture is None:
            return None
        self.current = capture.pixel(row, col, illuminant=self.illuminant.currentText(), uncertainty=uncertainty,
                                     reference=self.reference)
        if uncertainty:  # a click or `readout`, not the cursor passing by: marked on the image
            self._mark(row, col)
        self._show_current()
        return self.current

    def _mark(self, row: int, col: int) -> None:
        layer = next((layer for layer in self.viewer.layers if layer.name == PIXEL_LAYER), None)
        if layer is None:
            active = self.viewer.layers.selection.active
            self.viewer.add_points([[row, col]], name=PIXEL_LAYER, size=7, face_color="transparent",
                                   border_color="red", border_width=0.25, ndim=2)
            self.viewer.layers.selection.active = active  # a click keeps reading pixels out
        else:
            layer.data = np.array([[row, col]], float)

    def _show_current(self) -> None:
        r = self.current
        self.title.setText(f"pixel (row {r['row']}, col {r['col']})")
        lab, u = r["lab"], r.get("u_lab")
        if not np.all(np.isfinite(lab)):
            self.lab.setText("none (flagged)")
        elif u is None:
            self.lab.setText("{:.2f}, {:.2f}, {:.2f}".format(*lab))
        else:
            self.lab.setText("  ".join(f"{v:.2f} ± {COVERAGE_FACTOR * e:.2f}" for v, e in zip(lab, u))
                             + f"  (U, k = {COVERAGE_FACTOR:g})")
        self.quality.setText(f"{r['quality']}: " + (", ".join(r["quality_names"]) or "good"))
        if "delta_e" in r:
            u_text = "" if not np.isfinite(r["delta_e_u"]) else f" ± {COVERAGE_FACTOR * r['delta_e_u']:.2f}"
            self.delta_e.setText(f"{r['delta_e']:.2f}{u_text} against {r['reference']}")
        else:
            self.delta_e.setText("-")
        self._draw()

    def _cursor_moved(self, event=None) -> None:
        self._hover = pixel_at(self.viewer, self.viewer.cursor.position)
        if self._hover is not None:
            self._hover_timer.start()

    def _show_hover(self) -> None:
        if self._hover is not None:
            self.show_pixel(*self._hover, uncertainty=False)

    def _clicked(self, viewer, event):
        """napari's drag callback: a press and release without a move between them (a click,
        not the start of a pan) in pan-zoom mode reads the pressed pixel out."""
        if event.type != "mouse_press" or getattr(viewer.layers.selection.active, "mode", "pan_zoom") != "pan_zoom":
            return
        pixel = pixel_at(viewer, event.position)
        yield
        moved = False
        while event.type == "mouse_move":
            moved = True
            yield
        if pixel is not None and not moved:
            self.show_pixel(*pixel)

    def _illuminant_changed(self, _name: str) -> None:
        if self.current is not None:
            self.show_pixel(self.current["row"], self.current["col"])
        if self.regions:
            self._regions_changed()

    # -- reference --------------------------------------------------------------------------
    def set_reference(self, reference: Reference | None) -> None:
        """Measure ΔE00 against `reference` from now on (None: no ΔE00)."""
        self.reference = reference
        if self.current is not None:
            self.show_pixel(self.current["row"], self.current["col"])
        if self.regions:
            self.regions = [dataclasses.replace(r, **self._against_reference(r.measurement)) for r in self.regions]
            self._show_region()

    def _typed_reference(self) -> None:
        try:
            self.set_reference(Reference.typed(self.reference_text.text()))
        except ValueError as error:
            self.status.setText(str(error))

    def use_pixel_as_reference(self) -> None:
        """The last clicked pixel as the reference."""
        try:
            if self.current is None:
                raise ValueError("no pixel yet: click one first")
            self.set_reference(Reference.of_pixel(self.current))
        except ValueError as error:
            self.status.setText(str(error))

    def use_region_as_reference(self) -> None:
        """The last region as the reference."""
        if not self.regions:
            self.status.setText("no region yet: draw one in the 'regions' layer first")
            return
        self.set_reference(Reference.of_region(self.regions[-1].name, self.regions[-1].measurement))

    # -- regions ----------------------------------------------------------------------------
    def _regions_layer(self):
        from napari.layers import Shapes

        for layer in self.viewer.layers:
            if layer.name == REGIONS_LAYER and isinstance(layer, Shapes):
                return layer
        return self.viewer.add_shapes(name=REGIONS_LAYER, ndim=2, face_color="transparent", edge_color="yellow",
                                      edge_width=2)

    def _against_reference(self, measured) -> dict:
        """A region's delta_e and delta_e_u against the reference (None without one)."""
        if self.reference is None:
            return {"delta_e": None, "delta_e_u": None}
        delta_e, u = measured.delta_e(self.reference.lab, self.reference.covariance)
        return {"delta_e": delta_e, "delta_e_u": u}

    def measure_regions(self) -> list[RegionResult]:
        """Measure every shape of the regions layer (module docstring); shown and returned."""
        capture = capture_of(self.viewer)
        layer = self.regions_layer
        results = []
        if capture is not None and len(layer.data):
            masks = np.asarray(layer.to_masks(mask_shape=capture.shape), bool)
            for number, mask in enumerate(masks, start=1):
                if not mask.any():
                    continue
                rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
                rect = (int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1)
                measured = capture.region(mask, illuminant=self.illuminant.currentText())
                results.append(RegionResult(f"region {number}", rect, measured, **self._against_reference(measured)))
        self.regions = results
        self._show_region()
        return results

    def _regions_changed(self, event=None) -> None:
        try:
            self.measure_regions()
        except ValueError as error:  # a region with no good pixel
            self.regions = []
            self.region_text.setText(str(error))
            self._draw()

    def _show_region(self) -> None:
        if not self.regions:
            self.region_text.setText("-")
            self._draw()
            return
        r = self.regions[-1]
        m = r.measurement
        u = m.lab_u
        lab = ("{:.2f}, {:.2f}, {:.2f}".format(*m.lab) if u is None else
               "  ".join(f"{v:.2f} ± {COVERAGE_FACTOR * e:.2f}" for v, e in zip(m.lab, u)))
        text = f"{r.name}: {m.pixels} pixels ({m.excluded} flagged, left out), L*a*b* {lab} ({m.illuminant})"
        if r.delta_e is not None:
            u_text = "" if not np.isfinite(r.delta_e_u) else f" ± {COVERAGE_FACTOR * r.delta_e_u:.2f}"
            text += f", ΔE00 {r.delta_e:.2f}{u_text}"
        self.region_text.setText(text)
        self._draw()

    def export(self, *, csv_path=None, cgats_path=None) -> list[pathlib.Path]:
        """Write the regions as `spherejax measure` does (`outputs.write_region_files`)."""
        capture = capture_of(self.viewer)
        results = self.measure_regions()
        inputs = {"the reflectance": capture.reflectance_path, "the raw cube": capture.raw_path,
                  "the calibration": capture.calibration_path, "the preview": capture.preview_path}
        written = write_region_files(results, inputs=inputs, input_path=capture.raw_path or capture.reflectance_path,
                                     instrument_id=capture.instrument_id, csv_path=csv_path, cgats_path=cgats_path)
        self.status.setText("written: " + ", ".join(map(str, written)))
        return written

    def _export_dialog(self, kind: str) -> None:
        suffix = {"csv": "CSV (*.csv)", "cgats": "CGATS (*.txt *.cgats *.cgt)"}[kind]
        path, _ = QFileDialog.getSaveFileName(self, f"Export regions as {kind.upper()}", "", suffix)
        if not path:
            return
        try:
            self.export(**{f"{kind}_path": path})
        except (ValueError, OSError) as error:  # SpherejaxFileError is an OSError: its one line
            self.status.setText(str(error))

    # -- the plot ---------------------------------------------------------------------------
    def _draw(self) -> None:
        axes = self.axes
        axes.clear()
        axes.set_xlabel("wavelength (nm)")
        axes.set_ylabel("reflectance")
        capture = capture_of(self.viewer)
        top = 1.0
        if self.current is not None:
            nm, r = self.current["wavelength_nm"], self.current["reflectance"]
            axes.plot(nm, r, color="tab:blue", label=f"pixel ({self.current['row']}, {self.current['col']})")
            u = self.current.get("u_reflectance")
            if u is not None:
                axes.fill_between(nm, r - COVERAGE_FACTOR * u, r + COVERAGE_FACTOR * u, color="tab:blue", alpha=0.25,
                                  label=f"± U (k = {COVERAGE_FACTOR:g})")
            if np.any(np.isfinite(r)):
                top = max(top, float(np.nanmax(r)))
        if self.regions and capture is not None:
            m = self.regions[-1].measurement
            axes.plot(capture.wavelengths_nm, m.reflectance, color="tab:orange", label=self.regions[-1].name)
            top = max(top, float(np.max(m.reflectance)))
        axes.set_xlim(400, 700)
        axes.set_ylim(0, 1.05 * top)
        if axes.lines:
            axes.legend(loc="upper left", fontsize="small")
        self.canvas.draw_idle()


__all__ = ["PIXEL_LAYER", "REGIONS_LAYER", "ReadoutWidget", "capture_of", "pixel_at", "widget_of"]
