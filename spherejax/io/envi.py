"""ENVI images: a plain-text header (N.hdr) and raw pixels (N.img), the format hyperspectral
software reads (ENVI, Spectral Python, QGIS and GDAL, hylite).

What `spherejax correct --format envi` writes for each output (reflectance, Lab):

    ENVI
    description = { spherejax reflectance factor ... }
    samples = W, lines = H, bands = C, header offset = 0
    file type = ENVI Standard
    data type = 4                      float32
    interleave = bip                   band interleaved by pixel: (H, W, C) in C order, each
                                       pixel's spectrum contiguous, as spherejax holds it in
                                       memory; rows are appended strip by strip as corrected
    byte order = 0                     little-endian
    wavelength units = Nanometers      (reflectance only)
    wavelength = { 400 , 410 , ... }   (reflectance only)
    band names = { ... }
    data ignore value = -9999          flagged pixels (quality != 0), NaN in the EXR outputs
    reflectance scale factor = 1       (reflectance only) reflectance factors 0..1
    spherejax calibration checksum = sha256:...   and the other spherejax attributes, one per
                                       line ("spherejax:name_of_it" becomes "spherejax name of it";
                                       control characters as spaces, braces as parentheses: ENVI
                                       headers have no escapes)

Both files are written under temporary names (`spherejax.atomic_files`) and renamed into place
together, the data first and the header last, once every row is written. The pixels are written
past the page cache where the system allows it (`io.direct_io`: they are fsynced before the
rename anyway, and the kernel's copy into the cache was most of this writer's time).

The header text is written by Spectral Python's `write_envi_header` and read back by its
`read_envi_header` (the library the field uses for ENVI); the pixels are appended here, strip by
strip, because its `create_image` writes in place through a memory map, with no temporary name.
"""

from __future__ import annotations

import os
import pathlib
from collections.abc import Mapping, Sequence

import numpy as np

from .atomic_writer import AtomicWriter
from .errors import SpherejaxFileError
from .hashing import sha256_file

#: The value flagged pixels hold in ENVI outputs ("data ignore value"): NaN is not a value every
#: ENVI reader can compare against.
IGNORE_VALUE = -9999.0
_FLOAT32 = 4  # ENVI "data type" code of IEEE float32
_ATTRIBUTE_PREFIX = "spherejax:"


def _header_key(name: str) -> str:
    """"spherejax:calibration_checksum" -> "spherejax calibration checksum" (ENVI keys are words)."""
    if name.startswith(_ATTRIBUTE_PREFIX):
        return "spherejax " + name[len(_ATTRIBUTE_PREFIX):].replace("_", " ")
    return name


def _attribute_name(key: str) -> str:
    """The reverse of `_header_key` for spherejax's keys."""
    if key.startswith("spherejax "):
        return _ATTRIBUTE_PREFIX + key[len("spherejax "):].replace(" ", "_")
    return key


def _header_value(text: str) -> str:
    """A header value on one line and outside braces: ENVI has no escapes, and a newline or a
    brace (in a file name, say) would end the value or a {...} block early."""
    text = "".join(c if c.isprintable() else " " for c in text)
    return text.replace("{", "(").replace("}", ")")


def data_path(header_path) -> pathlib.Path:
    """N.img for N.hdr: the name Spectral Python, ENVI and GDAL look for first."""
    return pathlib.Path(header_path).with_suffix(".img")


