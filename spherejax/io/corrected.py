"""Corrected outputs opened as xarray (`spherejax.open_corrected`), lazily, in row chunks.

An input N of `spherejax correct` leaves N.reflectance (OpenEXR in the spectral layout, or ENVI),
N.lab and N.quality.png in OUT. `open_corrected` takes any of those files, or N itself, and
returns one `xarray.Dataset` with the names of `spherejax.labelled`: reflectance (y, x,
wavelength) with wavelength in nm, lab (y, x, lab) and quality (y, x) where their files are
there, and the reflectance file's header as attributes. The pixels are dask arrays of whole-row
chunks read on demand (an EXR's scanlines through OpenImageIO, an ENVI file through a memory
map), so a file larger than memory opens at once and a selection reads only its rows.

The files of one Dataset must be one correction's outputs: a reflectance beside another input's
Lab or quality mask (copied there, or left by another run) would give a Dataset whose variables
describe different pixels. `spherejax correct` writes into every output of an input (the EXRs'
and ENVI headers' attributes, the PNGs' tEXt chunks) one `OUTPUT_SET_ATTRIBUTE`, a digest of the
input's SHA-256, the calibration's checksum and the software version (`output_set_id`), and
`open_corrected` refuses, in one line naming both files, a Lab, quality or preview file beside
the reflectance that carries another one. Beyond it, the attributes the reflectance and the Lab
both carry must agree: the input's SHA-256, the calibration's checksum, the software version and
the Lab illuminant (a Lab made under another illuminant than the reflectance's file names would
be labelled wrongly; the reflectance, quality mask and preview do not depend on it).

Outputs of versions that wrote no output set are still read, and a file that carries none is
checked for what it carries: the EXR and ENVI Lab of every version carry the attributes above,
so a Lab of another input or calibration is refused all the same; a quality mask or preview
without attributes is checked for its size only.
"""

from __future__ import annotations

import hashlib
import json
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


#: The attribute naming the correction an output belongs to (module docstring): the same value in
#: every output of one input of one run of `spherejax correct`.
OUTPUT_SET_ATTRIBUTE = "spherejax:output_set"
#: What must agree between the files of one Dataset wherever both carry it, beside
#: `OUTPUT_SET_ATTRIBUTE` (the Lab illuminant most of all: the output set leaves it out).
_SHARED_ATTRIBUTES = ("spherejax:input_sha256", "spherejax:calibration_checksum", "spherejax:illuminant",
                      "spherejax:software_version")


def output_set_id(*, input_sha256: str, calibration_checksum: str, software_version: str) -> str:
    """The `OUTPUT_SET_ATTRIBUTE` of an input's outputs: "sha256:" and the SHA-256 of what makes
    them (the input's bytes, the calibration, the software), so that the outputs of one
    correction share it and a rerun writes the same bytes. The Lab illuminant is left out: the
    reflectance, quality and preview do not depend on it (the Lab's own attribute names it)."""
    identity = json.dumps({"input_sha256": input_sha256, "calibration_checksum": calibration_checksum,
                           "software_version": software_version}, sort_keys=True)
    return "sha256:" + hashlib.sha256(identity.encode("utf-8", "surrogateescape")).hexdigest()


def _require_one_set(reflectance: pathlib.Path, ours: dict, other: pathlib.Path, theirs: dict) -> None:
    """Refuse `other` (a Lab, quality or preview file beside the reflectance) unless it is an
    output of the same correction (module docstring)."""
    expected = f"the outputs of one input from one run of spherejax correct, as {reflectance.name} is"
    for name in (OUTPUT_SET_ATTRIBUTE, *_SHARED_ATTRIBUTES):  # what both carry (older files carry less)
        if name in ours and name in theirs and ours[name] != theirs[name]:
            problem = (f"is not an output of the correction {reflectance} is from: its {name} is "
                       f"{theirs[name]}, the reflectance's {ours[name]}")
            raise SpherejaxFileError(other, problem, expected)


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


def _png_attributes(path: pathlib.Path, shape: tuple[int, int]) -> dict:
    """A quality or preview PNG's attributes (its tEXt chunks), once its size is checked."""
    spec, attributes = _image_header(path)
    if (spec.height, spec.width) != shape:
        raise SpherejaxFileError(path, f"is {spec.height} x {spec.width}", f"the reflectance's {shape[0]} x {shape[1]}")
    return attributes


