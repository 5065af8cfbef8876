"""Calibration files (format "spherejax-calibration", the package docstring): HDF5 written
atomically with a checksum, read whole or by rows without loading every array; the .npz files of
format versions 1 to 3 are still read (whole).

This module is the public API: `save_calibration`, `open_calibration`, `load_calibration` and
`CalibrationFile`. The rest, by job (their names are importable from here too):
`calibration_checks` (the format, its versions and their arrays, the header, the checks of header
and arrays, the noise model, the usable white patch), `calibration_hdf5` (the HDF5 layout: writing,
indexing a file before reading it, the check that it stores every declared byte, reads by rows and
blocks, the checksum) and `calibration_npz` (the .npz of format versions 1 to 3, read only)."""

from __future__ import annotations

import collections
import contextlib
import pathlib
from collections.abc import Iterator

import h5py
import jax.numpy as jnp
import numpy as np

from .. import band_resampling
from ..grid import N_WAVELENGTHS
from .._checks import require_finite
from ..calibration import Calibration, patch_bounding_box
from ..uncertainty import NoiseModel
# The functions here look their helpers up in this module: tests patch `_require_usable_patch`,
# `_utc_now` and `IN_MEMORY_BYTES` here. The block sizes `_READ_BLOCK` and `_CHUNK_BYTES` are read
# in `calibration_hdf5` (patch them there) and are not re-exported, so a patch here fails loudly.
from .calibration_checks import (
    CALIBRATION_ARRAYS, CALIBRATION_FORMAT, CALIBRATION_FORMAT_VERSION, RESIDUAL_ARRAYS, VARIANCE_ARRAYS, _HDF5_SINCE,
    _array_entry, _check_calibration_contents, _check_no_residual, _decode_header, _require_usable_patch,
    check_variance_values, noise_model_of,
)
from .calibration_hdf5 import (
    _EXPECTED_FILE, _StoredArray, _checksum, _container, _hdf5_errors, _index_hdf5, _write_hdf5,
)
# Kept importable from here only (tests and other software use them).
from .calibration_checks import _ArrayEntry, _CalibrationHeader, _CalibrationHeaderV1, _MAX_HEADER_BYTES  # noqa: F401
from .calibration_hdf5 import HDF5_SIGNATURE, ZIP_SIGNATURE, _FRAME_ARRAYS, _row_chunks  # noqa: F401
from .calibration_npz import _read_npz
from .documents import _describe_bands, _json_value, _utc_now
from .errors import CalibrationFileError, SpherejaxFileError

#: Arrays up to this size are read into memory when a calibration file is opened; larger ones
#: (the dark frame and white standard of a big sensor) are read by rows when needed.
IN_MEMORY_BYTES = 256 << 20

#: The most bytes of dark and white rows a `CalibrationFile` keeps as `Calibration`s of strips
#: (`CalibrationFile.rows`): the strips of an image of IN_MEMORY_BYTES, with room for a second
#: strip height.
ROWS_KEPT_BYTES = 2 * IN_MEMORY_BYTES


def save_calibration(
    path, calibration: Calibration, *, instrument_id: str, band_centres_nm, metadata=None,
    noise_model: NoiseModel | None = None, band_registration: dict | None = None,
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
      band_registration: how the calibration's band maps were estimated (JSON: the reference
        band, each band's residual in pixels, the frame used; `calibrate`'s report), stored in the
        header's "band_registration" with the maps themselves under "band_transforms" (the array
        "band_transforms" holds them too, bit for bit). None: only the maps, if the calibration has
        them; a calibration without maps stores neither.

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
    with _reraise_invalid(path):
        # Built calibrations were checked; one made by jax.tree_util.tree_map never was.
        calibration.check_values()
    arrays = {name: np.asarray(getattr(calibration, name)) for name in CALIBRATION_ARRAYS
              if name not in RESIDUAL_ARRAYS + VARIANCE_ARRAYS}
    arrays.update(_residual_arrays(calibration))
    registration = None
    if calibration.band_transforms is not None:
        arrays["band_transforms"] = np.asarray(calibration.band_transforms)
        registration = {**(band_registration or {}), "band_transforms": arrays["band_transforms"].tolist()}
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
    if registration is not None:  # absent without maps: such a header reads as format version 6's did
        header["band_registration"] = registration
    # The checksum is over the header as it will read back from JSON.
    header = _json_value(path, header, CalibrationFileError, "the header")
    header["checksum"] = _checksum(header, arrays)
    _check_calibration_contents(path, header, arrays)  # refuse to write what load would refuse
    _require_usable_patch(path, arrays["dark"], arrays["white"], arrays["patch"])
    _write_hdf5(path, header, arrays)
    return header


