"""Opening and hashing inputs: the calibration (cached per process), an input's checksum and the
proof that the pixels read are the bytes hashed, the input opened for reading by strips."""

from __future__ import annotations

import functools
import hashlib
import os
import pathlib
import stat

from .. import io
from ..io.hashing import sha256_file
from .discovery import Identity, InputSpec, identity


@functools.lru_cache(maxsize=4)
def _calibration(path: str, stamp: tuple, illuminant: str | None) -> io.CalibrationFile:
    """The open calibration file, verified once per process (per file version and illuminant)."""
    return io.open_calibration(path, illuminant=illuminant)


def load_calibration(path, illuminant: str | None = None) -> io.CalibrationFile:
    """The open `io.CalibrationFile` of a calibration, cached per process; --illuminant applied."""
    path = pathlib.Path(path).resolve()
    try:
        stat = path.stat()
        # The file's identity too: another file renamed over it may keep the time and size
        # (cp -p, a tool that sets them), and the cache must not give the old one's contents.
        stamp = (stat.st_dev, stat.st_ino, stat.st_mtime_ns, stat.st_size)
    except OSError:
        stamp = None  # open_calibration names the problem
    return _calibration(str(path), stamp, illuminant)


def input_checksum(spec: InputSpec, max_bytes: tuple[int, str] | None = None) -> str:
    """SHA-256 (hex) over the bytes of the input's files, in order. A file larger than
    `max_bytes` is refused before any read (a sparse file claiming a terabyte would be read for
    hours). `max_bytes`: (the limit, the cube it is for, in words), `max_input_bytes`."""
    return hash_input(spec, max_bytes)[0]


# What says a name still leads to the file hashed is its identity, `discovery.identity` (st_dev,
# st_ino): os.replace (how a file is swapped for another, or a copy lands) gives the name another
# inode.
# Bytes appended in place (a copy still arriving) leave the pixels read those hashed (the image is
# what its header points at); the hash recorded then differs from the file's, so --resume
# corrects it again.


def hash_input(spec: InputSpec, max_bytes: tuple[int, str] | None = None) -> tuple[str, tuple[Identity, ...]]:
    """(SHA-256 hex over the input's files, each file's `identity` as hashed): the state lets
    `check_unchanged` prove afterwards that the pixels read came from the bytes hashed."""
    digest = hashlib.sha256()
    states = []
    for file in spec.files:
        if not _utf8_name(file):
            # OpenImageIO takes paths as UTF-8 text only; refused here, before any read, in words
            # rather than with its "incompatible function arguments".
            raise io.SpherejaxFileError(
                file, "has a name that is not UTF-8 text, which OpenImageIO cannot open",
                "a cube file whose name is UTF-8: rename it",
            )
        # The first read of an input. O_NONBLOCK: should a FIFO have taken the file's place since
        # discovery, the open returns at once instead of waiting for a writer; then it is refused
        # by what it is, before any read.
        try:
            fd = os.open(file, os.O_RDONLY | os.O_NONBLOCK)
        except OSError as error:
            gone = isinstance(error, FileNotFoundError)
            problem = "no such file (removed or renamed since the batch found it)" if gone else f"cannot be read: {error.strerror}"
            raise io.SpherejaxFileError(file, problem, "a readable cube file") from None
        with open(fd, "rb") as handle:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode):
                raise io.SpherejaxFileError(file, f"is {io.file_kind(st.st_mode)}", "a cube file")
            if max_bytes is not None and st.st_size > max_bytes[0]:
                raise io.SpherejaxFileError(
                    file, f"is {st.st_size} bytes, more than {max_bytes[1]} can take ({max_bytes[0]} at most)",
                    "a cube file",
                )
            sha256_file(handle, into=digest)  # 1 MiB blocks, each a safe point
            states.append(identity(st))
    return digest.hexdigest(), tuple(states)


def check_unchanged(spec: InputSpec, states: tuple[Identity, ...]) -> None:
    """Raise unless each of the input's files is still the file `hash_input` hashed.

    The hash is taken through one open and the pixels are read through OpenImageIO's own: an
    input replaced (os.replace) or rewritten in between would give outputs of the new pixels
    recorded under the old file's hash, which --resume would then trust. Checked once the pixels
    are read and before the outputs go into place, so such an input fails and leaves nothing.
    """
    for file, state in zip(spec.files, states, strict=True):
        try:
            now = identity(os.stat(file))
        except OSError as error:
            now = error.strerror
        if now != state:
            raise io.SpherejaxFileError(
                file, "was replaced while it was corrected: its outputs would not match its hash",
                "an input left alone until it is corrected; run again with --resume",
            )


def _utf8_name(path) -> bool:
    """True if `path` is UTF-8 text (a name with other bytes reaches Python as lone surrogates)."""
    try:
        os.fsencode(path).decode("utf-8")
    except UnicodeDecodeError:
        return False
    return True


def max_input_bytes(calibration: io.CalibrationFile) -> tuple[int, str]:
    """The most bytes one input file may hold: the calibration's cube in 64-bit samples, twice
    over (any layout, compression that grew the data, metadata), and 64 MiB to spare
    (`io.frames.image_byte_limit`, the limit every cube reader applies)."""
    from ..io.frames import image_byte_limit

    height, width = calibration.image_shape
    cube = f"a {height} x {width} x {calibration.bands} cube"
    return image_byte_limit((height, width, calibration.bands)), cube


def open_input(spec: InputSpec, calibration: io.CalibrationFile) -> io.CubeReader:
    """The input opened for reading by strips, after checking it against the calibration."""
    header = calibration.header
    bands = header["band_centres_nm"]
    shape = (*calibration.image_shape, calibration.bands)
    if spec.instrument_id is not None and spec.instrument_id != header["instrument_id"]:
        raise io.SpherejaxFileError(
            spec.files[0],
            f"was taken on instrument {spec.instrument_id!r}, the calibration was built for "
            f"{header['instrument_id']!r}",
            "a calibration of the session's instrument",
        )
    if spec.kind == "bands":
        if list(spec.band_centres_nm) != list(bands):
            raise io.SpherejaxFileError(
                spec.source,
                f"has band files for {list(spec.band_centres_nm)} nm",
                f"one file per calibration band, {bands} nm",
            )
        return io.open_band_files(spec.files, expected_shape=shape)
    return io.open_cube(spec.files[0], expected_shape=shape, band_centres_nm=bands)


__all__ = ["check_unchanged", "hash_input", "input_checksum", "load_calibration", "max_input_bytes", "open_input"]
