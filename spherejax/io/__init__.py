"""Files on disk: camera frames, sessions and calibration files (the formats are documented here).

This module, `archive` and `cli` are the only ones that touch the filesystem; the maths modules
never import them. Every failure raises a `SpherejaxFileError` (a ValueError) whose message is one
line, "PATH: problem (expected ...)", naming the file, the value found and what was expected. No
format uses pickle. Every writer is atomic: it writes under a temporary name in the destination's
folder and renames into place only when complete, so a failure leaves nothing new on disk
(`spherejax.io.atomic`: the steps, and the one rule for temporary names that cleanup recognises).

Camera frame
------------
One TIFF per capture holding all bands as channels: shape (H, W, C), 16-bit unsigned samples,
deflate-compressed, a single page, no alpha channel. TIFF keeps no channel names or free attributes,
so `write_frame` also stores them as JSON in the ImageDescription tag,
``{"channel_names": ["400nm", ...], "attributes": {"key": "value", ...}}`` (`read_frame_metadata`).

Cube (an input of `spherejax correct`, `read_cube`)
---------------------------------------------------
A camera frame as above; a multi-page 16-bit TIFF with one single-channel page per band; or an
OpenEXR with one half or float channel per band. Channel names that all read "<nm>nm" must be the
calibration's bands and put the channels in band order. A folder of single-channel band frames
is read with `read_band_files`.

Corrected outputs (`write_exr`, `write_png`)
---------------------------------------------
float32 OpenEXR (PIZ-compressed by default, or ZIP or none: all lossless) with named channels and
string attributes, and 8-bit PNG. Neither
carries a time stamp, so writing the same pixels twice gives the same bytes (`spherejax.archive`
relies on it to resume a batch into byte-identical outputs).

Session (format "spherejax-session", version 1)
-----------------------------------------------
A folder with ``manifest.json`` and the frame files (`write_session` writes ``frames/<id>.tif``):

    {
      "format": "spherejax-session", "format_version": 1,
      "software_version": "0.1.0",             the spherejax that wrote it
      "instrument_id": "sim-sphere-1",
      "created": "2026-11-22T10:00:00+00:00",  ISO 8601
      "band_centres_nm": [400, 420, ..., 700], B integers, strictly increasing
      "image_shape": [H, W],
      "saturation": 16383,                     raw level at or above which a pixel is saturated
      "white_patch": [r0, r1, c0, c1],         reference white patch, rows r0:r1, columns c0:c1
      "holder": [r0, r1, c0, c1],              sample holder (the Markov baseline's holder mean)
      "frames": [frame, ...],
      "metadata": {...}                        optional, free JSON (e.g. simulator parameters)
    }

A frame is an object with
      "id": unique in the session ([A-Za-z0-9._-]+ when written by `write_session`),
      "role": "dark" | "white" | "sample" | "target" (exactly one dark and one white frame),
      "file": path relative to the folder, inside it (no absolute paths, "..", or links out),
      "exposure_s": B exposure times in seconds, one per band, > 0,
      "timestamp": ISO 8601,
      "set": "training" | "test", required for samples, optional otherwise,
      "background": name of the background the sample lies on, required for samples,
      "regions": [region, ...], samples and targets only (optional, default []),
      "metadata": {...} optional, free JSON;
and a region is
      "name": unique in the frame, "patch": which physical patch it shows (default: the name),
      "region": [r0, r1, c0, c1], a non-empty rectangle inside the image,
      "reflectance": 31 known reflectances at 400..700 nm step 10 (required for targets).
Rectangles are half-open, like slices: rows r0..r1-1 and columns c0..c1-1. Every frame file is a
camera frame of shape (H, W, B). Unknown fields are refused (a typo must not pass silently).

Calibration file (format "spherejax-calibration", version 3)
------------------------------------------------------------
An .npz archive (`numpy.savez`, no pickled objects) holding the arrays of a `Calibration`
    dark (H, W, B), white (H, W, B), patch (H, W) bool, coeffs (B, 4), wiener (31, B),
    wiener_offset (31,)
and "header", a uint8 array of UTF-8 JSON:
    {"format": "spherejax-calibration", "format_version": 3, "software_version",
     "instrument_id", "band_centres_nm": [B integers], "illuminant", "observer",
     "saturation": number or null, "created": UTC ISO 8601,
     "arrays": {name: {"shape": [...], "dtype": "<f4", "description": "..."}},
     "metadata": {...}, "noise_model": {...} or null, "checksum": "sha256:<64 hex digits>"}
Read the header with ``bytes(numpy.load(path)["header"]).decode()``. The checksum is SHA-256 over
the header JSON without the "checksum" field, serialised with sorted keys, separators "," and ":"
and UTF-8 (no ASCII escaping), followed, for each array in the order dark, white, patch, coeffs,
wiener, wiener_offset, by the line ``"<name> <dtype.str> <shape as a JSON list>\\n"`` in ASCII and
the array's raw bytes in C order. It is computed from the parsed header, so the stored JSON's
layout does not matter. "metadata" is free JSON from the writer (`save_calibration(...,
metadata=)`), e.g. how the Stage II and Wiener fits were made.

The reflectance estimate is affine, r = W v_tilde + r0, with W the "wiener" array and r0 the
"wiener_offset" array.

"noise_model" (optional; absent or null: none) is the camera's noise and the calibration's
uncertainties for per-pixel uncertainties (`spherejax.uncertainty.NoiseModel`, as its
`to_json()` writes it, numbers as float64 JSON, so that `CalibrationFile.noise_model` reads
every value back exactly):
    {"gain_e_per_count": number or [B numbers] > 0 (electrons per count),
     "read_noise_counts": number or [B numbers] >= 0 (one frame's read noise, counts rms),
     "dark_frames", "white_frames": frames averaged in the dark and white-standard frames (>= 1),
     "sample_frames": frames averaged in the sample frames it corrects (>= 1),
     "white_reflectance_u": number or [B numbers] >= 0, the relative standard uncertainty of
       the white standard's certified reflectance,
     "coeffs_covariance": [B][4][4] covariance of the Stage II coefficients c1..c4, or null,
     "estimator_covariance": {"gram": [B + 1][B + 1], "residual": [31][31]} (the reflectance
       estimator's sampling covariance, `spherejax.EstimatorCovariance`), or null}
All numbers finite. Only "gain_e_per_count" and "read_noise_counts" are required inside it.

Older versions are still read. Version 2 is version 3 without "noise_model" (no noise model;
a null one is read as absent, any other is refused).
Version 1 (before the offset existed) is version 2 without the member "wiener_offset", in the
header's "arrays" and in the checksum; it is read with r0 = 0, which is what it meant.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import functools
import hashlib
import json
import math
import os
import pathlib
import re
import shutil
import tokenize
import zipfile
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import OpenImageIO as oiio

from .. import jsontext
from ..grid import N_WAVELENGTHS
from ..pipeline import Calibration
from ..uncertainty import NoiseModel
from .atomic import atomic_file, create_exclusive, fsync_folder, is_temp_sibling, temp_sibling

SESSION_FORMAT = "spherejax-session"
SESSION_FORMAT_VERSION = 1
MANIFEST_NAME = "manifest.json"
CALIBRATION_FORMAT = "spherejax-calibration"
CALIBRATION_FORMAT_VERSION = 3

ROLES = ("dark", "white", "sample", "target")
SETS = ("training", "test")

#: Arrays of a calibration file in checksum order, with the description stored in its header.
CALIBRATION_ARRAYS = {
    "dark": "dark frame (H, W, B) in raw counts, subtracted in the flat field (Eq. 10)",
    "white": "white-standard frame (H, W, B) in raw counts at the samples' exposure (Eq. 10)",
    "patch": "reference white patch mask (H, W), True on the patch (Eq. 14-15)",
    "coeffs": "Stage II coefficients (B, 4) ordered c1..c4, dimensionless (Eq. 23)",
    "wiener": "Wiener matrix (31, B): Stage II response -> reflectance at 400..700 nm step 10 "
    "(Section 2, Wiener estimation)",
    "wiener_offset": "Wiener estimator offset r0 (31,), reflectance (dimensionless) at 400..700 nm "
    "step 10: reflectance = wiener @ v_tilde + wiener_offset, the affine form of the Wiener "
    "estimate (Section 2, Wiener estimation; new in format version 2, 0 in version 1)",
}
#: The arrays of an older calibration format version, where they differ from CALIBRATION_ARRAYS.
_OLDER_CALIBRATION_ARRAYS = {1: tuple(name for name in CALIBRATION_ARRAYS if name != "wiener_offset")}

_FRAME_EXPECTED = "a single-page 16-bit TIFF of shape (H, W, C)"
_SAFE_ID = re.compile(r"[A-Za-z0-9._-]+")
_RESERVED_ATTRIBUTES = ("ImageDescription",)
_SESSION_KEYS = frozenset(
    ("format format_version software_version instrument_id created band_centres_nm image_shape "
     "saturation white_patch holder frames metadata").split()
)
_FRAME_KEYS = frozenset(
    "id role file exposure_s timestamp set background regions metadata".split()
)
_REGION_KEYS = frozenset("name patch region reflectance".split())
_CALIBRATION_KEYS = frozenset(
    ("format format_version software_version instrument_id band_centres_nm illuminant observer "
     "saturation created arrays metadata noise_model checksum").split()
)
#: The calibration format version that added the header's "noise_model".
_NOISE_MODEL_SINCE = 3


# ----------------------------------------------------------------------------------------- errors


def _one_line(text) -> str:
    # OIIO and numpy errors can span lines; a message must stay one line on stderr.
    return " ".join(str(text).split())


class SpherejaxFileError(ValueError):
    """A file or folder that cannot be read or written: "PATH: problem (expected ...)"."""

    def __init__(self, path, problem: str, expected: str | None = None):
        self.path = str(path)
        self.problem = _one_line(problem)
        self.expected = _one_line(expected) if expected else None
        message = f"{self.path}: {self.problem}"
        if self.expected:
            message += f" (expected {self.expected})"
        super().__init__(message)

    def __reduce__(self):
        # Rebuild from the three parts: dask.distributed ships worker exceptions between processes.
        return type(self), (self.path, self.problem, self.expected)


class SessionError(SpherejaxFileError):
    """A session folder, its manifest or one of its frame files is missing or invalid."""


class CalibrationFileError(SpherejaxFileError):
    """A calibration file is missing, corrupted, of another format or version, or other bands."""


@contextlib.contextmanager
def _reraise_as(error_type: type[SpherejaxFileError]) -> Iterator[None]:
    """Turn a SpherejaxFileError raised inside into `error_type`, same path and message."""
    try:
        yield
    except SpherejaxFileError as error:
        if isinstance(error, error_type):
            raise
        raise error_type(error.path, error.problem, error.expected) from None


def _show(value) -> str:
    """A short one-line rendering of a value found in a file, for error messages."""
    try:
        text = json.dumps(value)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


# ------------------------------------------------------------------------------ shared file helpers


# temp_sibling, is_temp_sibling: `spherejax.io.atomic`, imported above (every writer's one rule).


def _json_value(path, value, error_type: type[SpherejaxFileError], what: str):
    """`value` as it reads back from JSON (numpy values, tuples and non-string keys normalised).

    Checksums and round trips compare what is written with what is read, so both start from this.
    """

    def default(obj):
        if isinstance(obj, (np.ndarray, np.generic)):
            return obj.tolist()
        if isinstance(obj, Region):
            return obj.to_json()
        raise TypeError(f"{type(obj).__name__} is not JSON-serialisable")

    try:
        return json.loads(json.dumps(value, default=default, allow_nan=False))
    except (TypeError, ValueError) as error:
        raise error_type(path, f"{what} cannot be stored as JSON: {error}", "JSON values") from None


def _canonical_json(value) -> bytes:
    return json.dumps(
        value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False
    ).encode("utf-8")


def _readable_json(value, indent: str = "") -> str:
    """JSON for people: one field per line, but a list of numbers or strings on one line.

    json.dumps(indent=2) would put each of a target's 31 reflectances on a line of its own.
    """
    inner = indent + "  "
    if isinstance(value, dict) and value:
        fields = [f"{inner}{json.dumps(k)}: {_readable_json(v, inner)}" for k, v in value.items()]
        return "{\n" + ",\n".join(fields) + "\n" + indent + "}"
    if isinstance(value, list) and any(isinstance(v, (dict, list)) for v in value):
        items = [inner + _readable_json(v, inner) for v in value]
        return "[\n" + ",\n".join(items) + "\n" + indent + "]"
    return json.dumps(value, allow_nan=False)


def _utc_now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # a JSON integer beyond float range (JSON puts no limit on digits)
        return False


def _is_timestamp(value) -> bool:
    if not isinstance(value, str):
        return False
    try:
        datetime.datetime.fromisoformat(value)
    except ValueError:
        return False
    return True


def _is_rect(value, image_shape: tuple[int, int]) -> bool:
    if not (isinstance(value, list) and len(value) == 4 and all(_is_int(v) for v in value)):
        return False
    r0, r1, c0, c1 = value
    return 0 <= r0 < r1 <= image_shape[0] and 0 <= c0 < c1 <= image_shape[1]


def _rect_expected(image_shape: tuple[int, int]) -> str:
    height, width = image_shape
    return (
        f"[r0, r1, c0, c1] with 0 <= r0 < r1 <= {height} and 0 <= c0 < c1 <= {width}: "
        f"a non-empty rectangle inside the {height} x {width} image"
    )


def _describe_bands(bands: Sequence[int]) -> str:
    """Band centres for a message: like 400..700 nm step 20 (16 bands), or the list."""
    bands = [int(b) for b in bands]
    steps = {b - a for a, b in zip(bands, bands[1:])}
    if len(bands) > 2 and len(steps) == 1:
        return f"{bands[0]}..{bands[-1]} nm step {steps.pop()} ({len(bands)} bands)"
    return f"{bands} nm"


_REQUIRED = object()


class _Fields:
    """One JSON object of a file, read one checked field at a time.

    Every problem raises `error(file, "<where>.<key> is <value found>", expected)`, so each message
    names the file, the field, the value and what was expected.
    """

    def __init__(self, obj: Mapping, *, file, error: type[SpherejaxFileError], where: str = ""):
        self.obj, self.file, self.error, self.where = obj, file, error, where

    def name(self, key: str) -> str:
        return f"{self.where}.{key}" if self.where else key

    def fail(self, key: str, problem: str, expected: str):
        raise self.error(self.file, f"{self.name(key)} {problem}", expected)

    def value(self, key: str, expected: str, check: Callable[[Any], bool], default=_REQUIRED):
        """The value of `key` if `check` accepts it; `default` when absent, unless required."""
        if key not in self.obj:
            if default is _REQUIRED:
                self.fail(key, "is missing", expected)
            return default
        value = self.obj[key]
        if not check(value):
            self.fail(key, f"is {_show(value)}", expected)
        return value

    def only(self, allowed: frozenset[str]) -> None:
        unknown = sorted(set(self.obj) - allowed)
        if unknown:
            where = self.where or "the top level"
            raise self.error(
                self.file, f"{where} has unknown fields {unknown}", f"only {sorted(allowed)}"
            )

    def string(self, key: str, *, choices: Sequence[str] | None = None, default=_REQUIRED):
        if choices is None:
            expected = "a non-empty string"
        else:
            expected = " or ".join(json.dumps(c) for c in choices)
        return self.value(
            key,
            expected,
            lambda v: isinstance(v, str) and v != "" and (choices is None or v in choices),
            default,
        )

    def integer(self, key: str, *, minimum: int) -> int:
        return self.value(key, f"an integer >= {minimum}", lambda v: _is_int(v) and v >= minimum)

    def number(self, key: str, *, allow_null: bool = False, default=_REQUIRED):
        expected = "a number > 0" + (" or null" if allow_null else "")
        return self.value(
            key,
            expected,
            lambda v: (allow_null and v is None) or (_is_number(v) and v > 0),
            default,
        )

    def increasing_ints(self, key: str, expected: str, *, maximum: int = 2**31 - 1) -> list[int]:
        # The maximum keeps the values inside int64 arithmetic (JSON puts no limit on digits).
        def check(v):
            if not (isinstance(v, list) and v and all(_is_int(x) and 0 < x <= maximum for x in v)):
                return False
            return all(a < b for a, b in zip(v, v[1:]))

        return self.value(key, expected, check)

    def numbers(self, key: str, length: int, expected: str, *, positive=False, default=_REQUIRED):
        def check(v):
            if not (isinstance(v, list) and len(v) == length and all(_is_number(x) for x in v)):
                return False
            return not positive or all(x > 0 for x in v)

        values = self.value(key, expected, check, default)
        return values if values is None else np.asarray(values, dtype=np.float64)

    def shape(self, key: str, ndim: int, expected: str) -> tuple[int, ...]:
        def check(v):  # the bound as in increasing_ints: sizes stay inside int64 arithmetic
            return isinstance(v, list) and len(v) == ndim and all(_is_int(x) and 0 < x < 2**31 for x in v)

        return tuple(self.value(key, expected, check))

    def rect(self, key: str, image_shape: tuple[int, int]) -> tuple[int, int, int, int]:
        rect = self.value(key, _rect_expected(image_shape), lambda v: _is_rect(v, image_shape))
        return tuple(rect)

    def timestamp(self, key: str, default=_REQUIRED) -> str:
        return self.value(key, "an ISO 8601 date and time", _is_timestamp, default)

    def mapping(self, key: str, expected: str = "a JSON object", default=_REQUIRED) -> dict:
        return self.value(key, expected, lambda v: isinstance(v, dict), default)

    def child(self, key: str, expected: str) -> _Fields:
        """The object `key`, as a `_Fields` named after it."""
        obj = self.mapping(key, expected)
        return _Fields(obj, file=self.file, error=self.error, where=self.name(key))

    def children(self, key: str, what: str, default=_REQUIRED) -> list[_Fields]:
        """The objects of the list `key`, each a `_Fields` named "key[i]"."""
        items = self.value(key, f"a list of {what}", lambda v: isinstance(v, list), default)
        children = []
        for index, item in enumerate(items):
            where = f"{key}[{index}]"
            if not isinstance(item, dict):
                self.fail(where, f"is {_show(item)}", f"one of the {what}, an object")
            children.append(_Fields(item, file=self.file, error=self.error, where=self.name(where)))
        return children

    def relative_path(self, key: str) -> str:
        """A path relative to the file's folder, with no "..": it cannot name a file outside."""

        def check(value):
            # A NUL byte cannot be in a file name: os calls on one raise ValueError.
            if not isinstance(value, str) or value in ("", ".") or "\0" in value:
                return False
            # Both readings: a manifest written on Windows may use "\\" and drive letters.
            posix, native = pathlib.PurePosixPath(value), pathlib.PurePath(value)
            escapes = ".." in posix.parts or ".." in native.parts
            return not (posix.is_absolute() or native.is_absolute() or native.drive or escapes)

        return self.value(key, 'a relative path inside the folder (not absolute, no "..")', check)