class EnviWriter(AtomicWriter):
    """One float32 ENVI image (BIP) written in row strips: N.img and N.hdr under temporary names,
    both renamed into place by `commit` once every row is written, the data first
    (`atomic_writer.AtomicWriter`, as `AtomicImageWriter`). Errors name N.hdr (`path`), a failed
    write of the pixels N.img."""

    def __init__(self, header_path, shape: Sequence[int], *, description: str, band_names: Sequence[str],
                 wavelengths_nm: Sequence[float] | None = None, attributes: Mapping[str, str] | None = None):
        self.header_path = pathlib.Path(header_path)
        self.data_path = data_path(self.header_path)
        height, width, channels = (int(n) for n in shape)
        if len(band_names) != channels:
            raise ValueError(f"band_names: {len(band_names)} names for {channels} channels")
        self.width, self.channels = width, channels
        self.header = {
            "description": _header_value(description),
            "samples": width, "lines": height, "bands": channels, "header offset": 0,
            "file type": "ENVI Standard", "data type": _FLOAT32, "interleave": "bip", "byte order": 0,
        }
        if wavelengths_nm is not None:
            self.header["wavelength units"] = "Nanometers"
            self.header["wavelength"] = [float(nm) for nm in wavelengths_nm]
            self.header["reflectance scale factor"] = 1
        self.header["band names"] = list(band_names)
        self.header["data ignore value"] = IGNORE_VALUE
        for name, value in (attributes or {}).items():
            self.header[_header_key(name)] = _header_value(str(value))
        self._scratch: np.ndarray | None = None  # the last strip's rows with NaN replaced, reused
        super().__init__(self.header_path, height, targets=[self.data_path, self.header_path])

    def _open(self) -> None:
        self._create(self.header_path)
        # Past the page cache where the system allows it (`AtomicWriter._open_stream`).
        self._open_stream(self.data_path)

    def _write_rows(self, row0: int, pixels: np.ndarray) -> None:
        """Rows row0:row0 + len(pixels), (rows, W, C); NaN becomes the data ignore value."""
        pixels = np.asarray(pixels, dtype="<f4")
        if pixels.shape[1:] != (self.width, self.channels):
            raise ValueError(f"pixels: expected (rows, {self.width}, {self.channels}), got {pixels.shape}")
        # NaN replaced in a buffer kept from strip to strip (a new array each strip cost its
        # page faults again: np.where took 0.03-0.07 s a megapixel of reflectance, this 0.02 s),
        # handed on as a memoryview (`tobytes` would copy it once more).
        if self._scratch is None or self._scratch.shape != pixels.shape:
            self._scratch = np.empty(pixels.shape, "<f4")
        values = self._scratch
        np.copyto(values, pixels)
        np.copyto(values, np.float32(IGNORE_VALUE), where=np.isnan(pixels))
        self._write(values)

    def _complete(self) -> dict[pathlib.Path, str]:
        """Both files finished and fsynced; {path: SHA-256 (hex)} of N.img and N.hdr."""
        from spectral.io.envi import write_envi_header

        data_digest = self._close_stream()
        header_temp = self._temps[self.header_path]
        write_envi_header(str(header_temp), self.header)
        with open(header_temp, "rb") as handle:
            header_digest = sha256_file(handle, check=None)  # past the last safe point
            os.fsync(handle.fileno())
        return {self.data_path: data_digest, self.header_path: header_digest}

    def _release(self) -> None:
        self._scratch = None
        super()._release()


def _check_header_against_data(header_path: pathlib.Path, image, kind: str) -> None:
    """Refuse a header whose sizes, offset or data type do not describe its data file as
    spherejax writes it (float32, no gaps): Spectral Python maps such a file to None or past its
    end (samples 2e6, header offset -100 or 1e11, data type 6 raised AttributeError here)."""
    metadata = image.metadata
    expected = f"a float32 ENVI {kind} image written by spherejax correct --format envi"
    fields = {}
    for name in ("samples", "lines", "bands", "header offset", "data type"):
        try:
            fields[name] = int(metadata.get(name, "0" if name == "header offset" else ""))
        except ValueError:
            raise SpherejaxFileError(header_path, f"has {name} = {metadata.get(name)!r}", f"{expected}: an integer") from None
    for name in ("samples", "lines", "bands"):
        if fields[name] < 1:
            raise SpherejaxFileError(header_path, f"has {name} = {fields[name]}", f"{expected}: {name} >= 1")
    if fields["header offset"] < 0:
        raise SpherejaxFileError(header_path, f"has header offset = {fields['header offset']}", f"{expected}: an offset >= 0")
    if fields["data type"] != 4:
        from spectral.io.envi import envi_to_dtype  # ENVI's data type codes, Spectral Python's table

        code = str(fields["data type"])
        held = np.dtype(envi_to_dtype[code]).name if code in envi_to_dtype else "unknown"
        raise SpherejaxFileError(header_path, f"holds {held} pixels (data type = {code})", f"float32 {kind} (data type = 4)")
    data_path = pathlib.Path(image.filename)
    try:
        size = data_path.stat().st_size
    except OSError as error:
        raise SpherejaxFileError(data_path, f"cannot be read: {error.strerror or error}", f"the data file of {header_path}") from None
    needed = fields["header offset"] + fields["samples"] * fields["lines"] * fields["bands"] * 4
    if size != needed:
        raise SpherejaxFileError(
            data_path, f"holds {size} bytes where its header ({header_path.name}: {fields['lines']} lines x "
            f"{fields['samples']} samples x {fields['bands']} bands of float32 after {fields['header offset']} bytes) "
            f"describes {needed}", expected,
        )


