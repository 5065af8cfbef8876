"""Calibration files (format "spherejax-calibration", the package docstring): HDF5 written
atomically with a checksum, read whole or by rows without loading every array; the .npz files of
format versions 1 to 3 are still read (whole)."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import itertools
import json
import math
import os
import pathlib
import tokenize
import zipfile
import zlib
from collections.abc import Iterator, Mapping
from typing import Annotated, Any

import h5py
import numpy as np
import pydantic

from .. import interrupt, jsontext
from ..grid import N_WAVELENGTHS
from .._checks import require_finite
from ..pipeline import PARAMETERS, Calibration
from ..uncertainty import NoiseModel
from .atomic import atomic_file
from .documents import (
    BandCentres, Checksum, Document, Expect, JsonObject, NonEmptyStr, PositiveNumber, Timestamp, _canonical_json,
    _check_format, _describe_bands, _json_value, _readable_json, _utc_now, check_document, located,
)
from .errors import CalibrationFileError, SpherejaxFileError, _one_line, _show
from .library_messages import hdf5_problem, library_detail

CALIBRATION_FORMAT = "spherejax-calibration"
CALIBRATION_FORMAT_VERSION = 4
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
    is never read whole) that the header's format version holds; the same in either container.

    Every block of about `_READ_BLOCK` bytes is a safe point (`spherejax.interrupt.check`):
    verifying a calibration of hundreds of gigabytes takes minutes, and SIGINT / SIGTERM must
    stop `spherejax correct` within a block rather than after the whole file.

    The exact byte sequence is in the docstring of spherejax.io: other software must reproduce it.
    """
    digest = hashlib.sha256(_canonical_json({k: v for k, v in header.items() if k != "checksum"}))
    for name in _calibration_arrays(header):
        array = arrays[name]
        digest.update(f"{name} {array.dtype.str} {json.dumps(list(array.shape))}\n".encode("ascii"))
        if isinstance(array, _StoredArray):
            for block in array.blocks():
                interrupt.check()
                digest.update(block)
        else:
            # The bytes tobytes() gives (C order, as stored), hashed in place a block at a time.
            data = np.ascontiguousarray(array).reshape(-1).view(np.uint8)
            for start in range(0, data.size, _READ_BLOCK):
                interrupt.check()
                digest.update(data[start:start + _READ_BLOCK])
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

#: The first bytes of the two containers: HDF5 (format version 4 on; its superblock at offset 0,
#: where h5py puts it) and zip (the .npz of format versions 1 to 3).
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
ZIP_SIGNATURE = b"PK\x03\x04"
#: The format version that moved from .npz to HDF5.
_HDF5_SINCE = 4
#: The arrays stored chunked by rows: the (H, W, B) frames and the (H, W) patch, read by rows.
_FRAME_ARRAYS = ("dark", "white", "patch")
# A chunk is whole rows (full width and all bands), so that reading rows r0:r1 reads only the
# chunks holding them, each one contiguous piece of the file; about 1 MiB of them, so that a
# 2048 x 2048 x 16 float32 frame has 256 chunks (a small chunk index) and a strip's first and last
# chunks read at most about 1 MiB it does not need. Uncompressed: the frames are noisy float
# counts that deflate barely shrinks, and rows read at disk speed with no decompression.
_CHUNK_BYTES = 1 << 20
#: The most chunks a frame array may be stored in. `save_calibration` writes chunks of about
#: `_CHUNK_BYTES` (one row where a row is larger): a million of them is a frame of a terabyte, or
#: of a million rows. A file may describe far more (HDF5's implicit chunk index stores no entry
#: per chunk: a 48 kB file can declare 10^10 chunks), and every check that lists its chunks
#: would take hours: such a file is refused before they are counted.
_MAX_CHUNKS = 1 << 20
#: How many bytes of a dataset may lie in holes of a sparse file (allocated, never written: they
#: read as zeros) before it is refused, when they are more than half of it too. A calibration is
#: written whole, but a file system may store runs of zeros as holes (ZFS with compression, `cp
#: --sparse=always`): an all-zero dark frame of an ordinary sensor is kept, while reading this
#: many bytes of holes takes well under a second.
_UNWRITTEN_ALLOWANCE = 256 << 20
_EXPECTED_WHOLE = "a calibration written whole by spherejax calibrate"
_EXPECTED_FILE = "a spherejax calibration file (HDF5; an .npz archive before format version 4)"