def _check_format(fields: _Fields, name: str, version: int) -> None:
    """Refuse a document of another format, or of a newer version than this software reads."""
    from .. import __version__

    found = fields.obj.get("format", _REQUIRED)
    if found != name:
        shown = "missing" if found is _REQUIRED else _show(found)
        problem = f"is not a {name} file: format is {shown}"
        raise fields.error(fields.file, problem, f'format "{name}"')
    found_version = fields.integer("format_version", minimum=1)
    if found_version > version:
        raise fields.error(
            fields.file,
            f"is {name} format version {found_version}, newer than spherejax {__version__} reads",
            f"format version {version} or older; upgrade spherejax to read it",
        )


# ------------------------------------------------------------------------------------------ frames


def _refuse_undecodable_text(expected: str):
    """Decorate a reader whose first argument is the file: a UnicodeDecodeError out of it
    becomes a SpherejaxFileError naming the file.

    OpenImageIO's binding decodes every string it hands to Python (error messages, channel
    names, attributes) as UTF-8. A damaged file can make them quote bytes that are not, and the
    UnicodeDecodeError would then name neither the file nor the problem.
    """

    def decorate(reader):
        @functools.wraps(reader)
        def checked(path, *args, **kwargs):
            try:
                return reader(path, *args, **kwargs)
            except UnicodeDecodeError:
                problem = "is corrupted: OpenImageIO finds text in it that is not UTF-8"
                raise SpherejaxFileError(path, problem, expected) from None

        return checked

    return decorate


