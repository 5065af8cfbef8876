"""What the libraries that read and write spherejax's files say about a damaged file, put in
spherejax's words: the problem part of a `SpherejaxFileError` ("PATH: problem (expected ...)").

OpenImageIO (and libtiff, OpenEXR and libpng under it) and h5py (HDF5) describe a damaged file in
their own terms, meant for their developers:

    Read error at scanline 4294967295; got 16460 bytes, expected 45643
    EXR Error (/data/a.exr): EXR_ERR_READ_IO End of file attempting to read header EXR Error ...
    Unable to synchronously open file (truncated file: eof = 1000, sblock->base_addr = 0, ...)

(4294967295 is libtiff's row counter at -1, read as unsigned: OpenImageIO read the strip raw and
libtiff never set a row.) Each function here says instead what is wrong with the file in plain
words: truncated or corrupted, not an image of its format, which rows cannot be read, how many
bytes a strip or the file holds of those it should. The library's own words follow as a trailing
detail in parentheses only where they add something, cleaned to one line: without the path (the
message names the file already), OpenEXR's error codes or repeated sentences, and cut short.

The callers (`frames`, `cubes`, `corrected`, `calibration_files`) add the path and what was
expected; every function returns the problem alone.

`library_path` is the other half of talking to OpenImageIO: the path as the str its binding
takes. pybind11 encodes a str as UTF-8, while Python decodes file names with the locale's
encoding: under LC_ALL=C a name "rôt.tif" is 'r\\udcc3\\udcb4t.tif' (os.fsdecode's escapes), which
pybind11 refuses ("incompatible function arguments"), and bytes are no better. Decoded as UTF-8
instead, the str encodes back to the name's own bytes, so the file opens under any locale; a
name that is not UTF-8 at all cannot be given to OpenImageIO and is refused in one line. (h5py
takes Python's own str paths under every locale: it encodes them with os.fsencode.)
"""

from __future__ import annotations

import os
import pathlib
import re
import resource

#: A library's words kept as a detail are cut to this many characters.
_DETAIL_LENGTH = 160
#: The library under OpenImageIO that reads or writes each of its formats (`ImageInput.format_name`).
_FORMAT_LIBRARIES = {"tiff": "libtiff", "openexr": "OpenEXR", "png": "libpng"}


def library_path(path: os.PathLike | str, expected: str = "a file whose name is UTF-8 text: rename it") -> str:
    """`path` as the str OpenImageIO's binding opens (module docstring): its bytes as UTF-8.

    Raises:
      SpherejaxFileError: the name's bytes are not UTF-8, naming the file.
    """
    raw = os.fsencode(path)
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        from .errors import SpherejaxFileError

        raise SpherejaxFileError(path, "has a name that is not UTF-8 text, which OpenImageIO cannot open",
                                 expected) from None


def library_text(text: str) -> str:
    """`text` with no lone surrogates, for what encodes text as UTF-8 (OpenImageIO's attributes,
    a calibration's or a manifest's JSON): a name decoded under a non-UTF-8 locale holds
    os.fsdecode's surrogates for its bytes, which become the characters those bytes spell in UTF-8
    ("rôt"), or \\xNN escapes where they are not UTF-8. Text without surrogates is returned as is."""
    if not any("\ud800" <= c <= "\udfff" for c in text):
        return text
    try:
        raw = text.encode("utf-8", "surrogateescape")
    except UnicodeEncodeError:  # a surrogate no file name gives (from a JSON escape, say)
        return text.encode("utf-8", "backslashreplace").decode("utf-8")
    return raw.decode("utf-8", "backslashreplace")


def _size(path) -> int | None:
    try:
        return os.stat(path).st_size
    except OSError:
        return None


def _without_paths(text: str, paths) -> str:
    for path in paths:
        if path is not None and str(path):
            text = text.replace(f'"{path}"', "").replace(f"'{path}'", "").replace(str(path), "")
    return text


