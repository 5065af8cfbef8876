"""Corrected outputs opened as xarray (`spherejax.open_corrected`), lazily, in row chunks.

An input N of `spherejax correct` leaves N.reflectance (OpenEXR in the spectral layout, or ENVI),
N.lab and N.quality.png in OUT. `open_corrected` takes any of those files, or N itself, and
returns one `xarray.Dataset` with the names of `spherejax.labelled`: reflectance (y, x,
wavelength) with wavelength in nm, lab (y, x, lab) and quality (y, x) where their files are
there, and the reflectance file's header as attributes. The pixels are dask arrays of whole-row
chunks read on demand (an EXR's scanlines through OpenImageIO, an ENVI file through a memory
map), so a file larger than memory opens at once and a selection reads only its rows.
"""

from __future__ import annotations

import pathlib

import numpy as np
import OpenImageIO as oiio

from .. import labelled
from . import envi
from .errors import SpherejaxFileError
from .library_messages import complete_image, image_open_problem, image_read_problem, library_path
from .quality_png import read_quality_png
from .spectral_layout import reflective_channels

#: Bytes of one chunk of rows (about): big enough that dask's per-task cost is small, small
#: enough that a few chunks in flight per thread stay far below memory.
CHUNK_BYTES = 32 << 20

_EXPECTED = (
    "an output of spherejax correct: N.reflectance.exr, N.lab.exr, N.quality.png "
    "(or their ENVI .hdr), or N"
)