def open_lazy(header_path, *, kind: str, chunk_bytes: int, shape: tuple[int, int] | None = None):
    """An ENVI output as (dask array (H, W, C) float32 with NaN for the data ignore value,
    wavelengths in nm or None, attributes); `kind` names it in messages ("reflectance", "lab").

    Read through Spectral Python (`spectral.open_image`), whose memory map dask reads in chunks
    of whole rows of about `chunk_bytes`, so only the rows a computation needs are read.
    """
    import dask.array as da
    import spectral

    expected = f"a float32 ENVI {kind} image written by spherejax correct --format envi"
    header_path = pathlib.Path(header_path)
    # The magic word first: Spectral Python leaves its file open when it refuses a header.
    try:
        with open(header_path, "rb") as handle:
            magic = handle.read(4)
    except OSError as error:
        raise SpherejaxFileError(header_path, f"cannot be read: {error.strerror or error}", expected) from None
    if magic != b"ENVI":
        raise SpherejaxFileError(header_path, f"cannot be read as ENVI: it starts with {magic!r}", f"{expected} (a header starting with ENVI)")
    try:
        image = spectral.open_image(str(header_path))
    except Exception as error:  # noqa: BLE001 -- Spectral Python raises many kinds for a bad header
        raise SpherejaxFileError(header_path, f"cannot be read as ENVI: {' '.join(str(error).split())}", expected) from None
    _check_header_against_data(header_path, image, kind)
    try:
        pixels = image.open_memmap(interleave="bip", writable=False)
    except Exception as error:  # noqa: BLE001 -- numpy's memmap refuses in several ways
        pixels, reason = None, " ".join(str(error).split())
    else:
        reason = "Spectral Python could not map it"
    if pixels is None:  # Spectral Python returns None for a layout it cannot map
        raise SpherejaxFileError(header_path, f"cannot be read as ENVI: {reason}", expected)
    if pixels.dtype != np.float32:
        raise SpherejaxFileError(header_path, f"holds {pixels.dtype} pixels", f"float32 {kind} (data type = 4)")
    if shape is not None and tuple(pixels.shape[:2]) != tuple(shape):
        raise SpherejaxFileError(header_path, f"is {pixels.shape[0]} x {pixels.shape[1]}", f"the reflectance's {shape[0]} x {shape[1]}")
    metadata = dict(image.metadata)
    wavelengths = [float(nm) for nm in metadata["wavelength"]] if "wavelength" in metadata else None
    if kind == "reflectance" and (wavelengths is None or len(wavelengths) != pixels.shape[2]):
        raise SpherejaxFileError(header_path, "has no wavelength for each band", "wavelength = { ... } in nm, one per band")
    ignore = float(metadata.get("data ignore value", "nan"))
    rows = max(1, chunk_bytes // max(1, pixels.shape[1] * pixels.shape[2] * 4))
    lazy = da.from_array(pixels, chunks=(rows, -1, -1), asarray=True)
    lazy = da.where(lazy == np.float32(ignore), np.float32(np.nan), lazy)
    attributes = {_attribute_name(key): value for key, value in metadata.items()
                  if isinstance(value, str) and key.startswith("spherejax ")}
    return lazy, wavelengths, attributes


__all__ = ["EnviWriter", "IGNORE_VALUE", "data_path", "open_lazy"]