def library_detail(text, *paths) -> str:
    """A library's message as one line of its own words: the `paths` it quotes removed, OpenEXR's
    "EXR Error (PATH): EXR_ERR_CODE" prefixes dropped, each sentence once, at most
    `_DETAIL_LENGTH` characters. "" when nothing is left."""
    text = _without_paths(" ".join(str(text).split()), paths)
    parts = [part for part in re.split(r"EXR Error \(\s*\):?\s*", text)]
    kept: list[str] = []
    for part in parts:
        part = re.sub(r"\bEXR_ERR_[A-Z_]+\s*", "", part)
        part = re.sub(r"^(Could not open file|PNG read error|PNG library error|OpenEXR exception):?\s*", "", part.strip())
        part = part.strip(" :;,.")
        if part and part not in kept:
            kept.append(part)
    detail = "; ".join(kept)
    detail = re.sub(r"\s+", " ", detail).strip()
    if len(detail) > _DETAIL_LENGTH:
        detail = detail[: _DETAIL_LENGTH - 3].rstrip() + "..."
    return detail


def _format_library(format_name: str | None, path) -> str:
    if format_name in _FORMAT_LIBRARIES:
        return _FORMAT_LIBRARIES[format_name]
    suffix = pathlib.Path(str(path)).suffix.lower()
    return {".tif": "libtiff", ".tiff": "libtiff", ".exr": "OpenEXR", ".png": "libpng"}.get(suffix, "OpenImageIO")


def _bytes(n: int | None) -> str:
    return "an unknown number of bytes" if n is None else "1 byte" if n == 1 else f"{n} bytes"


# ------------------------------------------------------------------------- images: opening


def image_open_problem(path, message) -> str:
    """Why OpenImageIO could not open `path` as an image (`ImageInput.open` gave None and
    `message`): empty, too short for its format's header, not of the format its name or first
    bytes say, or a header that is truncated or corrupted."""
    text = " ".join(str(message or "").split())
    size = _size(path)
    if size == 0:
        return "is empty"
    detail = library_detail(text, path)
    # TIFF (libtiff's words)
    if "Cannot read TIFF header" in text:
        if size is not None and size < 8:
            return (f"is not a readable image: it holds {_bytes(size)}, fewer than the 8 of a TIFF header "
                    "(a TIFF cut short, or no TIFF at all)")
        return "is truncated or corrupted: its TIFF header cannot be read"
    if "Not a TIFF" in text and "magic number" in text:
        return "is not a readable image: it does not start as a TIFF does (with II*\\0 or MM\\0*)"
    match = re.search(r"Failed to read (?:custom )?directory at offset (\d+)", text)
    if match:
        offset = int(match.group(1))
        directory = "its TIFF directory (the table of the image's size and layout)"
        if size is not None and offset >= size:
            return f"is truncated or corrupted: {directory} should start at byte {offset}, past the end of its {_bytes(size)}"
        return f"is truncated or corrupted: {directory}, at byte {offset} of its {_bytes(size)}, cannot be read"
    match = re.search(r'IO error during reading of "([^"]+)"', text)
    if match:
        return (f"is truncated or corrupted: the {match.group(1)} field of its TIFF directory cannot be read "
                f"from its {_bytes(size)}")
    # OpenEXR. Its words differ by release: "EXR Error (PATH): EXR_ERR_..." through OpenImageIO
    # 3.2, "OpenEXR exception: ..." or a bare "is not an OpenEXR file" through 3.1.
    if "is not an OpenEXR file" in text:
        return "is not a readable image: it does not start with the OpenEXR signature"
    if "OpenEXR exception" in text:
        if re.search(r"Unable to open .*for read", text):  # "Unable to open 'PATH' for read"
            return f"is truncated or corrupted: its OpenEXR header cannot be read (it holds {_bytes(size)})"
        return f"is truncated or corrupted: its OpenEXR header is invalid (OpenEXR: {detail.split('; ')[0]})"
    if "EXR Error" in text or "EXR_ERR_" in text:
        if "Unable to read magic and version flags" in text and size is not None and size < 8:
            return (f"is not a readable image: it holds {_bytes(size)}, fewer than the 8 of an OpenEXR "
                    "signature (an OpenEXR cut short, or none at all)")
        if "is not an OpenEXR file" in text:
            return "is not a readable image: it does not start with the OpenEXR signature"
        if "End of file" in text:
            return f"is truncated or corrupted: it ends inside its OpenEXR header (it holds {_bytes(size)})"
        first = detail.split("; ")[0]
        return f"is truncated or corrupted: its OpenEXR header is invalid (OpenEXR: {first})"
    # PNG (libpng's words, through OpenImageIO)
    if "Not a PNG file" in text:
        return "is not a readable image: it does not start with the PNG signature"
    if "PNG" in text or "png" in text:
        chunk = re.search(r"PNG read error: ([A-Za-z]{4}): ", text)
        of_chunk = f" its {chunk.group(1)} chunk" if chunk else " a chunk"
        if "hit end of file" in text:
            return f"is truncated or corrupted: it ends inside{of_chunk} (it holds {_bytes(size)})"
        if "CRC error" in text:
            return f"is corrupted:{of_chunk} fails its CRC check (its bytes were altered)"
        if "invalid type" in text:
            return "is corrupted: a chunk of it has no valid chunk type (its bytes were altered)"
        return f"is truncated or corrupted: its PNG data are invalid (libpng: {detail})"
    if "could not find a format reader" in text:
        return "is not a readable image: its format is none OpenImageIO reads"
    # libtiff on a directory it reads but refuses, and anything else
    if pathlib.Path(str(path)).suffix.lower() in (".tif", ".tiff") and detail:
        return f"is truncated or corrupted: its TIFF directory is invalid (libtiff: {detail})"
    return f"is not a readable image ({detail})" if detail else "is not a readable image"