@_refuse_undecodable_text(_FRAME_EXPECTED)
def _open_checked_frame(path: pathlib.Path) -> oiio.ImageInput:
    """An open ImageInput on a checked camera frame (one page, uint16 samples); the caller closes it."""
    if not path.is_file():
        raise SpherejaxFileError(path, "no such file", _FRAME_EXPECTED)
    image = oiio.ImageInput.open(str(path))
    if image is None:
        problem = f"is not a readable image: {oiio.geterror()}"
        raise SpherejaxFileError(path, problem, _FRAME_EXPECTED)
    try:
        _check_frame_header(path, image)
    except BaseException:
        image.close()
        raise
    return image


@contextlib.contextmanager
def _open_frame(path: pathlib.Path) -> Iterator[oiio.ImageInput]:
    """`_open_checked_frame`, closed on exit."""
    image = _open_checked_frame(path)
    try:
        yield image
    finally:
        image.close()


def _check_frame_header(path: pathlib.Path, image: oiio.ImageInput) -> None:
    spec = image.spec()
    if spec.deep or spec.depth != 1:
        raise SpherejaxFileError(path, "is a deep or volume image", _FRAME_EXPECTED)
    formats = [str(f) for f in (spec.channelformats or (spec.format,))]
    bits = spec.get_int_attribute("oiio:BitsPerSample", 16)
    if any(f != "uint16" for f in formats) or bits != 16:
        found = ", ".join(sorted(set(formats)))
        raise SpherejaxFileError(
            path, f"has {found} samples of {bits} bits", "16-bit unsigned integer samples (uint16)"
        )
    # A second page would be silently ignored by a single-image read: refuse it.
    if image.seek_subimage(1, 0):
        raise SpherejaxFileError(path, "holds more than one image (page)", _FRAME_EXPECTED)
    # The failed seek queued "could not seek to subimage 1", which would mask a later read error.
    image.geterror()
    image.seek_subimage(0, 0)


def _spec_shape(image: oiio.ImageInput) -> tuple[int, int, int]:
    spec = image.spec()
    return spec.height, spec.width, spec.nchannels


def _require_frame_shape(path, shape: tuple[int, int, int], expected: Sequence[int]) -> None:
    """Refuse a frame whose (H, W) or channel count differs from `expected` (H, W, C)."""
    height, width, channels = (int(n) for n in expected)
    if tuple(shape[:2]) != (height, width):
        raise SpherejaxFileError(
            path,
            f"is {shape[0]} x {shape[1]} pixels (H x W)",
            f"{height} x {width} pixels",
        )
    if shape[2] != channels:
        raise SpherejaxFileError(
            path, f"has {shape[2]} channels", f"{channels} channels, one per band"
        )


def frame_spec(path) -> tuple[int, int, int]:
    """The shape (H, W, C) of a camera frame, from its header only (no pixels are read).

    Raises SpherejaxFileError for a missing file, a file that is not an image, and an image that is
    not a single page of 16-bit unsigned samples.
    """
    path = pathlib.Path(path)
    with _open_frame(path) as image:
        return _spec_shape(image)


@_refuse_undecodable_text(_FRAME_EXPECTED)
def read_frame(path, *, expected_shape: Sequence[int] | None = None) -> np.ndarray:
    """Read a camera frame.

    Args:
      path: a 16-bit TIFF (any single-page uint16 image OpenImageIO reads).
      expected_shape: (H, W, C) to insist on, or None.

    Returns:
      (H, W, C) uint16 array.

    Raises:
      SpherejaxFileError: missing file, not an image or corrupted (with OpenImageIO's message),
        not 16-bit, more than one page, or a size or channel count other than `expected_shape`.
    """
    path = pathlib.Path(path)
    with _open_frame(path) as image:
        shape = _spec_shape(image)
        if expected_shape is not None:
            _require_frame_shape(path, shape, expected_shape)
        pixels = image.read_image(oiio.UINT16)
        if pixels is None:
            # OIIO does not always say why (a damaged deflate stream gives no message).
            detail = image.geterror() or oiio.geterror() or "the pixel data cannot be decoded"
            problem = f"is corrupted: {detail}"
            raise SpherejaxFileError(path, problem, _FRAME_EXPECTED)
    return np.ascontiguousarray(np.asarray(pixels, dtype=np.uint16).reshape(shape))


@_refuse_undecodable_text(_FRAME_EXPECTED)
def read_frame_metadata(path) -> dict:
    """The channel names and attributes `write_frame` stored in a frame (header only).

    Returns:
      {"channel_names": [C str], "attributes": {str: str}}. For a TIFF written by other software,
      the channel names OpenImageIO reports and no attributes.
    """
    path = pathlib.Path(path)
    with _open_frame(path) as image:
        spec = image.spec()
        description = spec.get_string_attribute("ImageDescription")
    try:
        stored = json.loads(description)
        # Converted inside the try: a description that is JSON but not write_frame's falls back too.
        return {"channel_names": list(stored["channel_names"]), "attributes": dict(stored["attributes"])}
    except (ValueError, TypeError, KeyError, RecursionError):
        return {"channel_names": list(spec.channelnames), "attributes": {}}


def _frame_names_and_attributes(path, channels: int, channel_names, attributes):
    """Checked channel names (C str) and string attributes for `write_frame`."""
    if channel_names is None:
        channel_names = [f"channel{i}" for i in range(channels)]
    channel_names = list(channel_names)
    if len(channel_names) != channels or not all(isinstance(n, str) and n for n in channel_names):
        raise SpherejaxFileError(
            path, f"channel_names is {_show(channel_names)}", f"{channels} non-empty strings"
        )
    attributes = dict(attributes or {})
    for key, value in attributes.items():
        if not (isinstance(key, str) and key and isinstance(value, str)):
            raise SpherejaxFileError(
                path, f"attribute {_show(key)} is {_show(value)}", "string names and values"
            )
        if key in _RESERVED_ATTRIBUTES:
            raise SpherejaxFileError(
                path,
                f"attribute {key!r} is reserved for the channel names and attributes",
                f"attribute names other than {list(_RESERVED_ATTRIBUTES)}",
            )
    return channel_names, attributes


def write_frame(path, array, *, channel_names=None, attributes=None) -> None:
    """Write a camera frame as a multi-channel 16-bit TIFF, atomically.

    Args:
      path: destination; its folder must exist. Replaces an existing file only when complete.
      array: (H, W, C) uint16. (H, W) is refused: pass (H, W, 1) for one channel.
      channel_names: C names such as "400nm"; default "channel0", "channel1", ...
      attributes: string metadata {name: value}, kept as TIFF tags where TIFF has one and always
        in the ImageDescription JSON (`read_frame_metadata`).

    Raises:
      SpherejaxFileError: a wrong array, names or attributes (nothing written), or a failed write
        (the temporary file is removed).
    """
    from .. import __version__

    path = pathlib.Path(path)
    array = np.asarray(array)
    if array.ndim != 3 or array.dtype != np.uint16 or 0 in array.shape:
        raise SpherejaxFileError(
            path,
            f"cannot hold an array of shape {array.shape} and dtype {array.dtype}",
            "a non-empty (H, W, C) uint16 array",
        )
    height, width, channels = array.shape
    names, attributes = _frame_names_and_attributes(path, channels, channel_names, attributes)
    if not path.parent.is_dir():
        raise SpherejaxFileError(path, "cannot be written: no such folder", "an existing folder")

    spec = oiio.ImageSpec(width, height, channels, oiio.UINT16)
    spec.channelnames = tuple(names)
    # Every channel is a band: no channel may be taken for alpha (and premultiplied on reading).
    spec.alpha_channel = -1
    spec.attribute("compression", "zip")  # lossless deflate, which every TIFF reader decodes
    spec.attribute("Software", f"spherejax {__version__}")
    for key, value in attributes.items():
        spec.attribute(key, value)
    description = {"channel_names": names, "attributes": attributes}
    spec.attribute("ImageDescription", json.dumps(description))

    _write_image_atomic(path, spec, array, "tiff")


class AtomicImageWriter:
    """One image written through OpenImageIO in row strips under a temporary name beside `path`,
    made the file by `commit` (fsync, then rename) only once every row is written.

    The temporary name is first created with O_EXCL, so it can never be an existing file or a
    link to one elsewhere; OpenImageIO then rewrites that fresh, empty file. Leaving the `with`
    block without `commit` (an error, a strip never written) removes the temporary file, and an
    existing `path` is untouched. Rows must be written in order, top to bottom; the bytes do not
    depend on how the rows are split into strips (tested).
    """

    def __init__(self, path, spec: oiio.ImageSpec, format_name: str):
        self.path = pathlib.Path(path)
        self.height = spec.height
        self._next_row = 0
        self._temp = temp_sibling(self.path)
        self._output = None
        try:
            create_exclusive(self._temp)  # `spherejax.io.atomic`: the rules every writer follows
        except OSError as error:
            raise SpherejaxFileError(self.path, f"could not be written: {error}") from None
        # The format is named, not guessed from the temporary file's extension.
        output = oiio.ImageOutput.create(format_name)
        if output is None or not output.open(str(self._temp), spec):
            detail = output.geterror() if output is not None else oiio.geterror()
            self.abort()
            raise SpherejaxFileError(self.path, f"could not be written: {detail}")
        self._output = output

    def write_rows(self, row0: int, pixels: np.ndarray) -> None:
        """Write rows row0:row0 + len(pixels), (rows, W, C), the next rows of the image."""
        if self._output is None:
            raise SpherejaxFileError(self.path, "is no longer open for writing")
        if row0 != self._next_row:
            raise ValueError(f"rows: expected the next row {self._next_row}, got {row0}")
        row1 = row0 + len(pixels)
        if not self._output.write_scanlines(row0, row1, 0, np.ascontiguousarray(pixels)):
            detail = self._output.geterror()
            self.abort()
            raise SpherejaxFileError(self.path, f"could not be written: {detail}")
        self._next_row = row1

    def commit(self) -> str:
        """Finish the file, fsync it, rename it into place; return its SHA-256 (hex)."""
        if self._output is None:
            raise SpherejaxFileError(self.path, "is no longer open for writing")
        if self._next_row != self.height:
            self.abort()
            raise SpherejaxFileError(
                self.path, f"has {self._next_row} of its {self.height} rows", "every row written"
            )
        output, self._output = self._output, None
        try:
            if not output.close():
                raise SpherejaxFileError(self.path, f"could not be written: {output.geterror()}")
            digest = hashlib.sha256()
            with open(self._temp, "rb") as file:
                for block in iter(lambda: file.read(1 << 20), b""):
                    digest.update(block)
                os.fsync(file.fileno())  # on disk before the rename makes it the file
            os.replace(self._temp, self.path)
            fsync_folder(self.path.parent)  # and the rename on disk too
        except OSError as error:
            raise SpherejaxFileError(self.path, f"could not be written: {error}") from None
        finally:
            self.abort()
        return digest.hexdigest()

    def abort(self) -> None:
        """Drop what was written: the temporary file goes, `path` is untouched."""
        output, self._output = self._output, None
        if output is not None:
            output.close()
        # Best effort: the folder itself may be what failed (gone, or a file in its place).
        with contextlib.suppress(OSError):
            self._temp.unlink(missing_ok=True)

    def __enter__(self) -> AtomicImageWriter:
        return self

    def __exit__(self, *exc_info) -> None:
        self.abort()


