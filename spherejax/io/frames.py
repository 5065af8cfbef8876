"""Camera frames: single-page 16-bit TIFFs of (H, W, C), channel names and attributes in their
ImageDescription, and `AtomicImageWriter`, the row-strip image writer every image output uses."""

from __future__ import annotations

import contextlib
import functools
import json
import os
import pathlib
import stat
from collections.abc import Iterator, Sequence

import numpy as np
import OpenImageIO as oiio

from .. import jsontext
from .atomic_writer import AtomicWriter
from .errors import SpherejaxFileError, _show
from .hashing import sha256_file
from .library_messages import (
    complete_image, image_open_problem, image_read_problem, image_write_problem, library_path, library_text,
    write_limit,
)
from .plain_files import file_kind

_FRAME_EXPECTED = "a single-page 16-bit TIFF of shape (H, W, C)"
_RESERVED_ATTRIBUTES = ("ImageDescription",)

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


def image_byte_limit(shape) -> int:
    """The most bytes an image file of `shape` (H, W, C) may hold: its samples as 64-bit values,
    twice over (any layout, compression that grew the data, metadata), and 64 MiB to spare."""
    return 2 * int(np.prod([int(n) for n in shape])) * 8 + (64 << 20)


def require_image_file(path: pathlib.Path, expected: str, shape=None) -> None:
    """Refuse, before OpenImageIO opens it, a path that is missing, not a regular file (a FIFO
    would be waited on, a device read forever) or, given the `shape` (H, W, C) it must have,
    larger than `image_byte_limit` (OpenImageIO tries its readers in turn on a file it does not
    know, and some read all of it: a 5 GB sparse file took minutes)."""
    try:
        found = os.stat(path)
    except FileNotFoundError:
        raise SpherejaxFileError(path, "no such file", expected) from None
    except OSError as error:
        raise SpherejaxFileError(path, f"cannot be read: {error.strerror}", expected) from None
    if not stat.S_ISREG(found.st_mode):
        raise SpherejaxFileError(path, f"is {file_kind(found.st_mode)}", expected)
    if shape is not None and found.st_size > image_byte_limit(shape):
        what = " x ".join(str(int(n)) for n in shape)
        raise SpherejaxFileError(
            path, f"is {found.st_size} bytes, more than a {what} image can take ({image_byte_limit(shape)} at most)",
            expected,
        )


@_refuse_undecodable_text(_FRAME_EXPECTED)
def _open_checked_frame(path: pathlib.Path) -> oiio.ImageInput:
    """An open ImageInput on a checked camera frame (one page, uint16 samples); the caller closes it."""
    require_image_file(path, _FRAME_EXPECTED)
    image = oiio.ImageInput.open(library_path(path, _FRAME_EXPECTED))
    if image is None:
        raise SpherejaxFileError(path, image_open_problem(path, oiio.geterror()), _FRAME_EXPECTED)
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
            detail = image.geterror() or oiio.geterror()
            problem = image_read_problem(path, detail, 0, shape[0], shape[0], image.format_name())
            raise SpherejaxFileError(path, problem, complete_image(image.format_name(), shape))
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
        stored = jsontext.loads(description)  # strict: a key given twice is not write_frame's JSON
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
    attributes = {key: library_text(value) for key, value in attributes.items()}  # names under LC_ALL=C
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


#: The last 12 bytes of every complete PNG: the IEND chunk (length 0, type, CRC).
_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"


class AtomicImageWriter(AtomicWriter):
    """One image written through OpenImageIO in row strips under a temporary name beside `path`,
    made the file by `commit` (fsync, then rename) only once every row is written
    (`atomic_writer.AtomicWriter`: the state machine every image writer shares).

    The temporary name is first created with O_EXCL, so it can never be an existing file or a
    link to one elsewhere; OpenImageIO then rewrites that fresh, empty file. Leaving the `with`
    block without `commit` (an error, a strip never written) removes the temporary file, and an
    existing `path` is untouched. Rows must be written in order, top to bottom; the bytes do not
    depend on how the rows are split into strips (tested).
    """

    def __init__(self, path, spec: oiio.ImageSpec, format_name: str):
        self._spec = spec
        self._format = format_name
        self._output = None
        super().__init__(path, spec.height)

    def _open(self) -> None:
        library_path(self.path)  # a name OpenImageIO cannot take: refused before the temporary file exists
        self._create(self.path)
        # The format is named, not guessed from the temporary file's extension.
        output = oiio.ImageOutput.create(self._format)
        if output is None or not output.open(library_path(self._temp), self._spec):
            detail = output.geterror() if output is not None else oiio.geterror()
            problem = image_write_problem(self.path, self._temp, detail, self._format)
            self.abort()
            raise SpherejaxFileError(self.path, problem)
        self._output = output

    def _write_rows(self, row0: int, pixels: np.ndarray) -> None:
        """Rows row0:row0 + len(pixels), (rows, W, C)."""
        if not self._output.write_scanlines(row0, row0 + len(pixels), 0, np.ascontiguousarray(pixels)):
            problem = image_write_problem(self.path, self._temp, self._output.geterror(), self._format)
            self.abort()
            raise SpherejaxFileError(self.path, problem)

    def _complete(self) -> str:
        """Close the image, hash it and fsync it; return its SHA-256 (hex)."""
        output, self._output = self._output, None
        if not output.close():
            raise SpherejaxFileError(self.path, image_write_problem(self.path, self._temp, output.geterror(), self._format))
        with open(self._temp, "rb") as file:
            digest = sha256_file(file, check=None)  # past the last safe point: never stopped here
            file.seek(max(file.tell() - len(_PNG_END), 0))
            tail = file.read()
            os.fsync(file.fileno())  # on disk before the rename makes it the file
        if self._format == "png" and tail != _PNG_END:
            # OpenImageIO's PNG writer reports no failed write (a full disk, a file-size
            # limit): the file is known whole only by ending in libpng's IEND chunk.
            cause = write_limit(self._temp) or "it stops short of its end (OpenImageIO reported no error)"
            raise SpherejaxFileError(self.path, f"could not be written: {cause}")
        return digest

    def _release(self) -> None:
        output, self._output = self._output, None
        if output is not None:
            output.close()
        super()._release()


def _write_image_atomic(path: pathlib.Path, spec, array: np.ndarray, format_name: str) -> str:
    """Write a whole image with `AtomicImageWriter`; return the SHA-256 (hex) of its bytes."""
    with AtomicImageWriter(path, spec, format_name) as writer:
        writer.write_rows(0, array)
        return writer.commit()
