"""The quality mask N.quality.png of `spherejax correct`: an indexed-colour PNG whose pixel values
(palette indices) are the quality bits (`pipeline.QUALITY_*`, 0 = good), so a program reads the
bits and a person opening it in any viewer sees the flagged pixels in colour on black.

A single-channel grey PNG of values 0..31 looks black everywhere. Here the pixels are the same
bytes, but the PNG is of colour type 3 (8-bit palette indices) with a 256-entry palette
(`PALETTE`): 0 is black, each flag bit has its own bright colour (`BIT_COLOURS`), and a value with
several bits set takes the colour of its highest bit (the bits are not ranked; the highest is
simply a rule a reader can apply by eye, and the value itself still holds every bit). A tEXt
chunk "Description" states the key (`KEY_TEXT`), so the file explains itself.

Written by hand (`QualityPngWriter`), not by a library, because the outputs are written in row
strips (`spherejax.stripwise`) and must be byte-identical whatever the strips: OpenImageIO, which
writes every other image here, has no palette PNG output (and reads palette PNGs back expanded
to RGB), and Pillow cannot write an image row by row. A PNG is simple enough: signature, IHDR,
PLTE, tEXt, IDAT (one zlib stream of filter byte 0 + row, fed one row at a time, so the bytes do
not depend on the strips), IEND; each chunk with its CRC-32 (`zlib.crc32`). No tIME chunk: a
rerun writes the same bytes.

Reading (`read_quality_png`) goes through Pillow, which decodes any PNG: palette files give their
indices, and the grey files earlier versions wrote (through OpenImageIO) their grey values; both
are the bits.
"""

from __future__ import annotations

import pathlib
import re
import struct
import zlib

import numpy as np

from .. import pipeline
from .errors import SpherejaxFileError
from .streamed_writer import StreamedImageWriter

_EXPECTED = "a spherejax quality PNG: 8-bit palette indices (or grey values) holding the quality bits"
_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Colour of each bit (RGB, name) and its meaning (pipeline.QUALITY_*; 64 and 128 are not used yet).
BIT_COLOURS = {
    pipeline.QUALITY_SATURATED: ((255, 0, 0), "red", "saturated (raw at or above the saturation level in some band)"),
    pipeline.QUALITY_NONFINITE: ((255, 0, 255), "magenta", "not finite (raw NaN or infinite in some band, float input)"),
    pipeline.QUALITY_WHITE_NOT_ABOVE_DARK: ((0, 255, 255), "cyan", "no flat field (white <= dark, or not finite, in some band)"),
    pipeline.QUALITY_PATCH_UNUSABLE: ((255, 255, 0), "yellow",
                                      "white patch unusable (its ratio not finite in some band: the whole image)"),
    pipeline.QUALITY_BELOW_DARK: ((0, 255, 0), "green",
                                  "below dark (raw below the dark level by more than noise allows in some band)"),
    pipeline.QUALITY_NOT_COVERED: ((255, 128, 0), "orange",
                                   "not covered (bands registered into one geometry: some band's image misses the pixel)"),
    64: ((96, 160, 255), "light blue", "not used"),
    128: ((255, 255, 255), "white", "not used"),
}
#: (256, 3) uint8: black for 0, else the colour of the value's highest bit.
PALETTE = np.array(
    [(0, 0, 0)] + [BIT_COLOURS[1 << (value.bit_length() - 1)][0] for value in range(1, 256)], dtype=np.uint8
)
#: The tEXt "Description" of every quality PNG.
KEY_TEXT = (
    "spherejax quality bits: each pixel value (palette index) is the sum of its flags; 0 = good (black). "
    + "; ".join(f"{bit} {name} = {meaning}" for bit, (_, name, meaning) in BIT_COLOURS.items() if meaning != "not used")
    + ". A pixel with several flags shows the colour of the highest."
)
#: IDAT chunks are written once this many compressed bytes are waiting.
_IDAT_BYTES = 1 << 16


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


