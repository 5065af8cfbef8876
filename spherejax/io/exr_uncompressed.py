"""Uncompressed scanline OpenEXR files written here, the bytes OpenImageIO would write, faster.

Why not OpenImageIO for these. `spherejax correct` writes its EXR outputs uncompressed by
default (`io.EXR_COMPRESSIONS` says why), and there OpenImageIO is slow for what the format is:
a megapixel of 31-band reflectance took it 0.16-0.26 s to reorder into OpenEXR's per-channel
scanlines and hand to the page cache, and the commit then read the 130 MB back to hash them
(0.1 s more). Uncompressed, the file is a header, a table of scanline offsets and the scanlines
themselves, each (y, byte count, then every channel's row in the header's channel order); NumPy
reorders a strip in one copy, the bytes are hashed as they are made and written past the page
cache (`io.direct_io`). Compressed EXRs, and headers with attributes outside the set below,
stay with OpenImageIO (`io.open_exr` chooses).

The bytes are OpenImageIO 3's, attribute for attribute (tested byte for byte against it, float
and half, in tests/test_io_exr_uncompressed.py), so a file does not depend on which writer made
it, and every OpenEXR reader reads it. The layout, from "OpenEXR File Layout"
(openexr.com/en/latest/OpenEXRFileLayout.html):

    magic 20000630 (int32), version 2 (int32; flag 0x400 where a name is over 31 bytes)
    header: attributes (name NUL, type name NUL, int32 size, value) sorted by name, then NUL:
        channels (chlist, sorted by name), compression (0 = NO_COMPRESSION), dataWindow and
        displayWindow (box2i 0, 0, W-1, H-1), lineOrder (0 = INCREASING_Y), pixelAspectRatio 1,
        screenWindowCenter (0, 0), screenWindowWidth 1, and the string attributes
    offsets: uint64 per scanline, where its block starts
    blocks: int32 y, int32 byte count, the row of each channel in chlist order
                (float32: type 2, 4 bytes; half: type 1, 2 bytes; little-endian)
"""

from __future__ import annotations

import re
import struct
from collections.abc import Mapping, Sequence

import numpy as np

from .streamed_writer import StreamedImageWriter

#: OpenEXR pixel type codes (HALF, FLOAT) and the NumPy types of their samples.
_PIXEL_TYPES = {"half": (1, np.dtype("<f2")), "float": (2, np.dtype("<f4"))}
_MAGIC = 20000630
_LONG_NAMES = 0x400  # version flag: attribute or channel names of 32 to 255 bytes
_SHORT_NAME_BYTES = 31

#: String attributes this writer takes: spherejax's own ("spherejax:..." and the spectral
#: layout's version), which OpenImageIO writes under their names as string attributes. Other
#: names may be ones OpenImageIO renames or types (ImageDescription becomes "comments",
#: "oiio:..." is not written at all): `io.open_exr` sends a header with any of those to
#: OpenImageIO, so that the two writers never disagree.
_NAME_TAKEN = re.compile(r"spherejax:[A-Za-z0-9_]+|spectralLayoutVersion")


def takes_attributes(attributes: Mapping[str, str]) -> bool:
    """Whether this writer writes these string attributes as OpenImageIO would."""
    return all(_NAME_TAKEN.fullmatch(name) and isinstance(value, str) for name, value in attributes.items())