def _residual_arrays(calibration: Calibration) -> dict[str, np.ndarray]:
    """The kernel residual's arrays as stored (`RESIDUAL_ARRAYS`): the calibration's, or those of
    no residual (m = 0 inducing points, zeros) for an affine estimator; and its variance's
    (`VARIANCE_ARRAYS`) when it carries one (E15)."""
    residual = calibration.wiener_residual
    if residual is None:
        bands, dtype = calibration.bands, np.asarray(calibration.wiener).dtype
        values = (np.zeros(bands, dtype), np.zeros((bands, bands), dtype), np.zeros((0, bands), dtype),
                  np.zeros((N_WAVELENGTHS, 0), dtype))
    else:
        values = (residual.centre, residual.whitening, residual.inducing, residual.weights)
    arrays = {name: np.asarray(value) for name, value in zip(RESIDUAL_ARRAYS, values)}
    variance = None if residual is None else residual.variance
    if variance is not None:
        values = (variance.components, variance.prior, variance.projection, variance.weights, variance.noise)
        arrays.update({name: np.asarray(value) for name, value in zip(VARIANCE_ARRAYS, values)})
    return arrays


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
      image_shape: (H, W). bands: B. patch_box: (row0, row1, col0, col1) bounding the patch;
        patch_read_box: the pixels its white-patch ratio reads (`patch_calibration`).
      band_transforms: (B, 2, 3) the band maps, or None (the bands taken as in register).
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
            for name in arrays:
                # Every array but the frames is a parameter every pixel goes through (small, read
                # whole): a NaN or infinity there makes every reflectance NaN or infinite with
                # quality 0. The check Calibration makes when built, here before any frame is read
                # and naming the array as the file does; new arrays are covered without a list.
                if name not in _FRAME_ARRAYS:
                    require_finite(name, self._value(name))
            if "band_transforms" in arrays:
                band_resampling.check_transforms(self._value("band_transforms"), self.bands, self.image_shape)
            if VARIANCE_ARRAYS[0] in arrays:
                check_variance_values(path, self._value(VARIANCE_ARRAYS[1]), self._value(VARIANCE_ARRAYS[4]))
            self.patch_box = patch_bounding_box(self._value("patch"))
            if self.patch_box is None:
                raise ValueError("patch: the mask selects no pixel; expected at least one True entry")
            # With band maps, the patch's registered pixels are interpolated from native ones around
            # it: the crop p is taken from holds them (`band_resampling.read_box`).
            self.patch_read_box = self.patch_box
            self.band_transforms = self._value("band_transforms") if "band_transforms" in arrays else None
            if self.band_transforms is not None:
                self.patch_read_box = band_resampling.read_box(self.patch_box, self._value("band_transforms"),
                                                               self.image_shape)
            self._patch_calibration = self._crop(*self.patch_read_box)
            crop = self._patch_calibration
            _require_usable_patch(path, np.asarray(crop.dark), np.asarray(crop.white), np.asarray(crop.patch))
        if RESIDUAL_ARRAYS[0] in arrays and arrays["wiener_residual_inducing"].shape[0] == 0:
            _check_no_residual(path, self._value("wiener_residual_centre"), self._value("wiener_residual_whitening"))
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
            dark=crop("dark"), white=crop("white"), patch=crop("patch"), **self._small_arrays(row0, col0),
            **self._calibration_fields,
        )

    def _small_arrays(self, row0: int = 0, col0: int = 0) -> dict:
        """What every part of the calibration shares: coeffs, wiener, wiener_offset and the
        estimator's kernel residual (None when the file has none: format version 4 and older,
        or m = 0), with its variance (None when the file has none: format version 5 and older,
        or a residual stored without it), and the band maps (None when the file has none), in the
        pixel coordinates of a part whose pixel (0, 0) is the image's (row0, col0)."""
        small = {name: self._value(name) for name in ("coeffs", "wiener", "wiener_offset")}
        residual = None
        if RESIDUAL_ARRAYS[0] in self._arrays and self._arrays["wiener_residual_inducing"].shape[0] > 0:
            from ..estimation.estimator import KernelResidual, ResidualVariance

            variance = None
            if VARIANCE_ARRAYS[0] in self._arrays:
                variance = ResidualVariance(*(jnp.asarray(self._value(name)) for name in VARIANCE_ARRAYS))
            residual = KernelResidual(*(jnp.asarray(self._value(name)) for name in RESIDUAL_ARRAYS), variance=variance)
        transforms = None
        if "band_transforms" in self._arrays:
            transforms = np.asarray(band_resampling.local_transforms(self._value("band_transforms"), row0, col0))
        return {**small, "wiener_residual": residual, "band_transforms": transforms}

    @property
    def noise_model(self) -> NoiseModel | None:
        """The header's noise model (`spherejax.NoiseModel`), or None when the file stores none."""
        return self._noise_model

    @property
    def patch_calibration(self) -> Calibration:
        """The calibration cropped to `patch_read_box` (r0, r1, c0, c1): `pipeline.patch_ratio(raw[r0:r1,
        c0:c1], patch_calibration)` is the white-patch ratio of the whole image. `patch_read_box` is
        `patch_box`, grown by the band maps' reach (`band_resampling.read_box`) when the file has them."""
        return self._patch_calibration

    def rows(self, row0: int, row1: int, *, padded_to: int | None = None) -> Calibration:
        """The calibration of image rows row0:row1 without the patch (`Calibration.rows`), read
        from disk for a large file; padded_to: that many rows, the rows beyond row1 with dark =
        white = 0 (pixels flagged white <= dark: a strip's padding computes nothing that could
        fail, `stripwise`).

        The same rows give the same `Calibration` object while it is kept (`ROWS_KEPT_BYTES`):
        a calibration keeps its plans (`spherejax._engine.plan`), so every input of a batch
        corrected strip by strip reuses one plan a strip shape instead of preparing it again."""
        height = self.image_shape[0]
        if not 0 <= row0 < row1 <= height:
            raise ValueError(f"rows: expected 0 <= row0 < row1 <= {height}, got {row0}:{row1}")
        if padded_to is not None and padded_to < row1 - row0:
            raise ValueError(f"padded_to: expected at least the {row1 - row0} rows asked for, got {padded_to}")
        key = (row0, row1, padded_to)
        kept = self.__dict__.setdefault("_kept_rows", collections.OrderedDict())
        rows = kept.get(key)
        if rows is not None:
            kept.move_to_end(key)
            return rows
        dark, white = self._rows("dark", row0, row1), self._rows("white", row0, row1)
        if padded_to is not None and padded_to > row1 - row0:
            dark, white = (np.concatenate([x, np.zeros((padded_to - len(x), *x.shape[1:]), x.dtype)]) for x in (dark, white))
        rows = Calibration(dark=dark, white=white, patch=None, **self._small_arrays(row0, 0), **self._calibration_fields)
        kept[key] = rows
        while len(kept) > 1 and sum(r.dark.nbytes + r.white.nbytes for r in kept.values()) > ROWS_KEPT_BYTES:
            kept.popitem(last=False)
        return rows

    def calibration(self) -> Calibration:
        """The whole `Calibration` in memory (one object per open file, so that it keeps its plans)."""
        whole = self.__dict__.get("_whole")
        if whole is None:
            whole = Calibration(
                **{name: self._value(name) for name in ("dark", "white", "patch")}, **self._small_arrays(),
                **self._calibration_fields,
            )
            self.__dict__["_whole"] = whole
        return whole

    @property
    def in_memory(self) -> bool:
        """True when the dark frame and white standard are held in memory (not read by rows)."""
        return not isinstance(self._arrays["dark"], _StoredArray)

    def close(self) -> None:
        file, self._file = getattr(self, "_file", None), None
        if file is not None:
            file.close()

    def __del__(self):
        self.close()

    def __getstate__(self) -> dict:
        if self._file is None:
            # everything in memory; the kept calibrations hold plans (compiled programs): not sent
            return {name: value for name, value in self.__dict__.items() if name not in ("_kept_rows", "_whole")}
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