def _write_image_atomic(path: pathlib.Path, spec, array: np.ndarray, format_name: str) -> str:
    """Write a whole image with `AtomicImageWriter`; return the SHA-256 (hex) of its bytes."""
    with AtomicImageWriter(path, spec, format_name) as writer:
        writer.write_rows(0, array)
        return writer.commit()


# ------------------------------------------------------------------------------- cubes and outputs

_CUBE_EXPECTED = (
    "a cube: a 16-bit TIFF with one channel or one page per band, or an OpenEXR with one "
    "float channel per band"
)
_BAND_NAME = re.compile(r"(\d+)\s*nm", re.IGNORECASE)


def band_centres_from_names(names: Sequence[str]) -> list[int] | None:
    """Band centres in nm if every name reads "<integer>nm" ("400nm", "420 nm"), else None."""
    if not names:
        return None
    centres = []
    for name in names:
        match = _BAND_NAME.fullmatch(str(name).strip())
        if match is None:
            return None
        centres.append(int(match.group(1)))
    return centres


def _channel_names(image: oiio.ImageInput) -> list[str]:
    """Channel names as written: a TIFF keeps them only in `write_frame`'s ImageDescription JSON."""
    spec = image.spec()
    try:
        stored = json.loads(spec.get_string_attribute("ImageDescription"))["channel_names"]
        if isinstance(stored, list) and len(stored) == spec.nchannels:
            return [str(name) for name in stored]
    except (ValueError, TypeError, KeyError, RecursionError):  # not write_frame's JSON
        pass
    return list(spec.channelnames)


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
            # OIIO does not always say why (a damaged deflate stream gives no message).
            try:
                detail = image.geterror() or oiio.geterror() or "the pixel data cannot be decoded"
            except UnicodeDecodeError:  # see _refuse_undecodable_text
                detail = "OpenImageIO's message about it is not UTF-8 text"
            raise SpherejaxFileError(plane.path, f"is corrupted: {detail}", plane.expected)
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
    page per band. When the channel names all read "<nm>nm" they must be `band_centres_nm` (in
    any order: OpenEXR stores channels sorted by name; they are put back in band order).

    Args:
      path: the file.
      expected_shape: (H, W, B) the cube must have (the calibration's).
      band_centres_nm: (B,) the calibration's band centres, checked against channel names.

    Raises:
      SpherejaxFileError: missing, not an image, samples of another type, another size, band count
        or set of bands. (Damaged pixel data is found by `read_rows`.)
    """
    path = pathlib.Path(path)
    height, width, bands = (int(n) for n in expected_shape)
    if not path.is_file():
        raise SpherejaxFileError(path, "no such file", _CUBE_EXPECTED)
    image = oiio.ImageInput.open(str(path))
    if image is None:
        raise SpherejaxFileError(path, f"is not a readable image: {oiio.geterror()}", _CUBE_EXPECTED)
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
            planes = [_Plane(image, path, 0, bands, _CUBE_EXPECTED)]
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
            planes = [_Plane(image, path, page, 1, _CUBE_EXPECTED) for page in range(pages)]
        order = None
        centres = band_centres_from_names(names)
        if centres is not None and band_centres_nm is not None:
            expected = [int(b) for b in np.asarray(band_centres_nm).tolist()]
            if sorted(centres) != expected:
                raise SpherejaxFileError(
                    path,
                    f"has bands {_describe_bands(sorted(centres))}",
                    f"the calibration's bands, {_describe_bands(expected)}",
                )
            order = np.argsort(centres, kind="stable")
            order = None if np.array_equal(order, np.arange(bands)) else order
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
            image = _open_checked_frame(path)
            planes.append(_Plane(image, path, 0, 1, _FRAME_EXPECTED))
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
    sample_type = {np.dtype(np.float32): oiio.FLOAT, np.dtype(np.uint8): oiio.UINT8}[np.dtype(dtype)]
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


#: Lossless OpenEXR compressions `open_exr` offers. PIZ (wavelet + Huffman) is the default: on
#: corrected reflectance, whose low mantissa bits are camera noise, it measured 31 % smaller than
#: uncompressed and faster than ZIP, which saves only 6 % and was the slowest step of a batch
#: (1024 x 1024 x 31 float32: none 0.25 s, PIZ 1.3 s, ZIP 1.5-2.8 s on 2 cores).
EXR_COMPRESSIONS = ("piz", "zip", "none")
DEFAULT_EXR_COMPRESSION = "piz"


def open_exr(path, shape, *, channel_names, attributes=None, compression: str = DEFAULT_EXR_COMPRESSION) -> AtomicImageWriter:
    """An `AtomicImageWriter` for a float32 (H, W, C) OpenEXR, losslessly compressed
    (`EXR_COMPRESSIONS`), with named channels and string `attributes` in its header, and no date:
    OpenImageIO would stamp the current time, and a rerun must give the same bytes."""
    path = pathlib.Path(path)
    if compression not in EXR_COMPRESSIONS:
        raise ValueError(f"compression: expected one of {list(EXR_COMPRESSIONS)}, got {compression!r}")
    shape = _require_image_shape(path, shape, "(H, W, C) float32")
    spec = _output_spec(path, shape, np.float32, channel_names, attributes)
    spec.attribute("compression", compression)
    spec.attribute("DateTime", "")  # an empty value suppresses OpenImageIO's time stamp
    return AtomicImageWriter(path, spec, "openexr")


def open_png(path, shape, *, channel_names) -> AtomicImageWriter:
    """An `AtomicImageWriter` for a uint8 (H, W, C) PNG, C = 1 (grey) or 3 (RGB)."""
    path = pathlib.Path(path)
    shape = _require_image_shape(path, shape, "(H, W, 1) or (H, W, 3) uint8", channels=(1, 3))
    return AtomicImageWriter(path, _output_spec(path, shape, np.uint8, channel_names, None), "png")


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


# ---------------------------------------------------------------------------------------- sessions


def rectangle_mask(rect: Sequence[int], image_shape: Sequence[int]) -> np.ndarray:
    """Boolean mask (H, W), True on rows r0:r1 and columns c0:c1 of rect = (r0, r1, c0, c1)."""
    r0, r1, c0, c1 = rect
    mask = np.zeros(tuple(image_shape), dtype=bool)
    mask[r0:r1, c0:c1] = True
    return mask


def _readonly(array: np.ndarray) -> np.ndarray:
    # The dataclasses are frozen; their arrays should not change under them either.
    array.setflags(write=False)
    return array


@dataclasses.dataclass(frozen=True, eq=False)
class Region:
    """A rectangle of a frame showing one patch. Compare regions with `to_json()`.

    Fields:
      name: unique within its frame.
      patch: the physical patch shown (the same patch on several backgrounds shares it).
      region: (r0, r1, c0, c1), rows r0:r1 and columns c0:c1.
      reflectance: known reflectance (31,) at 400..700 nm step 10, float64, or None.
    """

    name: str
    patch: str
    region: tuple[int, int, int, int]
    reflectance: np.ndarray | None = None

    def mask(self, image_shape: Sequence[int]) -> np.ndarray:
        """Boolean (H, W), True inside the rectangle."""
        return rectangle_mask(self.region, image_shape)

    def mean(self, array) -> np.ndarray:
        """Average of an (..., H, W, B) array over the rectangle -> (..., B).

        float64 for integer input (raw counts), the input's dtype for float input.
        """
        r0, r1, c0, c1 = self.region
        return np.asarray(array)[..., r0:r1, c0:c1, :].mean(axis=(-3, -2))

    def to_json(self) -> dict:
        """The region as it appears in a manifest."""
        out = {"name": self.name, "patch": self.patch, "region": [int(v) for v in self.region]}
        if self.reflectance is not None:
            out["reflectance"] = np.asarray(self.reflectance, dtype=np.float64).tolist()
        return out


@dataclasses.dataclass(frozen=True, eq=False)
class FrameInfo:
    """One frame of a session, as listed in its manifest (no pixels). Compare with `to_json()`.

    Fields:
      id: unique in the session.
      role: "dark", "white", "sample" or "target".
      file: path of the frame file relative to the session folder (`Session.frame_path`).
      exposure_s: exposure times (B,) in seconds, float64.
      timestamp: ISO 8601.
      set: "training" or "test" (always set for samples), or None.
      background: the background a sample lies on (always set for samples), or None.
      regions: the `Region`s of a sample or target frame.
      metadata: free JSON.
    """

    id: str
    role: str
    file: str
    exposure_s: np.ndarray
    timestamp: str
    set: str | None = None
    background: str | None = None
    regions: tuple[Region, ...] = ()
    metadata: dict = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict:
        """The frame as it appears in a manifest."""
        out = {
            "id": self.id,
            "role": self.role,
            "file": self.file,
            "exposure_s": self.exposure_s.tolist(),
            "timestamp": self.timestamp,
        }
        if self.set is not None:
            out["set"] = self.set
        if self.background is not None:
            out["background"] = self.background
        if self.regions:
            out["regions"] = [region.to_json() for region in self.regions]
        if self.metadata:
            out["metadata"] = self.metadata
        return out


@dataclasses.dataclass(frozen=True, eq=False)
class Session:
    """A loaded session: its manifest, checked, with methods to read its frames.

    Fields:
      path: the session folder.
      instrument_id, software_version, created: from the manifest.
      band_centres_nm: (B,) int64, strictly increasing.
      image_shape: (H, W).
      saturation: raw level at or above which a pixel counts as saturated.
      white_patch, holder: (r0, r1, c0, c1) rectangles.
      frames: every `FrameInfo`, in manifest order.
      metadata: free JSON.
    """

    path: pathlib.Path
    instrument_id: str
    band_centres_nm: np.ndarray
    image_shape: tuple[int, int]
    saturation: int | float
    white_patch: tuple[int, int, int, int]
    holder: tuple[int, int, int, int]
    frames: tuple[FrameInfo, ...]
    software_version: str
    created: str
    metadata: dict = dataclasses.field(default_factory=dict)

    @property
    def bands(self) -> int:
        return int(self.band_centres_nm.size)

    @property
    def manifest_path(self) -> pathlib.Path:
        return self.path / MANIFEST_NAME

    def frames_with(self, role: str | None = None, set: str | None = None) -> tuple[FrameInfo, ...]:
        """The frames of a role and/or set, in manifest order (None matches any)."""
        if role is not None and role not in ROLES:
            raise ValueError(f"role: expected one of {list(ROLES)}, got {role!r}")
        if set is not None and set not in SETS:
            raise ValueError(f"set: expected one of {list(SETS)}, got {set!r}")
        return tuple(
            frame
            for frame in self.frames
            if (role is None or frame.role == role) and (set is None or frame.set == set)
        )

    def frame(self, id: str) -> FrameInfo:
        """The frame with this id."""
        for frame in self.frames:
            if frame.id == id:
                return frame
        known = [frame.id for frame in self.frames]
        raise SessionError(self.manifest_path, f"has no frame {id!r}", f"one of {known}")

    def frame_path(self, frame: FrameInfo | str) -> pathlib.Path:
        """Where a frame's file lies."""
        frame = self.frame(frame) if isinstance(frame, str) else frame
        return self.path / frame.file

    def read(self, frame: FrameInfo | str) -> np.ndarray:
        """The pixels of a frame (or frame id): (H, W, B) uint16, checked against the manifest."""
        with _reraise_as(SessionError):
            expected_shape = (*self.image_shape, self.bands)
            return read_frame(self.frame_path(frame), expected_shape=expected_shape)

    def dark(self) -> np.ndarray:
        """The dark frame, (H, W, B) uint16."""
        return self.read(self.frames_with(role="dark")[0])

    def white(self) -> np.ndarray:
        """The white-standard frame, (H, W, B) uint16."""
        return self.read(self.frames_with(role="white")[0])

    def white_patch_mask(self) -> np.ndarray:
        """Boolean (H, W), True on the reference white patch (Eq. 14-15)."""
        return rectangle_mask(self.white_patch, self.image_shape)

    def holder_mask(self) -> np.ndarray:
        """Boolean (H, W), True on the sample holder."""
        return rectangle_mask(self.holder, self.image_shape)

    def to_manifest(self) -> dict:
        """The manifest this session was loaded from, as written by `write_session`."""
        return {
            "format": SESSION_FORMAT,
            "format_version": SESSION_FORMAT_VERSION,
            "software_version": self.software_version,
            "instrument_id": self.instrument_id,
            "created": self.created,
            "band_centres_nm": self.band_centres_nm.tolist(),
            "image_shape": list(self.image_shape),
            "saturation": self.saturation,
            "white_patch": list(self.white_patch),
            "holder": list(self.holder),
            "frames": [frame.to_json() for frame in self.frames],
            "metadata": self.metadata,
        }


def _parse_region(fields: _Fields, image_shape, *, reflectance_required: bool) -> Region:
    fields.only(_REGION_KEYS)
    name = fields.string("name")
    reflectance = fields.numbers(
        "reflectance",
        N_WAVELENGTHS,
        f"{N_WAVELENGTHS} finite reflectances at 400..700 nm step 10"
        + (", required for a target" if reflectance_required else ""),
        default=_REQUIRED if reflectance_required else None,
    )
    return Region(
        name=name,
        patch=fields.string("patch", default=name),
        region=fields.rect("region", image_shape),
        reflectance=None if reflectance is None else _readonly(reflectance),
    )


def _parse_frame(fields: _Fields, *, bands: int, image_shape) -> FrameInfo:
    fields.only(_FRAME_KEYS)
    role = fields.string("role", choices=ROLES)
    sample = _REQUIRED if role == "sample" else None  # set and background: required for samples
    exposure_s = fields.numbers(
        "exposure_s", bands, f"{bands} exposure times in seconds > 0, one per band", positive=True
    )
    region_fields = fields.children("regions", "regions", default=[])
    if region_fields and role in ("dark", "white"):
        fields.fail("regions", f"lists {len(region_fields)} regions", f"none on a {role} frame")
    regions = tuple(
        _parse_region(child, image_shape, reflectance_required=role == "target")
        for child in region_fields
    )
    names = [region.name for region in regions]
    if len(set(names)) != len(names):
        fields.fail("regions", f"repeat names: {names}", "unique region names within a frame")
    return FrameInfo(
        id=fields.string("id"),
        role=role,
        file=fields.relative_path("file"),
        exposure_s=_readonly(exposure_s),
        timestamp=fields.timestamp("timestamp"),
        set=fields.string("set", choices=SETS, default=sample),
        background=fields.string("background", default=sample),
        regions=regions,
        metadata=fields.mapping("metadata", default={}),
    )


def _check_frame_roles(manifest_path, frames: Sequence[FrameInfo]) -> None:
    ids = [frame.id for frame in frames]
    repeated = sorted({i for i in ids if ids.count(i) > 1})
    if repeated:
        raise SessionError(manifest_path, f"frame ids {repeated} repeat", "unique frame ids")
    for role in ("dark", "white"):
        count = sum(frame.role == role for frame in frames)
        if count != 1:
            raise SessionError(
                manifest_path, f"lists {count} {role} frames", f"exactly one with role {role!r}"
            )


def _parse_manifest(doc, *, manifest_path: pathlib.Path, root: pathlib.Path) -> Session:
    """Check a manifest's content (not its frame files) and build the `Session`."""
    if not isinstance(doc, dict):
        raise SessionError(manifest_path, f"holds {_show(doc)}", "a JSON object, the manifest")
    top = _Fields(doc, file=manifest_path, error=SessionError)
    _check_format(top, SESSION_FORMAT, SESSION_FORMAT_VERSION)
    top.only(_SESSION_KEYS)
    bands = np.asarray(
        top.increasing_ints("band_centres_nm", "band centres in nm: integers from 1 to 100000, increasing", maximum=100_000),
        dtype=np.int64,
    )
    image_shape = top.shape("image_shape", 2, "[H, W], two integers > 0")
    frames = tuple(
        _parse_frame(child, bands=bands.size, image_shape=image_shape)
        for child in top.children("frames", "frames")
    )
    _check_frame_roles(manifest_path, frames)
    return Session(
        path=root,
        instrument_id=top.string("instrument_id"),
        band_centres_nm=_readonly(bands),
        image_shape=image_shape,
        saturation=top.number("saturation"),
        white_patch=top.rect("white_patch", image_shape),
        holder=top.rect("holder", image_shape),
        frames=frames,
        software_version=top.string("software_version"),
        created=top.timestamp("created"),
        metadata=top.mapping("metadata", default={}),
    )


def _read_manifest(manifest_path: pathlib.Path):
    try:
        data = manifest_path.read_bytes()
    except OSError as error:
        raise SessionError(manifest_path, f"cannot be read: {error.strerror}") from None
    try:
        # Not json.loads: jsontext also turns bad UTF-8, 4300-digit integers and deep nesting
        # into the one-line problem.
        return jsontext.loads(data)
    except jsontext.JSONTextError as error:
        raise SessionError(manifest_path, error.problem, "JSON") from None


def _check_frame_file(session: Session, frame: FrameInfo) -> None:
    """A frame's file lies inside the session (links included) and has the right header."""
    file = session.frame_path(frame)
    resolved, root = file.resolve(), session.path.resolve()
    if not resolved.is_relative_to(root):
        raise SessionError(
            file, f"resolves to {resolved}, outside the session folder", "frame files inside it"
        )
    if not file.is_file():
        raise SessionError(
            file, f"no such file (frame {frame.id!r} in {MANIFEST_NAME})", _FRAME_EXPECTED
        )
    with _reraise_as(SessionError):
        _require_frame_shape(file, frame_spec(file), (*session.image_shape, session.bands))


def load_session(path) -> Session:
    """Load and check a session folder (manifest and every frame header; no pixels are read).

    Raises:
      SessionError: a missing folder or manifest; a manifest that is not JSON, not a session,
        of a newer format version, with a missing or mistyped field (named), exposures that do not
        match the bands, or a bad region; a frame file that is missing, outside the folder, not a
        16-bit image, or of the wrong size or channel count. The message names the file.
    """
    root = pathlib.Path(path)
    if not root.is_dir():
        problem = "is not a folder" if root.exists() else "no such folder"
        raise SessionError(root, problem, f"a session folder holding {MANIFEST_NAME}")
    manifest_path = root / MANIFEST_NAME
    if not manifest_path.is_file():
        raise SessionError(manifest_path, "no such file", "the manifest of a spherejax session")
    session = _parse_manifest(_read_manifest(manifest_path), manifest_path=manifest_path, root=root)
    for frame in session.frames:
        _check_frame_file(session, frame)
    return session


def _frame_entries(manifest_path, frames) -> list[tuple[dict, np.ndarray]]:
    """(manifest entry with "file", array) per (frame dict, array) given to `write_session`."""
    entries = []
    for index, item in enumerate(frames):
        where = f"frames[{index}]"
        if not (isinstance(item, Sequence) and len(item) == 2 and isinstance(item[0], Mapping)):
            problem = f"{where} is a {type(item).__name__}"
            raise SessionError(manifest_path, problem, "a (frame dict, array) pair")
        frame, array = item
        frame_id = frame.get("id")
        if not (isinstance(frame_id, str) and _SAFE_ID.fullmatch(frame_id)):
            raise SessionError(
                manifest_path, f"{where}.id is {_show(frame_id)}", "a name of A-Z a-z 0-9 . _ -"
            )
        if "file" in frame:
            raise SessionError(
                manifest_path, f"{where} names a file", f"none: it goes to frames/{frame_id}.tif"
            )
        entries.append(({**frame, "file": f"frames/{frame_id}.tif"}, np.asarray(array)))
    return entries


def check_new_session_folder(path) -> None:
    """Raise SessionError unless `path` is absent or an empty folder (where a session may go)."""
    path = pathlib.Path(path)
    if path.exists() and not (path.is_dir() and not any(path.iterdir())):
        raise SessionError(
            path, "already exists and is not an empty folder", "a new or empty folder"
        )


def write_session(
    path,
    *,
    instrument_id: str,
    band_centres_nm,
    image_shape: Sequence[int],
    saturation: int | float,
    white_patch: Sequence[int],
    holder: Sequence[int],
    frames: Sequence[tuple[Mapping, np.ndarray]],
    metadata: Mapping | None = None,
    created: str | None = None,
) -> Session:
    """Write a session folder, all or nothing, and load it back.

    Args:
      path: the session folder; must not exist or be empty. Missing parents are created.
      instrument_id, band_centres_nm (B,), image_shape (H, W), saturation, white_patch, holder,
        metadata: the manifest's fields (module docstring).
      frames: (frame, array) pairs; frame is a dict with the manifest's frame fields except
        "file" (regions as dicts or `Region`s), its "id" a file name ([A-Za-z0-9._-]+); array is
        (H, W, B) uint16. Files go to frames/<id>.tif with channel names "<nm>nm".
      created: ISO 8601 creation time; default now (UTC). Pass one for reproducible output.

    Returns:
      `load_session(path)`.

    Raises:
      SessionError: invalid fields or arrays, or an existing non-empty target, before anything
        is written; a failed write, after which the partly written temporary folder is removed.
    """
    from .. import __version__

    path = pathlib.Path(path)
    manifest_path = path / MANIFEST_NAME
    entries = _frame_entries(manifest_path, frames)
    manifest = {
        "format": SESSION_FORMAT,
        "format_version": SESSION_FORMAT_VERSION,
        "software_version": __version__,
        "instrument_id": instrument_id,
        "created": created if created is not None else _utc_now(),
        "band_centres_nm": band_centres_nm,
        "image_shape": image_shape,
        "saturation": saturation,
        "white_patch": white_patch,
        "holder": holder,
        "frames": [entry for entry, _ in entries],
        "metadata": {} if metadata is None else metadata,
    }
    # Check with the loader's own rules first, so nothing is written for a manifest it would refuse.
    manifest = _json_value(manifest_path, manifest, SessionError, "the manifest")
    session = _parse_manifest(manifest, manifest_path=manifest_path, root=path)
    expected_shape = (*session.image_shape, session.bands)
    for frame, (_, array) in zip(session.frames, entries):
        if array.shape != expected_shape or array.dtype != np.uint16:
            raise SessionError(
                path / frame.file,
                f"frame {frame.id!r} is an array of shape {array.shape} and dtype {array.dtype}",
                f"{expected_shape} uint16, (H, W, B) of the session",
            )
    check_new_session_folder(path)

    staging = temp_sibling(path)
    channel_names = [f"{nm}nm" for nm in session.band_centres_nm.tolist()]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        (staging / "frames").mkdir(parents=True)
        for frame, (_, array) in zip(session.frames, entries):
            attributes = {"spherejax:frame_id": frame.id, "spherejax:role": frame.role}
            try:
                write_frame(
                    staging / frame.file, array, channel_names=channel_names, attributes=attributes
                )
            except SpherejaxFileError as error:
                # Name the file as it would have been, not the temporary folder (removed below).
                raise SessionError(path / frame.file, error.problem, error.expected) from None
        # The manifest last: a folder with a manifest is a complete session.
        text = _readable_json(session.to_manifest()) + "\n"
        with atomic_file(staging / MANIFEST_NAME, "w") as manifest:  # fsynced before the folder's rename
            manifest.write(text)
        # POSIX rename replaces an empty folder atomically, and fails on a non-empty one.
        os.rename(staging, path)
        fsync_folder(path.parent)
    except OSError as error:
        raise SessionError(path, f"could not be written: {error}") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return load_session(path)


def write_simulated_session(path, seed: int = 0, instrument=None, design=None) -> Session:
    """Simulate the paper's experiment (`spherejax.simulate.simulate_experiment`) and write it as a
    session folder (`write_session`); return the loaded `Session`.

    Args:
      path: the session folder to create (refused if it exists and is not empty).
      seed: the simulation's seed.
      instrument, design: `simulate.InstrumentModel` and `simulate.ExperimentDesign`, or None
        for the defaults.
    """
    from .. import simulate  # here: the files layer calls the simulator only when asked to

    experiment = simulate.simulate_experiment(seed, instrument, design)
    return write_session(path, **simulate.session_contents(experiment))


# -------------------------------------------------------------------------------- calibration file


def _calibration_arrays(header: Mapping) -> tuple[str, ...]:
    """The names of the arrays a calibration file of the header's format version holds, in
    checksum order (version 1 has no wiener_offset). Call after the version was checked."""
    version = header.get("format_version", CALIBRATION_FORMAT_VERSION)
    return _OLDER_CALIBRATION_ARRAYS.get(version, tuple(CALIBRATION_ARRAYS))


def _checksum(header: Mapping, arrays: Mapping) -> str:
    """The header's checksum, sha256:<hex>, over the header without it and the arrays (numpy
    arrays or `_StoredArray`s, hashed block by block so that a calibration larger than memory
    is never read whole) that the header's format version holds.

    The exact byte sequence is in the module docstring: other software must reproduce it.
    """
    digest = hashlib.sha256(_canonical_json({k: v for k, v in header.items() if k != "checksum"}))
    for name in _calibration_arrays(header):
        array = arrays[name]
        digest.update(f"{name} {array.dtype.str} {json.dumps(list(array.shape))}\n".encode("ascii"))
        if isinstance(array, _StoredArray):
            for block in array.blocks():
                digest.update(block)
        else:
            digest.update(np.ascontiguousarray(array).tobytes())
    return "sha256:" + digest.hexdigest()


def _array_entry(name: str, array: np.ndarray) -> dict:
    """How the header describes one array: shape, dtype (numpy's dtype.str) and meaning."""
    return {
        "shape": list(array.shape),
        "dtype": array.dtype.str,
        "description": CALIBRATION_ARRAYS[name],
    }


def _check_calibration_header(path, header) -> None:
    """Check the header's fields, format and version first (a newer file may differ in the rest)."""
    if not isinstance(header, dict):
        raise CalibrationFileError(path, f"has a header of {_show(header)}", "a JSON object")
    fields = _Fields(header, file=path, error=CalibrationFileError, where="header")
    _check_format(fields, CALIBRATION_FORMAT, CALIBRATION_FORMAT_VERSION)
    fields.only(_CALIBRATION_KEYS)
    for key in ("software_version", "instrument_id", "illuminant", "observer"):
        fields.string(key)
    fields.increasing_ints("band_centres_nm", "band centres in nm: integers from 1 to 100000, increasing", maximum=100_000)
    fields.number("saturation", allow_null=True)
    fields.timestamp("created")
    fields.mapping("metadata")
    fields.value("checksum", '"sha256:" and 64 hex digits', _is_sha256)
    names = _calibration_arrays(header)
    described = fields.child("arrays", f"an object describing {list(names)}")
    described.only(frozenset(names))
    for name in names:
        array = described.child(name, "the array's shape, dtype and description")
        array.only(frozenset({"shape", "dtype", "description"}))
        array.value("shape", "a list of integers >= 0", _is_shape)
        array.string("dtype")
        array.string("description")
    noise_model_of(path, header)


#: The shape of `EstimatorCovariance.residual`, which `NoiseModel.check_bands` does not check.
_RESIDUAL_SHAPE = (N_WAVELENGTHS, N_WAVELENGTHS)


def noise_model_of(path, header: Mapping) -> NoiseModel | None:
    """The `NoiseModel` of a calibration header's "noise_model" (None when absent or null).

    Raises CalibrationFileError naming the file, on one line, unless it is what
    `NoiseModel.to_json()` writes for the header's bands (module docstring).
    """
    doc = header.get("noise_model")
    if doc is None:
        return None
    version = header.get("format_version", CALIBRATION_FORMAT_VERSION)
    if version < _NOISE_MODEL_SINCE:
        # null there means what absent means; a model is not what that version's writer wrote.
        raise CalibrationFileError(
            path, f"header.noise_model holds a noise model in a format version {version} file",
            f"null or absent before format version {_NOISE_MODEL_SINCE}, which added it",
        )
    expected = (
        f"null or a noise model as spherejax.NoiseModel.to_json() writes it, for the "
        f"{len(header['band_centres_nm'])} bands of band_centres_nm"
    )
    try:
        model = NoiseModel.from_json(doc)
        model.check_bands(len(header["band_centres_nm"]))
        estimator = model.estimator_covariance
        if estimator is not None and tuple(estimator.residual.shape) != _RESIDUAL_SHAPE:
            raise ValueError(
                f"estimator_covariance.residual has shape {tuple(estimator.residual.shape)}, expected {_RESIDUAL_SHAPE}"
            )
    except (ValueError, TypeError, OverflowError) as error:
        # OverflowError: a JSON integer beyond float range.
        problem = _one_line(error)
        if len(problem) > 240:  # a value found may be a long list: the message stays readable
            problem = problem[:237] + "..."
        raise CalibrationFileError(path, f"header.noise_model is not valid: {problem}", expected) from None
    return model


def _is_sha256(value) -> bool:
    return isinstance(value, str) and re.fullmatch("sha256:[0-9a-f]{64}", value) is not None


def _is_shape(value) -> bool:
    return isinstance(value, list) and all(_is_int(n) and n >= 0 for n in value)


def _check_calibration_contents(path, header, arrays: Mapping[str, np.ndarray]) -> None:
    """Everything but the checksum: header fields, and arrays present and as the header says."""
    _check_calibration_header(path, header)
    names = _calibration_arrays(header)
    version = header["format_version"]
    missing = [name for name in names if name not in arrays]
    if missing:
        raise CalibrationFileError(
            path, f"has no array {missing}", f"the arrays {list(names)} and a header (format version {version})"
        )
    unexpected = sorted(set(arrays) - set(names))
    if unexpected:
        raise CalibrationFileError(
            path, f"holds unexpected entries {unexpected}", f"only {list(names)} (format version {version})"
        )
    for name, array in arrays.items():
        described = header["arrays"][name]
        found = {"shape": list(array.shape), "dtype": array.dtype.str}
        if found != {"shape": described["shape"], "dtype": described["dtype"]}:
            raise CalibrationFileError(
                path,
                f"array {name!r} has shape {found['shape']} and dtype {found['dtype']}, "
                f"the header says {described['shape']} and {described['dtype']}",
                "the arrays the header describes",
            )
    if arrays["patch"].dtype != np.bool_:
        # A Calibration may hold floating patch weights (for differentiable studies); the file
        # format stores the mask only.
        raise CalibrationFileError(
            path,
            f"array 'patch' has dtype {arrays['patch'].dtype.str}: patch weights cannot be stored",
            "a boolean patch mask (|b1), e.g. weights > 0",
        )
    for name in (n for n in names if n != "patch"):
        # Strings, raw bytes (|V...) or complex numbers would pass the header check but are no
        # calibration (JAX would refuse them with a TypeError that names no file).
        if arrays[name].dtype.kind not in "iuf":
            raise CalibrationFileError(
                path, f"array {name!r} has dtype {arrays[name].dtype.str}", "integer or floating-point numbers"
            )
    bands = header["band_centres_nm"]
    if arrays["dark"].shape[-1:] != (len(bands),):
        raise CalibrationFileError(
            path,
            f"header.band_centres_nm lists {len(bands)} bands, the dark frame has shape "
            f"{arrays['dark'].shape}",
            "one band centre per band of the arrays",
        )


#: Arrays up to this size are read into memory when a calibration file is opened; larger ones
#: (the dark frame and white standard of a big sensor) are read by rows when needed.
IN_MEMORY_BYTES = 256 << 20
_READ_BLOCK = 16 << 20
# A header is a few kB of JSON, some 40 kB with a noise model of 16 bands (its 31 x 31 residual
# covariance, about 20 bytes a number): refuse to read gigabytes as one.
_MAX_HEADER_BYTES = 16 << 20


class _StoredArray:
    """An array stored uncompressed in an .npz (np.savez), read from the open file by offset.

    Attributes: shape, dtype (as the .npy header says); reads go through the file descriptor
    taken when the calibration was opened, so a file replaced meanwhile is never mixed in.
    """

    def __init__(self, path: pathlib.Path, fd: int, offset: int, shape, dtype):
        self.path, self._fd, self.offset = path, fd, offset
        self.shape, self.dtype = tuple(shape), np.dtype(dtype)
        self.row_bytes = math.prod(self.shape[1:]) * self.dtype.itemsize
        self.nbytes = (self.shape[0] if self.shape else 1) * self.row_bytes

    def _read_into(self, buffer: np.ndarray, offset: int) -> None:
        if not buffer.nbytes:
            return  # an empty array: memoryview refuses to cast a view with a 0 in its shape
        view = memoryview(buffer).cast("B")
        done = 0
        while done < len(view):
            got = os.preadv(self._fd, [view[done:]], offset + done)
            if got <= 0:
                raise CalibrationFileError(
                    self.path, "is truncated: an array ends before its data", "a whole calibration file"
                )
            done += got

    def read_rows(self, row0: int, row1: int) -> np.ndarray:
        """Rows row0:row1 of the first axis, as a new array."""
        out = np.empty((row1 - row0, *self.shape[1:]), dtype=self.dtype)
        self._read_into(out, self.offset + row0 * self.row_bytes)
        return out

    def read(self) -> np.ndarray:
        if not self.shape:
            out = np.empty((), dtype=self.dtype)
            self._read_into(out.reshape(1), self.offset)
            return out
        return self.read_rows(0, self.shape[0])

    def blocks(self) -> Iterator[memoryview]:
        buffer = np.empty(min(self.nbytes, _READ_BLOCK), dtype=np.uint8)
        for start in range(0, self.nbytes, _READ_BLOCK):
            block = buffer[: min(_READ_BLOCK, self.nbytes - start)]
            self._read_into(block, self.offset + start)
            yield memoryview(block)


def _member_data_offset(fd: int, info: zipfile.ZipInfo) -> int:
    """Where a member's data starts: after its local header, whose name and extra field lengths
    may differ from the central directory's (zip64 members carry an extra field)."""
    local = os.pread(fd, 30, info.header_offset)
    if len(local) != 30 or local[:4] != b"PK\x03\x04":
        raise zipfile.BadZipFile(f"member {info.filename!r} has no local header")
    name_length, extra_length = int.from_bytes(local[26:28], "little"), int.from_bytes(local[28:30], "little")
    return info.header_offset + 30 + name_length + extra_length


def _index_npz(path: pathlib.Path, fd: int) -> dict:
    """Every entry of an .npz archive: uncompressed .npy members as `_StoredArray`s (read later,
    by offset), compressed ones read now; never pickle."""
    # A cut-off archive loses its zip directory, which sits at the end.
    if not zipfile.is_zipfile(path):
        raise CalibrationFileError(
            path,
            "is not an .npz (zip) archive: truncated, or not a calibration file",
            "a spherejax calibration file",
        )
    entries, foreign = {}, []
    try:
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                if not info.filename.endswith(".npy"):
                    foreign.append(info.filename)
                    continue
                name = info.filename[: -len(".npy")]
                with archive.open(info) as member:
                    version = np.lib.format.read_magic(member)
                    read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}.get(version)
                    if read_header is None:
                        raise ValueError(f"member {info.filename!r} has .npy version {version}")
                    try:
                        shape, fortran_order, dtype = read_header(member)
                    except (SyntaxError, tokenize.TokenError, TypeError, RecursionError) as error:
                        # numpy parses the header's text with ast and tokenize, which raise these
                        # (not ValueError) on some damaged texts.
                        raise ValueError(f"member {info.filename!r} has a damaged .npy header: {error!r}") from None
                    if dtype.hasobject:
                        raise ValueError(f"member {info.filename!r} holds Python objects")
                    header_length = member.tell()
                # Checked before any data is read: a damaged shape must not make a compressed
                # member allocate more than the archive holds.
                if any(n < 0 for n in shape) or header_length + math.prod(shape) * dtype.itemsize != info.file_size:
                    raise ValueError(f"member {info.filename!r} does not hold the array its header describes")
                if info.compress_type == zipfile.ZIP_STORED and not fortran_order:
                    offset = _member_data_offset(fd, info) + header_length
                    entries[name] = _StoredArray(path, fd, offset, shape, dtype)
                else:
                    with archive.open(info) as member:
                        entries[name] = np.lib.format.read_array(member, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, RuntimeError, zlib.error) as error:
        # zipfile raises RuntimeError for an encrypted member (NotImplementedError, a subclass,
        # for an unknown compression method) and zlib.error for a damaged deflate stream.
        raise CalibrationFileError(path, f"is corrupted: {error}", "a spherejax calibration file") from None
    if foreign:
        raise CalibrationFileError(
            path, f"holds entries that are not .npy arrays: {sorted(foreign)}", "an .npz of arrays"
        )
    return entries


