"""Calibration files (format "spherejax-calibration", the package docstring): written
atomically with a checksum, read whole or by rows without loading every array."""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import pathlib
import tokenize
import zipfile
import zlib
from collections.abc import Iterator, Mapping
from typing import Annotated, Any

import numpy as np
import pydantic

from .. import jsontext
from ..grid import N_WAVELENGTHS
from ..pipeline import Calibration
from ..uncertainty import NoiseModel
from .atomic import atomic_file
from .documents import (
    BandCentres, Checksum, Document, Expect, JsonObject, NonEmptyStr, PositiveNumber, Timestamp, _canonical_json,
    _check_format, _describe_bands, _json_value, _readable_json, _utc_now, check_document, located,
)
from .errors import CalibrationFileError, SpherejaxFileError, _one_line, _show

CALIBRATION_FORMAT = "spherejax-calibration"
CALIBRATION_FORMAT_VERSION = 3
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
#: The calibration format version that added the header's "noise_model".
_NOISE_MODEL_SINCE = 3

def _calibration_arrays(header: Mapping) -> tuple[str, ...]:
    """The names of the arrays a calibration file of the header's format version holds, in
    checksum order (version 1 has no wiener_offset). Call after the version was checked."""
    version = header.get("format_version", CALIBRATION_FORMAT_VERSION)
    return _OLDER_CALIBRATION_ARRAYS.get(version, tuple(CALIBRATION_ARRAYS))


def _checksum(header: Mapping, arrays: Mapping) -> str:
    """The header's checksum, sha256:<hex>, over the header without it and the arrays (numpy
    arrays or `_StoredArray`s, hashed block by block so that a calibration larger than memory
    is never read whole) that the header's format version holds.

    The exact byte sequence is in the docstring of spherejax.io: other software must reproduce it.
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


class _ArrayEntry(Document):
    """How the header describes one array."""

    shape: Annotated[list[Annotated[int, pydantic.Field(ge=0)]], Expect("a list of integers >= 0")]
    dtype: NonEmptyStr
    description: NonEmptyStr


_Entry = Annotated[_ArrayEntry, Expect("the array's shape, dtype and description")]


class _ArraysV1(Document):
    dark: _Entry
    white: _Entry
    patch: _Entry
    coeffs: _Entry
    wiener: _Entry


class _Arrays(_ArraysV1):
    wiener_offset: _Entry


class _CalibrationHeader(Document):
    """The header of a calibration file (the docstring of spherejax.io), fields in checking order."""

    format: str
    format_version: int
    software_version: NonEmptyStr
    instrument_id: NonEmptyStr
    illuminant: NonEmptyStr
    observer: NonEmptyStr
    band_centres_nm: BandCentres
    saturation: Annotated[PositiveNumber | None, Expect("a number > 0 or null")]
    created: Timestamp
    metadata: JsonObject
    checksum: Checksum
    arrays: Annotated[_Arrays, Expect(f"an object describing {list(CALIBRATION_ARRAYS)}")]
    noise_model: Any = None  # checked by noise_model_of, against NoiseModel.from_json


class _CalibrationHeaderV1(_CalibrationHeader):
    arrays: Annotated[_ArraysV1, Expect(f"an object describing {list(_OLDER_CALIBRATION_ARRAYS[1])}")]


def _check_calibration_header(path, header) -> None:
    """Check the header's fields, format and version first (a newer file may differ in the rest)."""
    if not isinstance(header, dict):
        raise CalibrationFileError(path, f"has a header of {_show(header)}", "a JSON object")
    error = located(CalibrationFileError, path)
    version = _check_format(header, CALIBRATION_FORMAT, CALIBRATION_FORMAT_VERSION, error=error, where="header")
    model = _CalibrationHeaderV1 if version in _OLDER_CALIBRATION_ARRAYS else _CalibrationHeader
    check_document(model, header, error=error, where="header")
    noise_model_of(path, header)


#: The shape of `EstimatorCovariance.residual`, which `NoiseModel.check_bands` does not check.
_RESIDUAL_SHAPE = (N_WAVELENGTHS, N_WAVELENGTHS)


def noise_model_of(path, header: Mapping) -> NoiseModel | None:
    """The `NoiseModel` of a calibration header's "noise_model" (None when absent or null).

    Raises CalibrationFileError naming the file, on one line, unless it is what
    `NoiseModel.to_json()` writes for the header's bands (the docstring of spherejax.io).
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
    """Write a calibration file (the docstring of spherejax.io), atomically.

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
