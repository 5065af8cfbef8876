"""The napari reader of the plugin (spherejax/napari.yaml): spherejax's outputs as layers.

`napari_get_reader(path)` accepts an output of `spherejax correct` (N.reflectance.exr, the ENVI
N.reflectance.hdr / .img, N.lab.*, N.quality.png, N.preview.png, or N) and a folder holding such
outputs (a `correct` OUT folder, searched recursively), and returns `read_layers`, which gives
each output set three layers, bottom to top:

  N reflectance  image (wavelength, y, x), the cube as a dask array through `open_corrected`,
                 nothing read until shown (hidden at first, contrast limits 0..1 given so that
                 napari computes none): a slider steps through the 31 wavelengths;
  N preview      the sRGB preview (N.preview.png), shown; where there is no preview, the
                 reflectance layer is shown instead;
  N quality      labels: the quality bits, each value in the colour of its highest bit as the
                 quality PNG's palette shows it (`io.quality_png.PALETTE`), good pixels (0)
                 transparent; the layer's features name the bits of each value, so napari's
                 status bar says "SATURATED | BELOW_DARK" under the cursor.

Every layer's metadata["spherejax"] is the `CorrectedCapture` (`viewer.capture`) the readout
and the dock widget read pixels and regions from.
"""

from __future__ import annotations

import pathlib

import numpy as np

from ..io.corrected import output_stem
from ..io.quality_png import PALETTE
from .capture import CorrectedCapture, quality_names

#: Names of a reflectance file, by which a folder's output sets are found.
_REFLECTANCE_SUFFIXES = (".reflectance.exr", ".reflectance.hdr")
#: The file names the reader takes (a folder aside).
_OUTPUT_SUFFIXES = (*_REFLECTANCE_SUFFIXES, ".reflectance.img", ".lab.exr", ".lab.hdr", ".lab.img",
                    ".quality.png", ".preview.png")
#: Key of a layer's metadata holding its `CorrectedCapture`.
METADATA_KEY = "spherejax"


def output_sets(path) -> list[pathlib.Path]:
    """The reflectance files of the output sets `path` names: its own set, or each set in a
    folder (recursively, in name order); [] for anything else."""
    path = pathlib.Path(path)
    if path.is_dir():
        found = sorted(file for suffix in _REFLECTANCE_SUFFIXES for file in path.rglob("*" + suffix) if file.is_file())
        # An ENVI set has both files; one set per stem, its EXR where both formats are there.
        by_stem = {}
        for file in found:
            by_stem.setdefault(output_stem(file), file)
        return list(by_stem.values())
    if not path.name.endswith(_OUTPUT_SUFFIXES):
        return []
    stem = output_stem(path)
    return [file for suffix in _REFLECTANCE_SUFFIXES if (file := stem.with_name(stem.name + suffix)).is_file()][:1]


def napari_get_reader(path):
    """npe2's reader hook: a reader of the output sets `path` (or each of a list) names, else
    None (napari then tries its other readers). The sets found here are the ones it reads (a
    folder is searched once)."""
    paths = path if isinstance(path, (list, tuple)) else [path]
    found = [output_sets(p) for p in paths]
    if not paths or not all(found):
        return None
    sets = [reflectance for each in found for reflectance in each]
    return lambda _path: _layers_of(sets)


def quality_colormap():
    """napari's DirectLabelColormap of the quality bits: the quality PNG's palette, 0 transparent."""
    from napari.utils.colormaps import DirectLabelColormap

    colours = {None: np.zeros(4, np.float32), 0: np.zeros(4, np.float32)}
    for value in range(1, 256):
        colours[value] = np.array([*(PALETTE[value] / 255.0), 1.0], np.float32)
    return DirectLabelColormap(color_dict=colours)


def quality_features() -> dict:
    """The Labels layer's features: for each value 0..255, the names of its bits."""
    values = np.arange(256)
    return {"index": values, "flags": [" | ".join(quality_names(v)) or "good" for v in values]}


def capture_layers(capture: CorrectedCapture) -> list[tuple]:
    """napari LayerData tuples (data, kwargs, layer type) of one output set (module docstring)."""
    name = capture.stem.name
    metadata = {METADATA_KEY: capture}
    preview = capture.preview
    reflectance = capture.dataset["reflectance"].data.transpose(2, 0, 1)  # lazy: (wavelength, y, x)
    layers = [(reflectance, {
        "name": f"{name} reflectance", "visible": preview is None, "contrast_limits": (0.0, 1.0),
        "colormap": "gray", "metadata": metadata,
    }, "image")]
    if preview is not None:
        layers.append((preview, {"name": f"{name} preview", "rgb": True, "metadata": metadata}, "image"))
    layers.append((capture.quality, {
        "name": f"{name} quality", "colormap": quality_colormap(), "features": quality_features(),
        "opacity": 0.7, "metadata": metadata,
    }, "labels"))
    return layers


def read_layers(path, *, calibration=None, raw=None) -> list[tuple]:
    """The layers of every output set `path` names (`output_sets`), each set's `capture_layers`.

    calibration, raw: given to each `CorrectedCapture` (for uncertainties); only with one set.
    """
    paths = path if isinstance(path, (list, tuple)) else [path]
    sets = [found for p in paths for found in output_sets(p)]
    if (calibration is not None or raw is not None) and len(sets) != 1:
        raise ValueError(f"{paths[0]}: holds {len(sets)} output sets; a calibration and raw cube go with one")
    return _layers_of(sets, calibration=calibration, raw=raw)


def _layers_of(sets, *, calibration=None, raw=None) -> list[tuple]:
    """`capture_layers` of each reflectance file in `sets`, in order."""
    return [layer for reflectance_file in sets
            for layer in capture_layers(CorrectedCapture(reflectance_file, calibration=calibration, raw=raw))]


__all__ = ["METADATA_KEY", "capture_layers", "napari_get_reader", "output_sets", "quality_colormap",
           "quality_features", "read_layers"]