def _decode_header(path, raw: np.ndarray | None) -> dict:
    expected = 'a "header" entry: a uint8 array of UTF-8 JSON'
    if raw is None:
        raise CalibrationFileError(path, "has no header", expected)
    if raw.dtype != np.uint8 or raw.ndim != 1:
        problem = f"has a header of dtype {raw.dtype} and shape {raw.shape}"
        raise CalibrationFileError(path, problem, expected)
    try:
        # NaN and Infinity are not JSON (save_calibration never writes them), and the checksum,
        # computed over strict JSON, could not be verified with one in the header.
        return jsontext.loads(raw.tobytes(), allow_nan=False)
    except jsontext.JSONTextError as error:
        problem = f"has a header that is not UTF-8 JSON: {error.detail}"
        raise CalibrationFileError(path, problem, expected) from None


def save_calibration(
    path, calibration: Calibration, *, instrument_id: str, band_centres_nm, metadata=None,
    noise_model: NoiseModel | None = None,
) -> dict:
    """Write a calibration file (module docstring), atomically.

    Args:
      path: destination (conventionally .npz); its folder must exist. An existing file is
        replaced only when the new one is complete.
      calibration: the `Calibration` to store, arrays bit for bit.
      instrument_id: the instrument it was built for.
      band_centres_nm: (B,) integer band centres, B = calibration.bands.
      metadata: free JSON stored in the header's "metadata" (e.g. how the fit was made: the
        Wiener estimator's method and cross-validated errors); read back as header["metadata"].
      noise_model: a `spherejax.NoiseModel` for per-pixel uncertainties (e.g.
        `calibrate_session`'s report.noise_model), stored in the header's "noise_model" as its
        `to_json()` (every number read back exactly: `CalibrationFile.noise_model`), or None
        (stored as null).

    Returns:
      The header written, checksum included.

    Raises:
      CalibrationFileError: not a Calibration, a patch of weights rather than a boolean mask,
        bands that do not match, metadata that is not JSON, a noise model that is not a
        NoiseModel or not for these bands, or a failed write (the temporary file is removed; an
        existing file is untouched).
    """
    from .. import __version__

    path = pathlib.Path(path)
    if not isinstance(calibration, Calibration):
        raise CalibrationFileError(
            path, f"cannot hold a {type(calibration).__name__}", "a spherejax.Calibration"
        )
    if noise_model is not None and not isinstance(noise_model, NoiseModel):
        raise CalibrationFileError(
            path, f"cannot hold a noise model of type {type(noise_model).__name__}", "a spherejax.NoiseModel or None"
        )
    arrays = {name: np.asarray(getattr(calibration, name)) for name in CALIBRATION_ARRAYS}
    header = {
        "format": CALIBRATION_FORMAT,
        "format_version": CALIBRATION_FORMAT_VERSION,
        "software_version": __version__,
        "instrument_id": instrument_id,
        "band_centres_nm": band_centres_nm,
        "illuminant": calibration.illuminant,
        "observer": calibration.observer,
        "saturation": calibration.saturation,
        "created": _utc_now(),
        "arrays": {name: _array_entry(name, array) for name, array in arrays.items()},
        "metadata": {} if metadata is None else metadata,
        "noise_model": None if noise_model is None else noise_model.to_json(),
    }
    # The checksum is over the header as it will read back from JSON.
    header = _json_value(path, header, CalibrationFileError, "the header")
    header["checksum"] = _checksum(header, arrays)
    _check_calibration_contents(path, header, arrays)  # refuse to write what load would refuse

    encoded = _readable_json(header).encode("utf-8")
    try:
        with atomic_file(path) as file:
            np.savez(file, header=np.frombuffer(encoded, dtype=np.uint8), **arrays)
    except OSError as error:
        raise CalibrationFileError(path, f"could not be written: {error}") from None
    return header