def _lazy_quality(path: pathlib.Path, shape: tuple[int, int]):
    """The quality PNG, of (H, W) `shape` (checked by `_png_attributes`), as a dask array: one
    task (a PNG is read from its start). Its values are the bits: a palette PNG's indices, not
    the colours OpenImageIO would expand them to (`quality_png.read_quality_png`), or an earlier
    version's grey values."""
    import dask
    import dask.array as da

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
    """(the Lab EXR as a dask array (H, W, 3), its attributes)."""
    spec, attributes = _image_header(path)
    names = list(spec.channelnames)
    if sorted(names) != sorted(labelled.LAB_LABELS):
        raise SpherejaxFileError(path, f"has channels {names}", 'the channels "L*", "a*", "b*"')
    if (spec.height, spec.width) != shape:
        raise SpherejaxFileError(path, f"is {spec.height} x {spec.width}", f"the reflectance's {shape[0]} x {shape[1]}")
    return _lazy_exr(path, spec, tuple(names.index(label) for label in labelled.LAB_LABELS)), attributes


def output_stem(path) -> pathlib.Path:
    """N from N, N.reflectance.exr, N.lab.hdr, N.quality.png, N.preview.png, ..."""
    path = pathlib.Path(path)
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
      (spherejax:calibration_checksum, spherejax:source, spherejax:output_set, ...). Pixels are
      dask arrays; `.load()` or `.values` reads them.

    Raises:
      SpherejaxFileError: no reflectance file for `path`, or one that is not a spherejax output;
        a Lab, quality or preview file beside it that is not an output of the same correction
        (module docstring: another `OUTPUT_SET_ATTRIBUTE`, or another input, calibration,
        software version or illuminant named in both), naming both files.
    """
    path = pathlib.Path(path)
    stem = output_stem(path)
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
    reflectance_path = exr if exr.is_file() else hdr
    arrays = {"reflectance": reflectance}
    lab_exr, lab_hdr = stem.with_name(stem.name + ".lab.exr"), stem.with_name(stem.name + ".lab.hdr")
    if lab_exr.is_file():
        arrays["lab"], lab_attributes = _lab_exr(lab_exr, shape)
        _require_one_set(reflectance_path, attributes, lab_exr, lab_attributes)
    elif lab_hdr.is_file():
        arrays["lab"], _, lab_attributes = envi.open_lazy(lab_hdr, kind="lab", chunk_bytes=CHUNK_BYTES, shape=shape)
        _require_one_set(reflectance_path, attributes, lab_hdr, lab_attributes)
    quality, preview = (stem.with_name(stem.name + suffix) for suffix in (".quality.png", ".preview.png"))
    if quality.is_file():
        _require_one_set(reflectance_path, attributes, quality, _png_attributes(quality, shape))
        arrays["quality"] = _lazy_quality(quality, shape)
    if preview.is_file():  # not in the Dataset, but one of the correction's outputs all the same
        _require_one_set(reflectance_path, attributes, preview, _png_attributes(preview, shape))
    return labelled.dataset(arrays, attrs=attributes, wavelengths_nm=wavelengths)


def read_preview(path, shape: tuple[int, int]) -> np.ndarray:
    """The sRGB preview N.preview.png of an output of (H, W) `shape`, (H, W, 3) uint8.

    Raises:
      SpherejaxFileError: not an 8-bit RGB PNG of that size, or damaged pixel data.
    """
    path = pathlib.Path(path)
    expected = f"an RGB preview PNG of the reflectance's {shape[0]} x {shape[1]}"
    image = oiio.ImageInput.open(library_path(path, expected))
    if image is None:
        raise SpherejaxFileError(path, image_open_problem(path, oiio.geterror()), expected)
    try:
        spec = image.spec()
        if (spec.height, spec.width) != tuple(shape) or spec.nchannels < 3:
            raise SpherejaxFileError(path, f"is {spec.height} x {spec.width} with {spec.nchannels} channels", expected)
        pixels = image.read_image(0, 0, 0, 3, oiio.UINT8)
        if pixels is None:
            raise SpherejaxFileError(path, f"cannot be read: {image.geterror()}", expected)
    finally:
        image.close()
    return np.ascontiguousarray(np.asarray(pixels, np.uint8).reshape(spec.height, spec.width, 3))


__all__ = ["CHUNK_BYTES", "OUTPUT_SET_ATTRIBUTE", "open_corrected", "output_set_id", "output_stem", "read_preview"]