# ------------------------------------------------------------------------- images: pixels


def _rows(row0: int, row1: int, height: int) -> str:
    if row1 - row0 == 1:
        return f"row {row0} of its {height}"
    return f"rows {row0} to {row1 - 1} of its {height}"


def image_read_problem(path, message, row0: int, row1: int, height: int, format_name: str | None = None) -> str:
    """Why OpenImageIO could not read rows row0:row1 of an image `height` rows tall whose header
    it read (`message`: its error, maybe empty): data cut short or that cannot be decoded. The
    rows are those asked for; libtiff's own row number is not trusted (OpenImageIO reads whole
    strips raw, and libtiff's counter then says 4294967295 or a row read before)."""
    text = " ".join(str(message or "").split())
    where = _rows(row0, row1, height)
    short = re.search(r"got (\d+) bytes, expected (\d+)", text)
    if short:
        got, wanted = int(short.group(1)), int(short.group(2))
        return (f"is truncated or corrupted: {where} cannot be read: a strip of their pixel data stops "
                f"after {got} of its {wanted} bytes (the file holds {_bytes(_size(path))})")
    decoding = re.search(r"Decoding error at scanline \d+,?\s*(.*)", text)
    if decoding:
        reason = library_detail(decoding.group(1), path)
        return (f"is corrupted: the compressed pixel data of {where} cannot be decoded"
                + (f" (zlib: {reason})" if reason else ""))
    if "chunks were missing or corrupted" in text or "Failed OpenEXR read" in text:
        # (OpenImageIO 3.1 says "Failed OpenEXR read: Unable to query scanline information".)
        return (f"is truncated or corrupted: the pixel data of {where} are missing or cannot be decoded "
                f"(the file holds {_bytes(_size(path))})")
    detail = library_detail(text, path)
    if not detail:
        # OpenImageIO 3.1 reads a cut TIFF strip without a word: whether the data stop short or
        # are garbled, the rows cannot be decoded.
        return f"is truncated or corrupted: {where} cannot be decoded (the file holds {_bytes(_size(path))})"
    return f"is truncated or corrupted: the pixel data of {where} cannot be read ({_format_library(format_name, path)}: {detail})"