def _attribute(name: str, type_name: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + type_name.encode() + b"\0" + struct.pack("<i", len(value)) + value


def _header(height: int, width: int, channel_names: Sequence[str], pixel_type: int, attributes: Mapping[str, str]) -> bytes:
    """The magic number, version and header of an uncompressed scanline EXR (module docstring)."""
    channels = b"".join(name.encode() + b"\0" + struct.pack("<iB3xii", pixel_type, 0, 1, 1) for name in channel_names) + b"\0"
    window = struct.pack("<iiii", 0, 0, width - 1, height - 1)
    fields = [
        ("channels", "chlist", channels),
        ("compression", "compression", b"\0"),
        ("dataWindow", "box2i", window),
        ("displayWindow", "box2i", window),
        ("lineOrder", "lineOrder", b"\0"),
        ("pixelAspectRatio", "float", struct.pack("<f", 1.0)),
        ("screenWindowCenter", "v2f", struct.pack("<ff", 0.0, 0.0)),
        ("screenWindowWidth", "float", struct.pack("<f", 1.0)),
        *((name, "string", value.encode()) for name, value in attributes.items()),
    ]
    # OpenEXR's header is a map ordered by name (strcmp): its writer puts them in that order.
    header = b"".join(_attribute(*field) for field in sorted(fields, key=lambda field: field[0].encode())) + b"\0"
    names = [*channel_names, *attributes]
    long_names = any(len(name.encode()) > _SHORT_NAME_BYTES for name in names)
    return struct.pack("<ii", _MAGIC, 2 | (_LONG_NAMES if long_names else 0)) + header


class UncompressedExrWriter(StreamedImageWriter):
    """An uncompressed scanline OpenEXR (H, W, C) written in row strips under a temporary name,
    renamed into place by `commit` once every row is written (`streamed_writer`: the same
    interface and guarantees as `io.AtomicImageWriter`, which `io.open_exr` returns for
    compressed files).

    Args:
      path: the file to write.
      shape: (H, W, C).
      channel_names: C names, in the order of the rows' last axis (stored sorted, as OpenEXR
        requires).
      attributes: string attributes (`takes_attributes`).
      pixel_type: "float" or "half" (float32 rows rounded to nearest, as OpenEXR's half does).
    """

    def __init__(self, path, shape: Sequence[int], *, channel_names: Sequence[str],
                 attributes: Mapping[str, str] | None = None, pixel_type: str = "float"):
        height, self.width, channels = (int(n) for n in shape)
        attributes = dict(attributes or {})
        if not takes_attributes(attributes):
            raise ValueError(f"attributes: only {_NAME_TAKEN.pattern} with string values, got {sorted(attributes)}")
        code, sample = _PIXEL_TYPES[pixel_type]
        names = list(channel_names)
        # OpenEXR stores channels sorted by name (byte order); rows arrive in the caller's order.
        self._order = sorted(range(channels), key=lambda i: names[i].encode())
        header = _header(height, self.width, [names[i] for i in self._order], code, attributes)
        row_bytes = 8 + channels * self.width * sample.itemsize
        offsets = np.arange(height, dtype="<u8") * row_bytes + len(header) + 8 * height
        self._block = np.dtype([("y", "<i4"), ("size", "<i4"), ("rows", sample, (channels, self.width))])
        self._blocks: np.ndarray | None = None  # the last strip's scanline blocks, reused
        super().__init__(path, height)
        self._write(header)
        self._write(offsets)

    def _write_rows(self, row0: int, pixels) -> None:
        rows = len(pixels)
        if self._blocks is None or len(self._blocks) != rows:
            self._blocks = np.empty(rows, self._block)
        blocks = self._blocks
        blocks["y"] = np.arange(row0, row0 + rows)
        blocks["size"] = self._block["rows"].itemsize
        # (rows, W, C) -> (rows, C sorted, W): the one reordering copy (and the rounding to half);
        # channels already sorted (spherejax's are) are not gathered first (0.03 s a megapixel).
        pixels = np.asarray(pixels)
        if self._order != sorted(self._order):
            pixels = pixels[:, :, self._order]
        with np.errstate(over="ignore"):  # beyond half's range is inf, as OpenEXR makes it
            np.copyto(blocks["rows"], pixels.transpose(0, 2, 1), casting="same_kind")
        self._write(blocks)

    def _release(self) -> None:
        self._blocks = None
        super()._release()


__all__ = ["UncompressedExrWriter", "takes_attributes"]