def _native(array: np.ndarray) -> np.ndarray:
    """`array` in this machine's byte order. A file may store another (">f4": written on a
    big-endian machine, or by a tool that chose it); the checksum covers the bytes as stored,
    but JAX takes native byte order only."""
    return array.astype(array.dtype.newbyteorder("="), copy=False)


class CalibrationFile:
    """A calibration file, open and verified (header, checksum, contents), whose arrays are read
    when needed: a dark frame and white standard larger than `IN_MEMORY_BYTES` stay on disk and
    are read by rows (`rows`), so a calibration larger than memory can correct by strips.

    Use `open_calibration`; close with `close` or a `with` block (smaller files hold no open
    file once opened).

    Attributes:
      path: the file. header: its header dict (checksum included).
      image_shape: (H, W). bands: B. patch_box: (row0, row1, col0, col1) bounding the patch.
      noise_model: the stored `NoiseModel`, or None (none stored; always None in format
        versions 1 and 2).
    """

    def __init__(
        self, path: pathlib.Path, fd: int | None, header: dict, arrays: dict, illuminant: str | None = None
    ):
        self.path, self.header = path, header
        if "wiener_offset" not in arrays:
            # Format version 1 (its checksum, verified before, covers no offset): the estimate
            # was linear, r = W v_tilde, i.e. r0 = 0.
            arrays = {**arrays, "wiener_offset": np.zeros(N_WAVELENGTHS, np.float32)}
        self._fd, self._arrays = None, arrays  # the fd is owned once the checks below pass
        self._calibration_fields = {
            "illuminant": header["illuminant"] if illuminant is None else illuminant,
            "observer": header["observer"],
            "saturation": header["saturation"],
        }
        with _reraise_invalid(path):
            dark, white, patch = (arrays[name].shape for name in ("dark", "white", "patch"))
            if len(dark) != 3:
                raise ValueError(f"dark: expected shape (H, W, B), got {dark}")
            if white != dark:
                raise ValueError(f"white: expected shape {dark} (the dark frame's (H, W, B)), got {white}")
            if patch != dark[:2]:
                raise ValueError(f"patch: expected shape {dark[:2]} (one entry per image pixel), got {patch}")
            self.image_shape, self.bands = dark[:2], dark[2]
            for name in ("wiener", "wiener_offset"):
                # Small arrays read whole: a NaN or infinity there makes every reflectance NaN.
                bad = np.flatnonzero(~np.isfinite(np.asarray(self._value(name), np.float64)))
                if bad.size:
                    raise ValueError(
                        f"{name}: {bad.size} entries are not finite (the first at flat index "
                        f"{int(bad[0])}); expected finite numbers"
                    )
            from ..pipeline import patch_bounding_box

            self.patch_box = patch_bounding_box(self._value("patch"))
            if self.patch_box is None:
                raise ValueError("patch: the mask selects no pixel; expected at least one True entry")
            self._patch_calibration = self._crop(*self.patch_box)
        self._noise_model = noise_model_of(path, header)
        self._fd = fd

    def _value(self, name: str) -> np.ndarray:
        array = self._arrays[name]
        return _native(array.read() if isinstance(array, _StoredArray) else array)

    def _rows(self, name: str, row0: int, row1: int) -> np.ndarray:
        array = self._arrays[name]
        return _native(array.read_rows(row0, row1) if isinstance(array, _StoredArray) else array[row0:row1])

    def _crop(self, row0: int, row1: int, col0: int, col1: int) -> Calibration:
        crop = lambda name: np.ascontiguousarray(self._rows(name, row0, row1)[:, col0:col1])  # noqa: E731
        return Calibration(
            dark=crop("dark"), white=crop("white"), patch=crop("patch"), **self._small_arrays(),
            **self._calibration_fields,
        )

    def _small_arrays(self) -> dict[str, np.ndarray]:
        """The arrays every part of the calibration shares: coeffs, wiener and wiener_offset."""
        return {name: self._value(name) for name in ("coeffs", "wiener", "wiener_offset")}

    @property
    def noise_model(self) -> NoiseModel | None:
        """The header's noise model (`spherejax.NoiseModel`), or None when the file stores none."""
        return self._noise_model

    @property
    def patch_calibration(self) -> Calibration:
        """The calibration cropped to `patch_box`: `pipeline.patch_ratio(raw[r0:r1, c0:c1],
        patch_calibration)` is the white-patch ratio of the whole image."""
        return self._patch_calibration

    def rows(self, row0: int, row1: int) -> Calibration:
        """The calibration of image rows row0:row1 without the patch (`Calibration.rows`), read
        from disk for a large file."""
        height = self.image_shape[0]
        if not 0 <= row0 < row1 <= height:
            raise ValueError(f"rows: expected 0 <= row0 < row1 <= {height}, got {row0}:{row1}")
        return Calibration(
            dark=self._rows("dark", row0, row1), white=self._rows("white", row0, row1), patch=None,
            **self._small_arrays(), **self._calibration_fields,
        )

    def calibration(self) -> Calibration:
        """The whole `Calibration` in memory."""
        return Calibration(
            **{name: self._value(name) for name in CALIBRATION_ARRAYS}, **self._calibration_fields
        )

    def close(self) -> None:
        fd, self._fd = getattr(self, "_fd", None), None
        if fd is not None:
            os.close(fd)

    def __del__(self):
        self.close()

    def __enter__(self) -> CalibrationFile:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


