"""The .npz container of calibration files of format versions 1 to 3 (the docstring of
spherejax.io), still read (whole, never unpickled); nothing writes it any more."""

from __future__ import annotations

import math
import pathlib
import tokenize
import zipfile
import zlib

import numpy as np

from .. import interrupt
from . import calibration_hdf5
from .errors import CalibrationFileError, SpherejaxFileError


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
            for start in range(0, raw.size, calibration_hdf5._READ_BLOCK):
                if start:
                    interrupt.check()
                block = data.read(min(calibration_hdf5._READ_BLOCK, raw.size - start))
                if len(block) != min(calibration_hdf5._READ_BLOCK, raw.size - start):
                    raise ValueError(f"member {member!r} ends before the array its header describes")
                raw[start:start + len(block)] = np.frombuffer(block, np.uint8)
    return array.reshape(shape[::-1]).transpose() if fortran_order else array.reshape(shape)
