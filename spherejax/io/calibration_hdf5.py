"""The HDF5 container of calibration files (format version 4 on; the docstring of spherejax.io):
how the datasets are laid out and written (`_write_hdf5`: frames in chunks of whole rows), which
container a file is (`_container`), a file indexed before any data is read (`_index_hdf5`,
`_check_written`: every declared byte stored in the file), arrays read by rows or block by block
(`_StoredArray`), and the checksum, hashed a block at a time in either container (`_checksum`)."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import itertools
import json
import math
import os
import pathlib
from collections.abc import Iterator, Mapping

import h5py
import numpy as np

from .. import interrupt
from ..atomic_files import atomic_file
from .calibration_checks import ARRAY_DESCRIPTIONS, _calibration_arrays
from .documents import _canonical_json, _readable_json
from .errors import CalibrationFileError, SpherejaxFileError, _show
from .library_messages import hdf5_problem, library_detail

#: How many bytes are read, inflated or hashed between two safe points (`spherejax.interrupt`).
_READ_BLOCK = 16 << 20

#: The first bytes of the two containers: HDF5 (format version 4 on; its superblock at offset 0,
#: where h5py puts it) and zip (the .npz of format versions 1 to 3).
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
ZIP_SIGNATURE = b"PK\x03\x04"
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


def _write_hdf5(path: pathlib.Path, header: dict, arrays: Mapping[str, np.ndarray]) -> None:
    """Write the checked header and arrays of `save_calibration` to `path` as HDF5, atomically:
    the header as the root's "header" attribute, each array a dataset with its description,
    the frame arrays in chunks of whole rows (`_row_chunks`). Raises CalibrationFileError on a
    failed write (the temporary file is removed; an existing file is untouched)."""
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
                    stored.create_dataset(name, data=array, chunks=chunks).attrs["description"] = ARRAY_DESCRIPTIONS[name]
            if keeping.error is not None:
                raise keeping.error
            # A safe point before the rename: a stop that came while HDF5 wrote (only recorded
            # there, `spherejax.interrupt`) leaves no file, the temporary removed.
            interrupt.check()
    except OSError as error:
        # Python's OSError (the first failed write, kept by _FailureKeepingFile) in its own words,
        # not "[Errno 28] No space left on device: 'PATH'"; h5py's as a cleaned detail.
        problem = f"could not be written: {error.strerror}" if error.strerror else f"could not be written (HDF5: {library_detail(error, path)})"
        raise CalibrationFileError(path, problem) from None
