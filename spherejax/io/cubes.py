"""Cubes (inputs of `spherejax correct`: a frame TIFF, a multi-page TIFF, an OpenEXR, or band
files) read by rows, and the corrected outputs: float32 OpenEXR and 8-bit PNG.

How a cube's channels map to bands (`open_cube`):

- Channels that each name a wavelength, "<nm>nm" ("400nm", "420 nm", any case) or the spectral
  layout's "T.<nm>nm" ("T.400nm", `spectral_layout`), are the bands of those wavelengths, in any
  order in the file, read back in band order (the calibration's, else increasing wavelength).
  They must be the calibration's bands, and no wavelength may be named twice.
- Channels of a TIFF that do not all name a wavelength are the bands in the order they are
  stored: a TIFF keeps the order they were written in (`write_frame`'s names, other software's
  "R", "G", "B" or "channel0"...), as do the pages of a multi-page TIFF.
- Channels of an OpenEXR that do not all name a wavelength are refused (one channel excepted):
  OpenEXR stores channels sorted by name, so c0..c15 read back as c0, c1, c10..c15, c2..c9, and
  the order they were written in is lost. A cube written with a name twice ("400nm" twice) is
  one of them: OpenImageIO writes "channel1" (its index) in place of the second, as it does for
  an empty name.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import re
from collections.abc import Sequence

import numpy as np
import OpenImageIO as oiio
from .. import jsontext
from .documents import _describe_bands
from .errors import SpherejaxFileError
from .library_messages import complete_image, image_open_problem, image_read_problem, library_path
from .frames import (
    AtomicImageWriter, _FRAME_EXPECTED, _frame_names_and_attributes, _open_checked_frame, _refuse_undecodable_text,
    _require_frame_shape, _spec_shape, require_image_file,
)
from .spectral_layout import wavelengths_of_channels
from .exr_uncompressed import UncompressedExrWriter, takes_attributes


_CUBE_EXPECTED = (
    "a cube: a 16-bit TIFF with one channel or one page per band, or an OpenEXR with one "
    "float channel per band"
)
_BAND_NAME = re.compile(r"(\d+)\s*nm", re.IGNORECASE)
_NAMED_BANDS_EXPECTED = (
    'one channel per band, each named by its own wavelength: "400nm" or "T.400nm"'
)
#: OpenImageIO's name for a channel whose name repeats one before it (or is empty).
_RENAMED_CHANNEL = re.compile(r"channel\d+")
#: At most this many channel names are listed in a message, each cut to this many characters.
_NAMES_SHOWN = 40
_NAME_LENGTH_SHOWN = 40


def _wavelength_of_name(name) -> float | None:
    """The wavelength in nm a channel name gives, "<nm>nm" or "T.<nm>nm", else None (also for
    a number too large to be finite, or one the layout's parser fails on: "T.e5nm", "T.0Hz")."""
    text = str(name).strip()
    match = _BAND_NAME.fullmatch(text)
    try:
        nm = float(match.group(1)) if match is not None else (wavelengths_of_channels([text]) or [None])[0]
    except (ValueError, ArithmeticError):
        return None
    return nm if nm is not None and nm < float("inf") else None


def band_centres_from_names(names: Sequence[str]) -> list[int | float] | None:
    """Band centres in nm if every name gives one, "<integer>nm" ("400nm", "420 nm") or the
    spectral layout's "T.<nm>nm" ("T.400nm", "T.412,5nm"), else None; whole numbers as int."""
    if not names:
        return None
    centres = []
    for name in names:
        nm = _wavelength_of_name(name)
        if nm is None:
            return None
        centres.append(int(nm) if nm.is_integer() else nm)
    return centres


def _show_names(names: Sequence[str]) -> str:
    """Channel names for a message, in the file's order: "c0, c1, c10" (quoted where needed)."""
    shown = []
    for name in names:
        name = name if len(name) <= _NAME_LENGTH_SHOWN else name[: _NAME_LENGTH_SHOWN - 3] + "..."
        shown.append(name if re.fullmatch(r"[\w.,*+-]+", name) else json.dumps(name))
    if len(shown) > _NAMES_SHOWN:
        shown = [*shown[:_NAMES_SHOWN], f"... ({len(shown)} in all)"]
    return ", ".join(shown)


def _show_nm(nm: float) -> str:
    return f"{nm:g}"


def _channel_names(image: oiio.ImageInput) -> list[str]:
    """Channel names as stored: a TIFF keeps them only in `write_frame`'s ImageDescription JSON.

    Only a TIFF's JSON is read: the channels of an OpenEXR are sorted by name, so names in the
    order they were written (a converter such as oiiotool copies the ImageDescription) would put
    the wrong name on each channel.
    """
    spec = image.spec()
    if image.format_name() == "tiff":
        try:
            stored = jsontext.loads(spec.get_string_attribute("ImageDescription"))["channel_names"]
            if isinstance(stored, list) and len(stored) == spec.nchannels:
                return [str(name) for name in stored]
        except (ValueError, TypeError, KeyError, RecursionError):  # not write_frame's JSON
            pass
    return list(spec.channelnames)


def _band_order(path, names: Sequence[str], sorted_by_name: bool, band_centres_nm) -> np.ndarray | None:
    """The channel index of each band (None: as stored), or raise when the names cannot say
    which channel is which band (`open_cube`'s rules, in the module docstring)."""
    centres = band_centres_from_names(names)
    if centres is None:
        if sorted_by_name and len(names) > 1:
            unnamed = [name for name in names if _wavelength_of_name(name) is None]
            problem = f"has {len(names)} channels {_show_names(names)}"
            if len(unnamed) < len(names):
                verb = "names" if len(unnamed) == 1 else "name"
                problem += f", of which {_show_names(unnamed)} {verb} no wavelength"
                if any(_RENAMED_CHANNEL.fullmatch(name) for name in unnamed):
                    problem += ' (OpenImageIO writes "channelN" in place of a repeated or empty channel name)'
            else:
                problem += ", named by no wavelength"
            problem += (
                "; an OpenEXR stores its channels sorted by name, not in the order they were "
                "written, so which channel is which band cannot be told"
            )
            raise SpherejaxFileError(path, problem, _NAMED_BANDS_EXPECTED)
        return None
    seen = {}
    for name, nm in zip(names, centres):
        if nm in seen:
            raise SpherejaxFileError(
                path,
                f"has {len(names)} channels {_show_names(names)}, giving {_show_nm(nm)} nm twice "
                f"({_show_names([seen[nm], name])}), so which of the two is that band cannot be told",
                _NAMED_BANDS_EXPECTED,
            )
        seen[nm] = name
    if band_centres_nm is None:
        bands = sorted(centres)
    else:
        bands = np.asarray(band_centres_nm).tolist()
        if sorted(centres) != sorted(bands):
            whole = all(float(nm).is_integer() for nm in centres)
            found = _describe_bands(sorted(centres)) if whole else f"{sorted(centres)} nm"
            raise SpherejaxFileError(
                path,
                f"has bands {found}",
                f"the calibration's bands, {_describe_bands(bands)}",
            )
    index = {nm: channel for channel, nm in enumerate(centres)}
    order = np.asarray([index[nm] for nm in bands])
    return None if np.array_equal(order, np.arange(len(names))) else order


def _sample_kind(path, spec) -> str:
    """"uint16" or "float" (half or float samples), or raise for anything else."""
    formats = {str(f) for f in (spec.channelformats or (spec.format,))}
    if formats == {"uint16"} and spec.get_int_attribute("oiio:BitsPerSample", 16) == 16:
        return "uint16"
    if formats <= {"half", "float"}:
        return "float"
    found = ", ".join(sorted(formats))
    raise SpherejaxFileError(path, f"has {found} samples", _CUBE_EXPECTED)


@dataclasses.dataclass(frozen=True)
class _Plane:
    """Channels 0:channels of one subimage of one open file: a part of a cube's bands."""

    image: oiio.ImageInput
    path: pathlib.Path
    subimage: int
    channels: int
    expected: str  # what the file should be, for the message when its pixels cannot be decoded
    height: int  # its rows, for that message


class CubeReader:
    """A camera cube opened for reading in row strips, so that no more than a strip of it is in
    memory (`open_cube`, `open_band_files`; a context manager closing its files).

    Attributes:
      shape: (H, W, B). dtype: uint16 (TIFF) or float32 (OpenEXR).
    """

    def __init__(self, planes: Sequence[_Plane], shape, dtype, band_order=None):
        self._planes = list(planes)
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(dtype)
        self._band_order = band_order  # channel index of each band, or None = as stored

    def read_rows(self, row0: int, row1: int) -> np.ndarray:
        """Rows row0:row1 of the cube, (row1 - row0, W, B), bands in band order.

        Raises SpherejaxFileError when the pixels of those rows cannot be decoded (truncated or
        damaged file): a strip reader learns that a file is damaged only when it gets there.
        """
        height, width, _ = self.shape
        if not 0 <= row0 < row1 <= height:
            raise ValueError(f"rows: expected 0 <= row0 < row1 <= {height}, got {row0}:{row1}")
        parts = [self._read_plane(plane, row0, row1) for plane in self._planes]
        cube = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=-1)
        if self._band_order is not None:
            cube = cube[..., self._band_order]
        return np.ascontiguousarray(cube)

    def read(self) -> np.ndarray:
        """The whole cube, (H, W, B)."""
        return self.read_rows(0, self.shape[0])

    def _read_plane(self, plane: _Plane, row0: int, row1: int) -> np.ndarray:
        image, sample_type = plane.image, oiio.UINT16 if self.dtype == np.uint16 else oiio.FLOAT
        image.seek_subimage(plane.subimage, 0)
        spec = image.spec()
        # Rows count from the data window's origin (an OpenEXR's may not be at 0).
        first, width = spec.y + row0, spec.width
        if spec.tile_width:
            # Tiled files are read in whole tiles (OpenEXR refuses scanline reads of them): the
            # tile rows covering the strip, then the strip is cut out of them.
            tile = spec.tile_height
            begin = spec.y + (row0 // tile) * tile
            end = min(spec.y + -(-row1 // tile) * tile, spec.y + spec.height)
            pixels = image.read_tiles(
                plane.subimage, 0, spec.x, spec.x + width, begin, end, spec.z, spec.z + 1,
                0, plane.channels, sample_type,
            )
            skip = first - begin
        else:
            pixels = image.read_scanlines(
                plane.subimage, 0, first, spec.y + row1, spec.z, 0, plane.channels, sample_type
            )
            skip = 0
        if pixels is None or image.has_error:
            # OIIO does not always say why (a damaged deflate stream gives no message), and says
            # it in libtiff's or OpenEXR's words: `library_messages` puts them in plain ones.
            try:
                detail = image.geterror() or oiio.geterror()
            except UnicodeDecodeError:  # see _refuse_undecodable_text: no words to go by
                detail = ""
            problem = image_read_problem(plane.path, detail, row0, row1, plane.height, image.format_name())
            raise SpherejaxFileError(plane.path, problem, plane.expected)
        rows = np.asarray(pixels, dtype=self.dtype).reshape(-1, width, plane.channels)
        return rows[skip : skip + row1 - row0]

    def close(self) -> None:
        for image in {id(plane.image): plane.image for plane in self._planes}.values():
            image.close()
        self._planes = []

    def __enter__(self) -> CubeReader:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


@_refuse_undecodable_text(_CUBE_EXPECTED)
def open_cube(path, *, expected_shape: Sequence[int], band_centres_nm=None) -> CubeReader:
    """Open a camera cube stored in one file, checking its header; pixels are read by
    `CubeReader.read_rows`.

    Accepted layouts: a single image with one channel per band (16-bit TIFF, or OpenEXR with half
    or float channels, scanline or tiled), or a multi-page 16-bit TIFF with one single-channel
    page per band. Channels that all name a wavelength ("400nm", "420 nm", "T.400nm") are the
    bands of those wavelengths in any order, put back in band order: `band_centres_nm`'s, which
    they must be, else increasing wavelength; a wavelength named twice is refused. Otherwise a
    TIFF's channels are the bands in their stored order, and an OpenEXR of more than one channel
    is refused: it stores its channels sorted by name, so their order is not the band order.

    Args:
      path: the file.
      expected_shape: (H, W, B) the cube must have (the calibration's).
      band_centres_nm: (B,) the calibration's band centres, checked against channel names.

    Raises:
      SpherejaxFileError: missing, not an image, samples of another type, another size, band count
        or set of bands, a wavelength named twice, an OpenEXR whose channels do not all name a
        wavelength (the message lists the channel names found). (Damaged pixel data is found by
        `read_rows`.)
    """
    path = pathlib.Path(path)
    height, width, bands = (int(n) for n in expected_shape)
    require_image_file(path, _CUBE_EXPECTED, (height, width, bands))
    image = oiio.ImageInput.open(library_path(path, _CUBE_EXPECTED))
    if image is None:
        raise SpherejaxFileError(path, image_open_problem(path, oiio.geterror()), _CUBE_EXPECTED)
    try:
        pages = 1
        while image.seek_subimage(pages, 0):
            pages += 1
        image.geterror()  # the failed seek queued an error that would mask a later read error
        image.seek_subimage(0, 0)
        spec = image.spec()
        if spec.deep or spec.depth != 1:
            raise SpherejaxFileError(path, "is a deep or volume image", _CUBE_EXPECTED)
        if pages == 1:
            kind = _sample_kind(path, spec)
            _require_frame_shape(path, _spec_shape(image), (height, width, bands))
            names = _channel_names(image)
            whole = complete_image(image.format_name(), (height, width, bands))
            planes = [_Plane(image, path, 0, bands, whole, height)]
        else:
            if pages != bands:
                raise SpherejaxFileError(path, f"has {pages} pages", f"{bands} pages, one per band")
            for page in range(pages):
                image.seek_subimage(page, 0)
                kind = _sample_kind(path, image.spec())
                if kind != "uint16":
                    raise SpherejaxFileError(path, f"page {page} has float samples", _CUBE_EXPECTED)
                _require_frame_shape(path, _spec_shape(image), (height, width, 1))
            names = []
            whole = complete_image("tiff", (height, width, 1), pages=pages)
            planes = [_Plane(image, path, page, 1, whole, height) for page in range(pages)]
        sorted_by_name = pages == 1 and image.format_name() == "openexr"
        order = _band_order(path, names, sorted_by_name, band_centres_nm)
    except BaseException:
        image.close()
        raise
    return CubeReader(planes, (height, width, bands), np.uint16 if kind == "uint16" else np.float32, order)


def open_band_files(paths: Sequence, *, expected_shape: Sequence[int]) -> CubeReader:
    """Open one cube made of B single-channel 16-bit frames, one per band, in band order."""
    height, width, bands = (int(n) for n in expected_shape)
    if len(paths) != bands:
        raise SpherejaxFileError(paths[0], f"is one of {len(paths)} band files", f"{bands} files")
    planes = []
    try:
        for path in paths:
            path = pathlib.Path(path)
            require_image_file(path, _FRAME_EXPECTED, (height, width, 1))
            image = _open_checked_frame(path)
            planes.append(_Plane(image, path, 0, 1, complete_image(image.format_name(), (height, width, 1)), height))
            _require_frame_shape(path, _spec_shape(image), (height, width, 1))
    except BaseException:
        for plane in planes:
            plane.image.close()
        raise
    return CubeReader(planes, (height, width, bands), np.uint16)


def read_cube(path, *, expected_shape: Sequence[int], band_centres_nm=None) -> np.ndarray:
    """The whole cube of `open_cube` (same arguments and checks), (H, W, B) uint16 (TIFF) or
    float32 (OpenEXR); damaged pixel data raises SpherejaxFileError too."""
    with open_cube(path, expected_shape=expected_shape, band_centres_nm=band_centres_nm) as cube:
        return cube.read()


def read_band_files(paths: Sequence, *, expected_shape: Sequence[int]) -> np.ndarray:
    """One cube from B single-channel 16-bit frames, one per band, in band order -> (H, W, B)."""
    with open_band_files(paths, expected_shape=expected_shape) as cube:
        return cube.read()


def _output_spec(path, shape, dtype, channel_names, attributes) -> oiio.ImageSpec:
    height, width, channels = shape
    names, attributes = _frame_names_and_attributes(path, channels, channel_names, attributes)
    sample_type = {np.dtype(np.float32): oiio.FLOAT, np.dtype(np.float16): oiio.HALF,
                   np.dtype(np.uint8): oiio.UINT8}[np.dtype(dtype)]
    spec = oiio.ImageSpec(width, height, channels, sample_type)
    spec.channelnames = tuple(names)
    spec.alpha_channel = -1  # "a" of Lab or a band is never alpha
    for key, value in attributes.items():
        spec.attribute(key, value)
    return spec


def _require_image_shape(path, shape, what: str, channels=None) -> tuple[int, int, int]:
    shape = tuple(int(n) for n in shape)
    if len(shape) != 3 or 0 in shape or (channels is not None and shape[-1] not in channels):
        raise SpherejaxFileError(path, f"cannot hold an image of shape {shape}", what)
    return shape


#: Lossless OpenEXR compressions `open_exr` offers. None is the default, by measurement: on
#: corrected reflectance, whose low mantissa bits are camera noise, no lossless codec saves much,
#: and each costs far more than the rest of a file's work. Writing 1024 x 1024 x 31 float32
#: through OpenImageIO 3.2 on 2 EPYC cores (median of 5; benchmarks/README.md, bench_archive.py):
#: none 0.16-0.26 s, 130 MB; PIZ 1.7 s on one core (1.0 s with OpenEXR's two threads), 95 MB
#: (-27 %); ZIP 2.0 s (1.2), 122 MB (-6 %); RLE and ZIPS (one scanline per block) save 0-4 % at
#: 0.4 and 1.7 s. A batch on 2 cores corrects and writes a megapixel capture in about a third of
#: a second uncompressed; PIZ alone would take three times that. For smaller files, half floats
#: (`pixel_type="half"`, OpenEXR's own 16-bit type) halve the reflectance at no cost in time,
#: within 4.9e-4 of every reflectance (archive docstring); PIZ stays for those who want lossless
#: and smaller.
EXR_COMPRESSIONS = ("piz", "zip", "none")
DEFAULT_EXR_COMPRESSION = "none"
#: OpenEXR pixel types `open_exr` writes: 32-bit float, or 16-bit half float (OpenImageIO converts
#: the float32 rows it is given, rounding to nearest).
EXR_PIXEL_TYPES = ("float", "half")


def open_exr(path, shape, *, channel_names, attributes=None, compression: str = DEFAULT_EXR_COMPRESSION,
             pixel_type: str = "float") -> AtomicImageWriter | UncompressedExrWriter:
    """A writer of an (H, W, C) OpenEXR of float32 rows, stored as `pixel_type`
    (`EXR_PIXEL_TYPES`: "float", or "half", rounded to nearest), losslessly compressed
    (`EXR_COMPRESSIONS`), with named channels and string `attributes` in its header, and no date:
    OpenImageIO would stamp the current time, and a rerun must give the same bytes.

    Uncompressed with spherejax's own attributes (`exr_uncompressed.takes_attributes`: what
    `spherejax correct` writes), an `UncompressedExrWriter`, which writes OpenImageIO's bytes
    faster; otherwise OpenImageIO's `AtomicImageWriter`. Both take rows strip by strip
    (`write_rows`) and put the file in place with `commit`, which returns its SHA-256."""
    path = pathlib.Path(path)
    if compression not in EXR_COMPRESSIONS:
        raise ValueError(f"compression: expected one of {list(EXR_COMPRESSIONS)}, got {compression!r}")
    if pixel_type not in EXR_PIXEL_TYPES:
        raise ValueError(f"pixel_type: expected one of {list(EXR_PIXEL_TYPES)}, got {pixel_type!r}")
    shape = _require_image_shape(path, shape, "(H, W, C) float32")
    if compression == "none":
        names, checked = _frame_names_and_attributes(path, shape[2], channel_names, attributes)
        if takes_attributes(checked):
            # The same bytes OpenImageIO writes, in a third of the time (`io.exr_uncompressed`).
            return UncompressedExrWriter(path, shape, channel_names=names, attributes=checked, pixel_type=pixel_type)
    spec = _output_spec(path, shape, np.float16 if pixel_type == "half" else np.float32, channel_names, attributes)
    spec.attribute("compression", compression)
    spec.attribute("DateTime", "")  # an empty value suppresses OpenImageIO's time stamp
    return AtomicImageWriter(path, spec, "openexr")


#: zlib level and row filter of `open_png(..., fast=True)`: level 1 and no filter. The sRGB
#: preview of a 1024 x 1024 capture through OpenImageIO 3.2 on an EPYC core (median of 5):
#: libpng's defaults (level 6, adaptive filters) 370 ms, 0.98 MB; level 1 with adaptive filters
#: 98 ms, 1.14 MB; level 1 unfiltered 36 ms, 1.30 MB; level 0 59 ms, 3.2 MB. A third of a
#: megabyte more, beside the outputs' 140, for a tenth of the time.
FAST_PNG_LEVEL = 1
FAST_PNG_FILTER = 8  # libpng's PNG_FILTER_NONE, as OpenImageIO's "png:filter" takes it


def open_png(path, shape, *, channel_names, fast: bool = False, attributes=None) -> AtomicImageWriter:
    """An `AtomicImageWriter` for a uint8 (H, W, C) PNG, C = 1 (grey) or 3 (RGB); `fast`: zlib
    level 1 without row filters (`FAST_PNG_LEVEL`), else libpng's defaults (smaller, ten times
    slower); string `attributes` become tEXt chunks under their names."""
    path = pathlib.Path(path)
    shape = _require_image_shape(path, shape, "(H, W, 1) or (H, W, 3) uint8", channels=(1, 3))
    spec = _output_spec(path, shape, np.uint8, channel_names, attributes)
    if fast:
        spec.attribute("png:compressionLevel", FAST_PNG_LEVEL)
        spec.attribute("png:filter", FAST_PNG_FILTER)
    return AtomicImageWriter(path, spec, "png")


def _write_whole(open_writer, path, array, dtype, what: str, **kwargs) -> str:
    path = pathlib.Path(path)
    array = np.asarray(array)
    if array.ndim != 3 or array.dtype != dtype:
        raise SpherejaxFileError(
            path, f"cannot hold an array of shape {array.shape} and dtype {array.dtype}", what
        )
    with open_writer(path, array.shape, **kwargs) as writer:
        writer.write_rows(0, array)
        return writer.commit()


def write_exr(path, array, *, channel_names, attributes=None, compression: str = DEFAULT_EXR_COMPRESSION) -> str:
    """Write a float32 (H, W, C) OpenEXR (`open_exr`), atomically; return its SHA-256 (hex)."""
    return _write_whole(
        open_exr, path, array, np.float32, "(H, W, C) float32",
        channel_names=channel_names, attributes=attributes, compression=compression,
    )


def write_png(path, array, *, channel_names) -> str:
    """Write a uint8 (H, W, C) PNG (C = 1 grey, 3 RGB), atomically; return its SHA-256 (hex)."""
    return _write_whole(
        open_png, path, array, np.uint8, "(H, W, 1) or (H, W, 3) uint8", channel_names=channel_names
    )