def _row_chunks(shape: tuple[int, ...], itemsize: int) -> tuple[int, ...] | None:
    """The chunk shape of a frame array: about `_CHUNK_BYTES` of whole rows; None (contiguous)
    for an array with no element, which HDF5 cannot chunk."""
    if not shape or 0 in shape:
        return None
    row_bytes = math.prod(shape[1:]) * itemsize
    return (max(1, min(shape[0], _CHUNK_BYTES // row_bytes)), *shape[1:])


@contextlib.contextmanager
def _hdf5_errors(path, dataset: str | None = None) -> Iterator[None]:
    """h5py's errors on a damaged file (OSError, KeyError, ValueError, RuntimeError from its
    checks and HDF5's) as one CalibrationFileError naming the file, in plain words
    (`library_messages.hdf5_problem`; `dataset`: the one being read, if any)."""
    try:
        yield
    except (OSError, KeyError, ValueError, RuntimeError, TypeError) as error:
        if isinstance(error, SpherejaxFileError):
            raise
        raise CalibrationFileError(path, hdf5_problem(error, dataset), _EXPECTED_WHOLE) from None


class _StoredArray:
    """An array of a calibration file's HDF5 dataset, read when needed: by rows, whole, or block by
    block (for the checksum).

    Attributes: shape, dtype (the dataset's); nbytes. Reads go through the HDF5 file opened with
    the calibration (it holds its own descriptor), so a file replaced meanwhile is never mixed in.
    """

    def __init__(self, path: pathlib.Path, dataset: h5py.Dataset, name: str | None = None):
        self.path, self._dataset, self.name = path, dataset, name
        self.shape, self.dtype = tuple(dataset.shape), dataset.dtype
        self.row_bytes = math.prod(self.shape[1:]) * self.dtype.itemsize
        self.nbytes = math.prod(self.shape) * self.dtype.itemsize

    def read_rows(self, row0: int, row1: int) -> np.ndarray:
        """Rows row0:row1 of the first axis, as a new array, read about `_READ_BLOCK` bytes at a
        time with a safe point (`spherejax.interrupt.check`) between blocks: a whole frame of a
        large calibration (the patch crop's rows, `CalibrationFile.calibration`) can take a
        while, and a stop request must not wait for it. A read of one block (a strip) has none."""
        out = np.empty((row1 - row0, *self.shape[1:]), dtype=self.dtype)
        if not out.size:  # HDF5 refuses an empty selection
            return out
        rows = max(1, _READ_BLOCK // max(self.row_bytes, 1))
        with _hdf5_errors(self.path, self.name):
            for start in range(row0, row1, rows):
                if start != row0:
                    interrupt.check()
                stop = min(start + rows, row1)
                self._dataset.read_direct(out, np.s_[start:stop], np.s_[start - row0:stop - row0])
        return out

    def read(self) -> np.ndarray:
        if not self.shape:
            with _hdf5_errors(self.path, self.name):
                return np.asarray(self._dataset[()], dtype=self.dtype)
        return self.read_rows(0, self.shape[0])

    def blocks(self) -> Iterator[np.ndarray]:
        """The array's C-order bytes as arrays of whole rows, about `_READ_BLOCK` bytes each."""
        if not self.shape:
            yield self.read()
            return
        rows = max(1, _READ_BLOCK // max(self.row_bytes, 1))
        for row0 in range(0, self.shape[0], rows):
            yield self.read_rows(row0, min(row0 + rows, self.shape[0]))


def _container(path: pathlib.Path) -> str:
    """"hdf5" or "zip", by the file's first bytes (not its name: any suffix is taken)."""
    try:
        with open(path, "rb") as file:
            start = file.read(len(HDF5_SIGNATURE))
    except OSError as error:
        raise CalibrationFileError(path, f"cannot be read: {error.strerror}") from None
    if start == HDF5_SIGNATURE:
        return "hdf5"
    if start.startswith(ZIP_SIGNATURE):
        return "zip"
    problem = "is empty" if not start else f"is neither HDF5 nor an .npz (zip) archive: it starts with {start!r}"
    raise CalibrationFileError(path, problem, _EXPECTED_FILE)


def _index_hdf5(path: pathlib.Path, stored: h5py.File) -> tuple[bytes | None, dict[str, _StoredArray]]:
    """The header attribute's bytes (None when absent) and every dataset of the root group as a
    `_StoredArray`, none read yet. Only plain datasets whose data lie whole in the file are
    taken: no links (an external link reads another file), groups, external or virtual storage,
    filters (compression: spherejax writes none), and every byte of the data written (a chunk
    never written reads as zeros, and a forged shape could ask for terabytes).

    "Written" is what the file really stores, not what HDF5 allocated (`_check_written`): a
    48 kB file can declare 100000 x 100000 x 16 frames allocated early and never written (a
    sparse file of 1.3 TB), which the checksum would read for hours, or data past the file's end
    (a truncated copy). Both are refused here, before any data is read."""
    with _hdf5_errors(path), _descriptor(path, stored) as fd:
        header = stored.attrs["header"] if "header" in stored.attrs else None
        if header is None and not any(name in stored for name in _FRAME_ARRAYS):
            # HDF5 written by other software (or another program's file named .h5): say so,
            # rather than which of its entries spherejax would refuse first.
            entries = sorted(stored)
            held = f"its entries are {_show(entries)}" if entries else "it holds no entry"
            raise CalibrationFileError(
                path, f'is an HDF5 file but not a spherejax calibration: no "header" attribute and no dark, '
                f"white or patch dataset; {held}", _EXPECTED_FILE,
            )
        if isinstance(header, str):
            # h5py decodes UTF-8 with surrogateescape: bytes that are not UTF-8 come back as
            # they were, for jsontext to name.
            header = header.encode("utf-8", "surrogateescape")
        elif header is not None and not isinstance(header, bytes):
            raise CalibrationFileError(
                path, f"has a header attribute of {type(header).__name__} {_show(np.asarray(header).tolist())}",
                'a "header" attribute: a string of UTF-8 JSON',
            )
        arrays = {}
        for name in stored:
            link = stored.get(name, getlink=True)
            if not isinstance(link, h5py.HardLink):
                raise CalibrationFileError(path, f"entry {name!r} is a {type(link).__name__}", "a dataset stored in the file")
            dataset = stored[name]
            if not isinstance(dataset, h5py.Dataset):
                raise CalibrationFileError(path, f"entry {name!r} is a {type(dataset).__name__}", "a dataset")
            if dataset.shape is None:
                raise CalibrationFileError(path, f"dataset {name!r} has no dataspace (an empty dataset)", "an array")
            if dataset.is_virtual or dataset.external is not None or dataset.id.get_create_plist().get_nfilters():
                raise CalibrationFileError(
                    path, f"dataset {name!r} is stored virtual, external or filtered (compressed)",
                    "its data in the file, unfiltered, as save_calibration writes them",
                )
            array = _StoredArray(path, dataset, name)
            # Chunks are stored whole: those over the last rows hold padding beyond the array.
            allocated = array.nbytes
            if dataset.chunks is not None:
                count = math.prod(-(-n // c) for n, c in zip(array.shape, dataset.chunks))
                if count > _MAX_CHUNKS:  # before HDF5 is asked anything that lists the chunks
                    raise CalibrationFileError(
                        path, f"dataset {name!r} of shape {list(array.shape)} is stored in {count} chunks "
                        f"of shape {list(dataset.chunks)}",
                        f"at most {_MAX_CHUNKS} chunks of whole rows, about {_CHUNK_BYTES} bytes each, "
                        "as save_calibration writes them",
                    )
                allocated = count * math.prod(dataset.chunks) * array.dtype.itemsize
            stored_bytes = dataset.id.get_storage_size()
            if stored_bytes != allocated:
                raise CalibrationFileError(
                    path, f"dataset {name!r} of shape {list(array.shape)} holds {stored_bytes} of its {allocated} bytes",
                    "every byte of its data written",
                )
            _check_written(path, fd, name, dataset, allocated)
            arrays[name] = array
    return header, arrays


@contextlib.contextmanager
def _descriptor(path: pathlib.Path, stored: h5py.File) -> Iterator[int]:
    """A descriptor of the open HDF5 file for `_check_written`'s lseek calls: the one HDF5 reads
    through (so a file replaced meanwhile is never the one checked), its offset restored after
    (HDF5 reads with pread, but nothing here relies on it); or, for a driver that has none, the
    path opened anew."""
    try:
        fd = stored.id.get_vfd_handle()
    except (OSError, ValueError, RuntimeError, TypeError, NotImplementedError):
        fd = None
    if isinstance(fd, int) and fd >= 0:
        position = os.lseek(fd, 0, os.SEEK_CUR)
        try:
            yield fd
        finally:
            os.lseek(fd, position, os.SEEK_SET)
        return
    fd = os.open(path, os.O_RDONLY)
    try:
        yield fd
    finally:
        os.close(fd)


def _storage_ranges(dataset: h5py.Dataset) -> list[tuple[int, int]] | None:
    """The byte ranges [start, end) of the file that hold the dataset's data, as HDF5 allocated
    them (its one range, or one per chunk; at most `_MAX_CHUNKS`, checked before), merged where
    they touch; None where this HDF5 cannot list chunks. Unallocated chunks are absent (the
    storage size check counts them)."""
    if dataset.chunks is None:
        offset = dataset.id.get_offset()
        return [] if offset is None else [(offset, offset + dataset.id.get_storage_size())]
    ranges = []
    if hasattr(dataset.id, "chunk_iter"):  # HDF5 1.12.3 / 1.14 on: one pass over the chunk index
        dataset.id.chunk_iter(lambda info: ranges.append((info.byte_offset, info.byte_offset + info.size)))
    elif not hasattr(dataset.id, "get_chunk_info_by_coord"):
        return None
    else:
        corners = itertools.product(*(range(0, n, c) for n, c in zip(dataset.shape, dataset.chunks)))
        for index, corner in enumerate(corners):
            if index % 4096 == 4095:
                interrupt.check()
            info = dataset.id.get_chunk_info_by_coord(corner)
            if info.byte_offset is not None:
                ranges.append((info.byte_offset, info.byte_offset + info.size))
    merged: list[tuple[int, int]] = []
    for start, end in sorted(ranges):
        if merged and start <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], end))
        else:
            merged.append((start, end))
    return merged


def _data_bytes(fd: int, start: int, end: int) -> int:
    """How many bytes of [start, end) the file stores as data: not in holes of a sparse file
    (allocated by HDF5, never written), found with lseek's SEEK_DATA / SEEK_HOLE, one pair of
    calls per stretch of data. Where the file system or platform cannot tell, all of it."""
    seek_data, seek_hole = getattr(os, "SEEK_DATA", None), getattr(os, "SEEK_HOLE", None)
    if seek_data is None or seek_hole is None:
        return end - start
    total, position = 0, start
    for step in itertools.count():
        if position >= end:
            break
        if step % 4096 == 4095:  # a file of many small stretches: still a safe point
            interrupt.check()
        try:
            data = os.lseek(fd, position, seek_data)
        except OSError as error:
            if error.errno == errno.ENXIO:  # no data from here to the file's end
                break
            if error.errno in (errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP):
                return end - start  # holes are not reported here
            raise
        if data >= end:
            break
        hole = os.lseek(fd, data, seek_hole)
        total += min(hole, end) - data
        position = hole
    return total


def _check_written(path: pathlib.Path, fd: int, name: str, dataset: h5py.Dataset, allocated: int) -> None:
    """Refuse a dataset whose declared data the file does not store, before any of it is read.

    HDF5's storage size counts what it allocated, and allocating writes nothing: a dataset
    created with early allocation and never written lies in a hole of a sparse file (reading as
    zeros), and one of a file cut short lies past its end. Refused:
    - any byte past the file's end (reading it fails, after all the bytes before it were read);
    - more than half of its bytes in holes, when they are more than `_UNWRITTEN_ALLOWANCE`
      (a little of them is no cost, and zeros a file system stored as holes are still data).
    """
    if not allocated:
        return
    size = os.fstat(fd).st_size
    ranges = _storage_ranges(dataset)
    if ranges is None:
        return  # the checksum's reads are still safe points
    last = max((end for _, end in ranges), default=0)
    written = sum(_data_bytes(fd, start, min(end, size)) for start, end in ranges if start < size)
    unwritten = allocated - written
    if last > size:
        reason = f"its data run to byte {last}, past the file's end at byte {size}: the file was cut short"
    elif unwritten > _UNWRITTEN_ALLOWANCE and 2 * unwritten > allocated:
        reason = f"the other {unwritten} were allocated but never written (holes of a sparse file)"
    else:
        return
    declared = " x ".join(map(str, dataset.shape)) or "1"
    raise CalibrationFileError(
        path, f"dataset {name!r} declares {declared} values ({allocated} bytes) but the file stores only "
        f"{written} bytes of them; {reason}",
        _EXPECTED_WHOLE,
    )


def _read_npz(path: pathlib.Path) -> tuple[bytes | None, dict[str, np.ndarray]]:
    """The header's bytes (None when absent) and every array of an .npz calibration file (format
    versions 1 to 3), read whole (`_read_npy`), never unpickled."""
    expected = 'a "header" entry: a uint8 array of UTF-8 JSON'
    try:
        # Opened here, not by np.load, which leaves its own file unclosed when the zip is refused.
        with open(path, "rb") as file, np.load(file, allow_pickle=False) as archive:
            foreign = sorted(name for name in archive.zip.namelist() if not name.endswith(".npy"))
            if foreign:
                raise CalibrationFileError(path, f"holds entries that are not .npy arrays: {foreign}", "an .npz of arrays")
            entries = {name: _read_npy(archive.zip, name + ".npy") for name in archive.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, RuntimeError, zlib.error,
            SyntaxError, tokenize.TokenError, TypeError, RecursionError) as error:
        # zipfile raises RuntimeError for an encrypted member (NotImplementedError, a subclass,
        # for an unknown compression method) and zlib.error for a damaged deflate stream; numpy
        # parses an .npy header's text with ast and tokenize, which raise SyntaxError,
        # TokenError, TypeError or RecursionError on some damaged texts.
        if isinstance(error, SpherejaxFileError):
            raise
        raise CalibrationFileError(
            path, f"is truncated or corrupted: {str(error) or type(error).__name__}", "a whole calibration file"
        ) from None
    header = entries.pop("header", None)
    if header is not None and (header.dtype != np.uint8 or header.ndim != 1):
        raise CalibrationFileError(path, f"has a header of dtype {header.dtype} and shape {header.shape}", expected)
    return None if header is None else header.tobytes(), entries


def _read_npy(archive: zipfile.ZipFile, member: str) -> np.ndarray:
    """The array of one .npy member, as np.load reads it (dtype and byte order as stored, C or
    Fortran order), refusing before any allocation a member whose .npy header describes
    another size than the member holds (a damaged shape could ask for terabytes) or one of
    Python objects (pickles). The data are read `_READ_BLOCK` bytes at a time with a safe point
    (`spherejax.interrupt.check`) between blocks: a large member takes a while to inflate."""
    info = archive.getinfo(member)
    with archive.open(info) as data:
        version = np.lib.format.read_magic(data)
        read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}.get(version)
        if read_header is None:
            raise ValueError(f"member {member!r} has .npy version {version}")
        shape, fortran_order, dtype = read_header(data)
        if dtype.hasobject:
            raise ValueError(f"member {member!r} holds Python objects")
        if any(n < 0 for n in shape) or data.tell() + math.prod(shape) * dtype.itemsize != info.file_size:
            raise ValueError(f"member {member!r} does not hold the array its header describes")
        array = np.empty(math.prod(shape), dtype)
        if array.nbytes:
            raw = array.view(np.uint8)
            for start in range(0, raw.size, _READ_BLOCK):
                if start:
                    interrupt.check()
                block = data.read(min(_READ_BLOCK, raw.size - start))
                if len(block) != min(_READ_BLOCK, raw.size - start):
                    raise ValueError(f"member {member!r} ends before the array its header describes")
                raw[start:start + len(block)] = np.frombuffer(block, np.uint8)
    return array.reshape(shape[::-1]).transpose() if fortran_order else array.reshape(shape)


def _decode_header(path, raw: bytes | None, container: str) -> dict:
    expected = 'a "header" attribute: a string of UTF-8 JSON' if container == "hdf5" else 'a "header" entry: a uint8 array of UTF-8 JSON'
    if raw is None:
        raise CalibrationFileError(path, "has no header", expected)
    if len(raw) > _MAX_HEADER_BYTES:
        raise CalibrationFileError(path, f"has a header of {len(raw)} bytes", f"a JSON header of at most {_MAX_HEADER_BYTES}")
    try:
        # NaN and Infinity are not JSON (save_calibration never writes them), and the checksum,
        # computed over strict JSON, could not be verified with one in the header.
        return jsontext.loads(raw, allow_nan=False)
    except jsontext.JSONTextError as error:
        problem = f"has a header that is not UTF-8 JSON: {error.detail}"
        raise CalibrationFileError(path, problem, expected) from None


class _FailureKeepingFile:
    """The temporary file as h5py's file-object driver sees it, keeping the first failed write
    (a full disk) in `error` and reporting success, so that `save_calibration` raises it once
    h5py has closed the file: h5py cannot raise a write that fails while it closes the file (the
    metadata it flushes then), it prints a traceback and carries on."""

    def __init__(self, file):
        self._file, self.error = file, None

    def _keep(self, operation, *args) -> None:
        if self.error is None:  # after a failure the file is given up: nothing more is written
            try:
                operation(*args)
            except OSError as error:
                self.error = error

    def write(self, data) -> int:
        self._keep(self._file.write, data)
        return memoryview(data).nbytes

    def truncate(self, size: int) -> int:
        self._keep(self._file.truncate, size)
        return size

    def flush(self) -> None:
        self._keep(self._file.flush)

    def read(self, size: int = -1) -> bytes:  # what h5py tells a file object by
        return self._file.read(size)

    def readinto(self, buffer) -> int:
        return self._file.readinto(buffer)

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._file.seek(offset, whence)

    def tell(self) -> int:
        return self._file.tell()


def _require_usable_patch(path, dark: np.ndarray, white: np.ndarray, patch: np.ndarray) -> None:
    """Refuse a calibration whose white patch has, in some band, no pixel with a usable flat field
    (white - dark finite and > 0, Eq. 10): the patch ratio (Eq. 14-15) of every image would be
    NaN there, and every pixel of every image flagged (QUALITY_PATCH_UNUSABLE), so such a file
    is no calibration. (Frames with unusable pixels elsewhere stay valid: those pixels are
    flagged one by one, and a `Calibration` of a strip of rows may hold only such pixels.)"""
    signal = white.astype(np.float64) - dark.astype(np.float64)
    usable = np.asarray(patch, bool)[..., None] & np.isfinite(signal) & (signal > 0)
    bands = np.flatnonzero(~usable.any(axis=(0, 1)))
    if bands.size:
        raise CalibrationFileError(
            path, f"no pixel of the white patch has white - dark finite and > 0 in band(s) {bands.tolist()} "
            "(counted from 0): every image's patch ratio would be NaN and every pixel flagged",
            "a white patch whose white frame lies above the dark frame in every band",
        )


def save_calibration(
    path, calibration: Calibration, *, instrument_id: str, band_centres_nm, metadata=None,
    noise_model: NoiseModel | None = None,
) -> dict:
    """Write a calibration file (the docstring of spherejax.io), atomically.

    Args:
      path: destination (conventionally .h5), any name; its folder must exist. An existing file is
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
    _require_usable_patch(path, arrays["dark"], arrays["white"], arrays["patch"])

    try:
        # h5py writes the temporary file through its handle ("w+b": h5py's file-object driver
        # reads too) and has closed it, every byte handed over, before atomic_file flushes,
        # fsyncs and renames it.
        with atomic_file(path, "w+b") as file:
            keeping = _FailureKeepingFile(file)
            with h5py.File(keeping, "w") as stored:
                stored.attrs["header"] = _readable_json(header)  # a UTF-8 string: h5dump shows the JSON
                for name, array in arrays.items():
                    chunks = _row_chunks(array.shape, array.dtype.itemsize) if name in _FRAME_ARRAYS else None
                    stored.create_dataset(name, data=array, chunks=chunks).attrs["description"] = CALIBRATION_ARRAYS[name]
            if keeping.error is not None:
                raise keeping.error
    except OSError as error:
        # Python's OSError (the first failed write, kept by _FailureKeepingFile) in its own words,
        # not "[Errno 28] No space left on device: 'PATH'"; h5py's as a cleaned detail.
        problem = f"could not be written: {error.strerror}" if error.strerror else f"could not be written (HDF5: {library_detail(error, path)})"
        raise CalibrationFileError(path, problem) from None
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
    file once opened). It pickles (e.g. to a dask worker): one that reads by rows is opened and
    verified again where it is unpickled, and must be the same file there (its checksum).

    Attributes:
      path: the file. header: its header dict (checksum included).
      image_shape: (H, W). bands: B. patch_box: (row0, row1, col0, col1) bounding the patch.
      noise_model: the stored `NoiseModel`, or None (none stored; always None in format
        versions 1 and 2).
    """

    def __init__(
        self, path: pathlib.Path, file: h5py.File | None, header: dict, arrays: dict, illuminant: str | None = None
    ):
        self.path, self.header = path, header
        if "wiener_offset" not in arrays:
            # Format version 1 (its checksum, verified before, covers no offset): the estimate
            # was linear, r = W v_tilde, i.e. r0 = 0.
            arrays = {**arrays, "wiener_offset": np.zeros(N_WAVELENGTHS, np.float32)}
        self._file, self._arrays = None, arrays  # the file is owned once the checks below pass
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
            for name in PARAMETERS:
                # Small arrays read whole: a NaN or infinity there makes every reflectance NaN.
                # The check Calibration makes when built, here before any frame is read.
                require_finite(name, self._value(name))
            from ..pipeline import patch_bounding_box

            self.patch_box = patch_bounding_box(self._value("patch"))
            if self.patch_box is None:
                raise ValueError("patch: the mask selects no pixel; expected at least one True entry")
            self._patch_calibration = self._crop(*self.patch_box)
            crop = self._patch_calibration
            _require_usable_patch(path, np.asarray(crop.dark), np.asarray(crop.white), np.asarray(crop.patch))
        self._noise_model = noise_model_of(path, header)
        self._file = file

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
        file, self._file = getattr(self, "_file", None), None
        if file is not None:
            file.close()

    def __del__(self):
        self.close()

    def __getstate__(self) -> dict:
        if self._file is None:
            return self.__dict__  # everything in memory
        # An open HDF5 file does not pickle (and a descriptor means nothing in another process).
        return {"reopen": (self.path, self._calibration_fields["illuminant"], self.header["checksum"])}

    def __setstate__(self, state: dict) -> None:
        if "reopen" not in state:
            self.__dict__.update(state)
            return
        path, illuminant, checksum = state["reopen"]
        opened = open_calibration(path, illuminant=illuminant)
        if opened.header["checksum"] != checksum:
            opened.close()
            raise CalibrationFileError(
                path, "changed since it was opened: another checksum", f"the calibration file of checksum {checksum}"
            )
        self.__dict__.update(opened.__dict__)
        opened._file = None  # this one owns the file now

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
    arrays up to `IN_MEMORY_BYTES`; the checksum is verified block by block. An .npz of format
    versions 1 to 3 is read whole.

    Before any data is read, each dataset's declared size is checked against what the file
    really stores (`_check_written`): a file declaring terabytes it never wrote is refused at
    once rather than checksummed for hours. Each block read or hashed is a safe point of
    `spherejax.interrupt`: inside `interrupt.stop_requests()`, SIGINT / SIGTERM stop a long
    verification with `interrupt.Interrupted` within a block.

    Args: as `load_calibration`, and illuminant: the Lab illuminant of the calibrations it
      gives, instead of the one the file names (None = the file's).
    Raises: as `load_calibration`; and `interrupt.Interrupted` on a stop request (SIGINT, SIGTERM
      inside `interrupt.stop_requests()`).
    """
    path = pathlib.Path(path)
    if not path.is_file():
        problem = "is not a file" if path.exists() else "no such file"
        raise CalibrationFileError(path, problem, _EXPECTED_FILE)
    container, stored = _container(path), None
    try:
        if container == "hdf5":
            # locking=False: HDF5's file locks fail on some network file systems, and a file is
            # never written in place (save_calibration renames a complete one over it).
            with _hdf5_errors(path):
                stored = h5py.File(path, "r", locking=False)
            raw_header, arrays = _index_hdf5(path, stored)
        else:
            raw_header, arrays = _read_npz(path)
        header = _decode_header(path, raw_header, container)
        _check_calibration_contents(path, header, arrays)
        version = header["format_version"]
        if (container == "hdf5") != (version >= _HDF5_SINCE):
            found = "HDF5" if container == "hdf5" else "an .npz archive"
            raise CalibrationFileError(
                path, f"is {found} of format version {version}",
                f"HDF5 from format version {_HDF5_SINCE} on, an .npz archive before",
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
            # Read before the checksum, which then hashes them in memory: each byte read once.
            if isinstance(array, _StoredArray) and array.nbytes <= IN_MEMORY_BYTES:
                arrays[name] = array.read()
        if _checksum(header, arrays) != header["checksum"]:
            raise CalibrationFileError(
                path,
                "does not match its checksum: tampered or corrupted",
                "the contents the checksum was computed from",
            )
        if stored is not None and not any(isinstance(array, _StoredArray) for array in arrays.values()):
            stored.close()  # everything is in memory: hold no open file
            stored = None
        return CalibrationFile(path, stored, header, arrays, illuminant)
    except BaseException:
        if stored is not None:
            stored.close()
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
      CalibrationFileError: missing, neither HDF5 nor .npz, truncated or corrupted, missing
        or unexpected arrays or header, datasets not stored as save_calibration stores them
        (filtered, in more chunks than it writes, or whose declared data the file does not store:
        past its end, or allocated and never written), another format, a newer format version, a checksum mismatch (tampered or corrupted), arrays that
        disagree with the header, a patch that is not a boolean mask, a "noise_model" that is
        not a valid noise model for its bands, other band centres than `band_centres_nm`, or
        contents that are not a valid `Calibration`.
    """
    with open_calibration(path, band_centres_nm=band_centres_nm) as opened:
        with _reraise_invalid(opened.path):
            return opened.calibration(), opened.header