class QualityPngWriter(StreamedImageWriter):
    """The quality PNG of shape (H, W) written in row strips, under a temporary name beside `path`
    made the file by `commit` (fsync, then rename) once every row is written
    (`streamed_writer`: the same interface and rules as `frames.AtomicImageWriter`). Rows in
    order, top to bottom; the bytes do not depend on the strips."""

    def __init__(self, path, shape, text=None):
        shape = tuple(int(n) for n in shape)
        if len(shape) == 3 and shape[-1] == 1:
            shape = shape[:2]
        if len(shape) != 2 or 0 in shape or max(shape) >= 2**31:
            raise SpherejaxFileError(pathlib.Path(path), f"cannot hold an image of shape {shape}", "(H, W) or (H, W, 1) uint8")
        height, self.width = shape
        self._pending = b""
        self._compressor = zlib.compressobj(9, zlib.DEFLATED, 15, 9, zlib.Z_DEFAULT_STRATEGY)
        super().__init__(path, height)
        from .. import __version__

        header = struct.pack(">IIBBBBB", self.width, self.height, 8, 3, 0, 0, 0)  # 8-bit palette, not interlaced
        self._write(
            _SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"PLTE", PALETTE.tobytes())
            + _chunk(b"tEXt", b"Description\0" + KEY_TEXT.encode("latin-1"))
            + _chunk(b"tEXt", b"Software\0" + f"spherejax {__version__}".encode("latin-1"))
            # More tEXt chunks (`text`: keyword -> Latin-1 value), e.g. the outputs' set (`io.corrected`).
            + b"".join(_chunk(b"tEXt", f"{key}\0{value}".encode("latin-1")) for key, value in (text or {}).items())
        )

    def _idat(self, data: bytes, final: bool = False) -> None:
        self._pending += data
        if len(self._pending) >= _IDAT_BYTES or (final and self._pending):
            pending, self._pending = self._pending, b""
            self._write(_chunk(b"IDAT", pending))

    def _write_rows(self, row0: int, pixels) -> None:
        """Rows row0:row0 + len(pixels), (rows, W) or (rows, W, 1) uint8."""
        pixels = np.asarray(pixels)
        if pixels.ndim == 3 and pixels.shape[-1] == 1:
            pixels = pixels[..., 0]
        if pixels.dtype != np.uint8 or pixels.ndim != 2 or pixels.shape[1] != self.width:
            raise ValueError(f"pixels: expected (rows, {self.width}) uint8, got {pixels.shape} {pixels.dtype}")
        if row0 + len(pixels) > self.height:
            raise ValueError(f"rows: the image has {self.height}, got rows up to {row0 + len(pixels)}")
        for row in pixels:
            # Filter type 0 (None) on every row, as the PNG specification advises for palette images.
            self._idat(self._compressor.compress(b"\0" + row.tobytes()))

    def _finish(self) -> None:
        self._idat(self._compressor.flush(), final=True)
        self._write(_chunk(b"IEND", b""))


def open_quality_png(path, shape, *, text=None) -> QualityPngWriter:
    """A `QualityPngWriter` for a quality mask of shape (H, W) or (H, W, 1); `text`: more tEXt
    chunks, keyword -> value (Latin-1)."""
    return QualityPngWriter(path, shape, text)


def write_quality_png(path, quality) -> str:
    """Write a whole (H, W) or (H, W, 1) uint8 quality mask, atomically; return its SHA-256 (hex)."""
    quality = np.asarray(quality)
    with QualityPngWriter(path, quality.shape) as writer:
        writer.write_rows(0, quality)
        return writer.commit()


def _read_problem(error: BaseException) -> str:
    """Pillow's words for a PNG it cannot read ("image file is truncated (0 bytes not processed)",
    "broken PNG file (bad header checksum in b'tEXt')", "not a PNG file") in plain ones."""
    text = " ".join(str(error).split())
    crc = re.search(r"checksum in b'([A-Za-z]{4})'", text)
    if crc:
        return f"is corrupted: its {crc.group(1)} chunk fails its CRC check"
    if "truncated" in text.lower() or isinstance(error, EOFError):
        return "is truncated: its pixel data stops before its last row"
    if "not a PNG file" in text or type(error).__name__ == "UnidentifiedImageError":
        return "is not a PNG file (it does not start with the PNG signature)"
    if isinstance(error, OSError) and error.strerror:
        return f"cannot be read: {error.strerror}"
    return f"is corrupted (Pillow: {text})"


def read_quality_png(path) -> np.ndarray:
    """The quality bits of a quality PNG, (H, W) uint8: the palette indices of one written by
    `QualityPngWriter`, the grey values of one written by an earlier spherejax (8-bit grey)."""
    from PIL import PngImagePlugin, UnidentifiedImageError

    path = pathlib.Path(path)
    try:
        # The PNG reader itself, not Image.open: that refuses images over 179 million pixels as
        # decompression bombs, and a camera's quality mask may be that large.
        with PngImagePlugin.PngImageFile(path) as image:
            if image.mode not in ("P", "L"):
                raise SpherejaxFileError(path, f"is a PNG of mode {image.mode}", _EXPECTED)
            pixels = np.asarray(image)
    except (OSError, SyntaxError, ValueError, UnidentifiedImageError, EOFError) as error:
        if isinstance(error, SpherejaxFileError):
            raise
        raise SpherejaxFileError(path, _read_problem(error), _EXPECTED) from None
    if pixels.dtype != np.uint8 or pixels.ndim != 2:
        raise SpherejaxFileError(path, f"holds pixels of shape {pixels.shape} and type {pixels.dtype}", _EXPECTED)
    return pixels


__all__ = ["BIT_COLOURS", "KEY_TEXT", "PALETTE", "QualityPngWriter", "open_quality_png", "read_quality_png",
           "write_quality_png"]