def _chunk_rows(width: int, channels: int, itemsize: int) -> int:
    return max(1, CHUNK_BYTES // max(1, width * channels * itemsize))


def _image_header(path: pathlib.Path) -> tuple[oiio.ImageSpec, dict]:
    image = oiio.ImageInput.open(library_path(path, _EXPECTED))
    if image is None:
        raise SpherejaxFileError(path, image_open_problem(path, oiio.geterror()), _EXPECTED)
    try:
        spec = image.spec()
        attributes = {a.name: a.value for a in spec.extra_attribs if isinstance(a.value, (str, int, float))}
        return spec, attributes
    finally:
        image.close()


def _read_rows(path: str, row0: int, row1: int, order: tuple[int, ...]) -> np.ndarray:
    """Rows row0:row1 of an image, float32 (rows, W, C), channels in `order`."""
    image = oiio.ImageInput.open(library_path(path, _EXPECTED))
    if image is None:
        raise SpherejaxFileError(path, image_open_problem(path, oiio.geterror()), _EXPECTED)
    try:
        spec = image.spec()
        pixels = image.read_scanlines(0, 0, spec.y + row0, spec.y + row1, 0, 0, spec.nchannels, "float")
        if pixels is None:
            problem = image_read_problem(path, image.geterror(), row0, row1, spec.height, image.format_name())
            shape = (spec.height, spec.width, spec.nchannels)
            raise SpherejaxFileError(path, problem, complete_image(image.format_name(), shape))
    finally:
        image.close()
    pixels = np.asarray(pixels, dtype=np.float32).reshape(row1 - row0, spec.width, spec.nchannels)
    return pixels[..., list(order)]


def _lazy_exr(path: pathlib.Path, spec: oiio.ImageSpec, order: tuple[int, ...]):
    """A dask array (H, W, C) of the image's rows, chunk by chunk of whole rows."""
    import dask
    import dask.array as da

    rows = _chunk_rows(spec.width, len(order), 4)
    blocks = []
    for row0 in range(0, spec.height, rows):
        row1 = min(spec.height, row0 + rows)
        block = dask.delayed(_read_rows, pure=True)(str(path), row0, row1, order)
        blocks.append(da.from_delayed(block, shape=(row1 - row0, spec.width, len(order)), dtype=np.float32))
    return da.concatenate(blocks, axis=0)


def _lazy_quality(path: pathlib.Path, shape: tuple[int, int]):
    """The quality PNG as a dask array (H, W): one task (a PNG is read from its start). Its
    values are the bits: a palette PNG's indices, not the colours OpenImageIO would expand them
    to (`quality_png.read_quality_png`), or an earlier version's grey values."""
    import dask
    import dask.array as da

    spec, _ = _image_header(path)
    if (spec.height, spec.width) != shape:
        raise SpherejaxFileError(path, f"is {spec.height} x {spec.width}", f"the reflectance's {shape[0]} x {shape[1]}")
    return da.from_delayed(dask.delayed(read_quality_png, pure=True)(str(path)), shape=shape, dtype=np.uint8)


def _reflectance_exr(path: pathlib.Path):
    spec, attributes = _image_header(path)
    names = list(spec.channelnames)
    channels = reflective_channels(names)
    if channels is None:
        raise SpherejaxFileError(path, f"has channels {names[:4]}{'...' if len(names) > 4 else ''}",
                                 'reflectance channels named "T.400nm".. (Fichet et al. 2021) or "400nm"..')
    # OpenEXR keeps channels in name order, which is not wavelength order once the digits differ.
    order = tuple(sorted(channels, key=lambda index: channels[index]))
    return _lazy_exr(path, spec, order), [channels[index] for index in order], attributes


def _lab_exr(path: pathlib.Path, shape: tuple[int, int]):
    spec, _ = _image_header(path)
    names = list(spec.channelnames)
    if sorted(names) != sorted(labelled.LAB_LABELS):
        raise SpherejaxFileError(path, f"has channels {names}", 'the channels "L*", "a*", "b*"')
    if (spec.height, spec.width) != shape:
        raise SpherejaxFileError(path, f"is {spec.height} x {spec.width}", f"the reflectance's {shape[0]} x {shape[1]}")
    return _lazy_exr(path, spec, tuple(names.index(label) for label in labelled.LAB_LABELS))


def _stem(path: pathlib.Path) -> pathlib.Path:
    """N from N, N.reflectance.exr, N.lab.hdr, N.quality.png, ..."""
    for suffix in (".reflectance.exr", ".reflectance.hdr", ".reflectance.img", ".lab.exr", ".lab.hdr",
                   ".lab.img", ".quality.png", ".preview.png"):
        if path.name.endswith(suffix):
            return path.with_name(path.name[: -len(suffix)])
    return path


def open_corrected(path):
    """An output of `spherejax correct` as an `xarray.Dataset`, lazily (module docstring).

    Args:
      path: N.reflectance.exr (Fichet et al. 2021 layout, or the older "400nm" names),
        N.reflectance.hdr / .img (ENVI), N.lab.*, N.quality.png, or N; or any spectral EXR or
        ENVI file of reflectance (its own name, no siblings).

    Returns:
      Dataset with reflectance (y, x, wavelength) float32, wavelength in nm; lab (y, x, lab_channel) and
      quality (y, x) uint8 when their files are beside it; attrs: the reflectance file's header
      (spherejax:calibration_checksum, spherejax:source, ...). Pixels are dask arrays; `.load()`
      or `.values` reads them.

    Raises:
      SpherejaxFileError: no reflectance file for `path`, or one that is not a spherejax output.
    """
    path = pathlib.Path(path)
    stem = _stem(path)
    exr, hdr = stem.with_name(stem.name + ".reflectance.exr"), stem.with_name(stem.name + ".reflectance.hdr")
    if stem == path and path.is_file():
        # A spectral image named otherwise ("scan.exr", "scan.hdr"): read as the reflectance.
        exr, hdr = (path, hdr) if path.suffix.lower() == ".exr" else (exr, path.with_suffix(".hdr"))
    if exr.is_file():
        reflectance, wavelengths, attributes = _reflectance_exr(exr)
    elif hdr.is_file():
        reflectance, wavelengths, attributes = envi.open_lazy(hdr, kind="reflectance", chunk_bytes=CHUNK_BYTES)
    else:
        raise SpherejaxFileError(path, "has no reflectance file beside it (N.reflectance.exr or .hdr)", _EXPECTED)
    shape = tuple(reflectance.shape[:2])
    arrays = {"reflectance": reflectance}
    lab_exr, lab_hdr = stem.with_name(stem.name + ".lab.exr"), stem.with_name(stem.name + ".lab.hdr")
    if lab_exr.is_file():
        arrays["lab"] = _lab_exr(lab_exr, shape)
    elif lab_hdr.is_file():
        arrays["lab"] = envi.open_lazy(lab_hdr, kind="lab", chunk_bytes=CHUNK_BYTES, shape=shape)[0]
    quality = stem.with_name(stem.name + ".quality.png")
    if quality.is_file():
        arrays["quality"] = _lazy_quality(quality, shape)
    return labelled.dataset(arrays, attrs=attributes, wavelengths_nm=wavelengths)


__all__ = ["CHUNK_BYTES", "open_corrected"]