@contextlib.contextmanager
def _reraise_invalid(path) -> Iterator[None]:
    try:
        yield
    except ValueError as error:
        if isinstance(error, SpherejaxFileError):
            raise
        raise CalibrationFileError(path, f"does not hold a valid calibration: {error}") from None


def open_calibration(path, *, band_centres_nm=None, illuminant: str | None = None) -> CalibrationFile:
    """Open and verify a calibration file (`CalibrationFile`), reading into memory only the
    arrays up to `IN_MEMORY_BYTES`; the checksum is verified block by block.

    Args: as `load_calibration`, and illuminant: the Lab illuminant of the calibrations it
      gives, instead of the one the file names (None = the file's).
    Raises: as `load_calibration`.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        problem = "is not a file" if path.exists() else "no such file"
        raise CalibrationFileError(path, problem, "a spherejax calibration file (.npz)")
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError as error:
        raise CalibrationFileError(path, f"cannot be read: {error.strerror}") from None
    try:
        arrays = _index_npz(path, fd)
        header_entry = arrays.pop("header", None)
        if isinstance(header_entry, _StoredArray):
            if header_entry.nbytes > _MAX_HEADER_BYTES:
                raise CalibrationFileError(
                    path, f"has a header of {header_entry.nbytes} bytes", f"a JSON header of at most {_MAX_HEADER_BYTES}"
                )
            header_entry = header_entry.read()
        header = _decode_header(path, header_entry)
        _check_calibration_contents(path, header, arrays)
        if _checksum(header, arrays) != header["checksum"]:
            raise CalibrationFileError(
                path,
                "does not match its checksum: tampered or corrupted",
                "the contents the checksum was computed from",
            )
        if band_centres_nm is not None:
            expected = np.asarray(band_centres_nm).tolist()
            if expected != header["band_centres_nm"]:
                raise CalibrationFileError(
                    path,
                    f"was built for bands {_describe_bands(header['band_centres_nm'])}, "
                    f"the session has {_describe_bands(expected)}",
                    "a calibration for the session's bands",
                )
        for name, array in arrays.items():
            if isinstance(array, _StoredArray) and array.nbytes <= IN_MEMORY_BYTES:
                arrays[name] = array.read()
        if not any(isinstance(array, _StoredArray) for array in arrays.values()):
            os.close(fd)  # everything is in memory: hold no open file
            fd = None
        return CalibrationFile(path, fd, header, arrays, illuminant)
    except BaseException:
        if fd is not None:
            os.close(fd)
        raise


def load_calibration(path, *, band_centres_nm=None) -> tuple[Calibration, dict]:
    """Read and verify a calibration file, whole (`open_calibration` reads large ones by rows).

    Args:
      path: a file written by `save_calibration`.
      band_centres_nm: (B,) the bands of the data it will correct, or None not to check.

    Returns:
      (calibration, header): the `Calibration` as saved (bit-identical arrays; float64 arrays stay
      float64 only with jax x64 enabled) and the header dict; header["noise_model"] is the
      stored noise model's JSON or None (`NoiseModel.from_json` reads it, or use
      `open_calibration(path).noise_model`; absent from format versions 1 and 2).

    Raises:
      CalibrationFileError: missing, not an .npz or truncated, missing arrays or header, another
        format, a newer format version, a checksum mismatch (tampered or corrupted), arrays that
        disagree with the header, a patch that is not a boolean mask, a "noise_model" that is
        not a valid noise model for its bands, other band centres than `band_centres_nm`, or
        contents that are not a valid `Calibration`.
    """
    with open_calibration(path, band_centres_nm=band_centres_nm) as opened:
        with _reraise_invalid(opened.path):
            return opened.calibration(), opened.header


__all__ = [
    "temp_sibling",
    "is_temp_sibling",
    "write_simulated_session",
    "SpherejaxFileError",
    "SessionError",
    "CalibrationFileError",
    "ROLES",
    "SETS",
    "Region",
    "FrameInfo",
    "Session",
    "frame_spec",
    "read_frame",
    "read_frame_metadata",
    "write_frame",
    "band_centres_from_names",
    "CubeReader",
    "open_cube",
    "open_band_files",
    "read_cube",
    "read_band_files",
    "AtomicImageWriter",
    "open_exr",
    "open_png",
    "write_exr",
    "write_png",
    "rectangle_mask",
    "load_session",
    "write_session",
    "save_calibration",
    "CalibrationFile",
    "open_calibration",
    "load_calibration",
    "noise_model_of",
]