def complete_image(format_name: str | None, shape, pages: int = 1) -> str:
    """What an image whose header was read should be, for the "expected" of a pixel error: "a
    complete 16-bit TIFF of 40 x 48 pixels and 16 channels"."""
    height, width, channels = (int(n) for n in shape)
    kind = {"tiff": "16-bit TIFF", "openexr": "OpenEXR", "png": "PNG"}.get(format_name or "", "image")
    if pages > 1:
        return f"a complete {kind} of {pages} pages of {height} x {width} pixels"
    plural = "channel" if channels == 1 else "channels"
    return f"a complete {kind} of {height} x {width} pixels and {channels} {plural}"


# ------------------------------------------------------------------------- images: writing


def image_write_problem(path, temporary, message, format_name: str | None = None) -> str:
    """Why OpenImageIO could not write `path` (through its `temporary` file): the disk full, the
    process's file-size limit reached, or what the library said."""
    cause = write_limit(temporary if temporary is not None else path)
    if cause is not None:
        return f"could not be written: {cause}"
    detail = library_detail(message, temporary, path)
    library = _format_library(format_name, path)
    return f"could not be written ({library}: {detail})" if detail else "could not be written"


def write_limit(path) -> str | None:
    """Why a write to `path` may have stopped, when something outside the file says so: the
    process's file-size limit (ulimit -f) reached, or no room left on its disk; else None."""
    size = _size(path)
    soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    if size is not None and soft != resource.RLIM_INFINITY and size >= soft:
        return f"it reached {soft} bytes, the largest file this process may write (ulimit -f)"
    try:
        found = os.statvfs(pathlib.Path(str(path)).parent)
    except OSError:
        return None
    if found.f_bavail * found.f_frsize < (1 << 16):
        return "the disk that holds it is full"
    return None


# ------------------------------------------------------------------------------------- HDF5


def _hdf5_action(major: str, dataset: str | None) -> str:
    major = major.lower()
    if "open file" in major:
        return "read the superblock at its start, which locates everything else in it"
    if "iterat" in major:
        return "list the entries it holds"
    if "attribute" in major:
        return "read its attributes, where the header is"
    if "read data" in major:
        return f"read the data of dataset {dataset!r}" if dataset else "read the data of a dataset"
    if "object" in major:
        return "open one of the entries it holds"
    return "read it"


def hdf5_problem(error: BaseException, dataset: str | None = None) -> str:
    """What h5py's `error` on a damaged file means: "is truncated: it holds 1000 of the 265884
    bytes its HDF5 superblock records", or "is truncated or corrupted: HDF5 cannot ... (HDF5:
    its reason)"; `dataset` names the dataset being read, if any."""
    if isinstance(error, UnicodeDecodeError):
        return "is corrupted: a name stored in it is not UTF-8 text"
    raw = error.args[0] if isinstance(error, KeyError) and error.args else error
    text = " ".join(str(raw).split())
    truncated = re.search(r"truncated file: eof = (\d+),.*stored_eof = (\d+)", text)
    if truncated:
        return (f"is truncated: it holds {int(truncated.group(1))} of the {int(truncated.group(2))} bytes "
                "its HDF5 superblock records")
    major, _, minor = text.partition(" (")
    minor = minor.removesuffix(")")
    reason = library_detail(minor or major)
    action = _hdf5_action(major, dataset)
    return f"is truncated or corrupted: HDF5 cannot {action}" + (f" (HDF5: {reason})" if reason else "")


__all__ = [
    "complete_image", "hdf5_problem", "image_open_problem", "image_read_problem", "image_write_problem",
    "library_detail", "library_path", "library_text", "write_limit",
]
