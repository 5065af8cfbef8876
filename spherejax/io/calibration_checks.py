"""What a calibration file holds, whatever its container (format "spherejax-calibration", the
docstring of spherejax.io): the format, its versions and their arrays, the header as a document,
the checks of header and arrays every reader and `save_calibration` make, the noise model, and
the usable white patch. `calibration_files` is the public API; `calibration_hdf5` and
`calibration_npz` the two containers."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any

import numpy as np
import pydantic

from .. import jsontext
from ..calibration import check_sizes
from ..grid import N_WAVELENGTHS
from ..uncertainty import NoiseModel
from .documents import (
    BandCentres, Checksum, Document, Expect, JsonObject, NonEmptyStr, PositiveNumber, Timestamp, _check_format,
    check_document, located,
)
from .errors import CalibrationFileError, _one_line, _show

CALIBRATION_FORMAT = "spherejax-calibration"
CALIBRATION_FORMAT_VERSION = 7
#: Arrays every calibration file of the current format version holds, in checksum order, with the
#: description stored in its header (the optional ones: `VARIANCE_DESCRIPTIONS`).
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
    "wiener_residual_centre": "kernel residual of the estimator, mu (B,): the training responses' mean "
    "(E9 of spherejax.estimation.kernel_residual; zeros for an affine estimator; new in format version 5)",
    "wiener_residual_whitening": "kernel residual, S / l (B, B): the whitening of responses v - mu divided by "
    "the kernel's lengthscale (E9; zeros for an affine estimator; new in format version 5)",
    "wiener_residual_inducing": "kernel residual, z / l (m, B): the m inducing points in whitened units "
    "(E10; m = 0 for an affine estimator; new in format version 5)",
    "wiener_residual_weights": "kernel residual, A (31, m): reflectance = wiener @ v_tilde + wiener_offset "
    "+ A @ exp(-|S (v_tilde - mu) / l - z_j / l|^2 / 2) (E8; m = 0 for an affine estimator; new in format "
    "version 5)",
}
#: The optional arrays of a calibration file, stored after CALIBRATION_ARRAYS in checksum order: the
#: kernel residual's own uncertainty (E15, `estimation.ResidualVariance`), all five or none.
VARIANCE_DESCRIPTIONS = {
    "wiener_residual_variance_components": "kernel residual's predictive variance, P (r, 31): the residual's r "
    "principal directions; its reflectance covariance is sum_j var_j P_j P_j^T (E13, E15; optional, new in "
    "format version 6)",
    "wiener_residual_variance_prior": "kernel residual's predictive variance, s^2 (r,) >= 0: each component's "
    "signal variance, its variance far from the targets (E15; optional, new in format version 6)",
    "wiener_residual_variance_projection": "kernel residual's predictive variance, X (m, q): X X^T = K_mm^-1, "
    "g = X^T k(v_tilde) (E15; optional, new in format version 6)",
    "wiener_residual_variance_weights": "kernel residual's predictive variance, C (r, q): var_j = s_j^2 "
    "(1 - |g|^2) + sum_i C_ji g_i^2 (E15; optional, new in format version 6)",
    "wiener_residual_variance_noise": "kernel residual's predictive variance, (31,) >= 0: a target's scatter "
    "about the fit per wavelength, reflectance squared (E15; optional, new in format version 6)",
}
#: The optional array of a calibration whose bands were registered (`Calibration.band_transforms`),
#: stored after the variance's in checksum order: format version 7 on.
REGISTRATION_DESCRIPTIONS = {
    "band_transforms": "each band's map from the reference band's geometry (B, 2, 3): 2 x 3 affine matrices in band "
    "order mapping pixel coordinates of the reference geometry (x = column, y = row, pixel centres at integers) to "
    "the band's; every correction resamples each band's flat-fielded response through it (optional, new in format "
    "version 7; absent: the bands are taken as in register)",
}
#: The format version that added `REGISTRATION_DESCRIPTIONS` and the header's "band_registration".
_REGISTRATION_SINCE = 7
#: The arrays of a kernel residual (`estimation.KernelResidual`: centre, whitening, inducing,
#: weights), in that order; m = 0 rows of inducing points for an affine estimator.
RESIDUAL_ARRAYS = ("wiener_residual_centre", "wiener_residual_whitening", "wiener_residual_inducing", "wiener_residual_weights")
#: The arrays of the kernel residual's predictive variance (`estimation.ResidualVariance`:
#: components, prior, projection, weights, noise), in that order: format version 6 on, optional
#: (a file holds all five, or none: a residual without its variance, or an affine estimator).
VARIANCE_ARRAYS = tuple(VARIANCE_DESCRIPTIONS)
#: Every array a calibration file may hold, with its description.
ARRAY_DESCRIPTIONS = {**CALIBRATION_ARRAYS, **VARIANCE_DESCRIPTIONS, **REGISTRATION_DESCRIPTIONS}
_AFFINE_ARRAYS = tuple(name for name in CALIBRATION_ARRAYS if name not in RESIDUAL_ARRAYS)
#: The arrays every file of the current format version holds.
_REQUIRED_ARRAYS = tuple(CALIBRATION_ARRAYS)
#: The arrays of an older calibration format version, where they differ from CALIBRATION_ARRAYS.
_OLDER_CALIBRATION_ARRAYS = {
    1: tuple(name for name in _AFFINE_ARRAYS if name != "wiener_offset"),
    **dict.fromkeys((2, 3, 4), _AFFINE_ARRAYS),
    5: _REQUIRED_ARRAYS,
}
#: The calibration format version that added the header's "noise_model".
_NOISE_MODEL_SINCE = 3
#: The format version that moved from .npz to HDF5.
_HDF5_SINCE = 4
# A header is a few kB of JSON, some 40 kB with a noise model of 16 bands (its 31 x 31 residual
# covariance, about 20 bytes a number): refuse to read gigabytes as one.
_MAX_HEADER_BYTES = 16 << 20


def _calibration_arrays(header: Mapping) -> tuple[str, ...]:
    """The names of the arrays a calibration file of the header's format version holds, in
    checksum order (version 1 has no wiener_offset; from version 6 on, the residual's variance
    arrays that the header's "arrays" lists). Call after the version was checked."""
    version = header.get("format_version", CALIBRATION_FORMAT_VERSION)
    if version in _OLDER_CALIBRATION_ARRAYS:
        return _OLDER_CALIBRATION_ARRAYS[version]
    listed = header.get("arrays", {})
    optional = VARIANCE_ARRAYS + (tuple(REGISTRATION_DESCRIPTIONS) if version >= _REGISTRATION_SINCE else ())
    return _REQUIRED_ARRAYS + tuple(name for name in optional if name in listed)


def _array_entry(name: str, array: np.ndarray) -> dict:
    """How the header describes one array: shape, dtype (numpy's dtype.str) and meaning."""
    return {
        "shape": list(array.shape),
        "dtype": array.dtype.str,
        "description": ARRAY_DESCRIPTIONS[name],
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


class _ArraysV2(_ArraysV1):
    wiener_offset: _Entry


class _ArraysV5(_ArraysV2):
    wiener_residual_centre: _Entry
    wiener_residual_whitening: _Entry
    wiener_residual_inducing: _Entry
    wiener_residual_weights: _Entry


class _Arrays(_ArraysV5):
    # Absent (the default) when the residual carries no variance; never null.
    wiener_residual_variance_components: _Entry = None
    wiener_residual_variance_prior: _Entry = None
    wiener_residual_variance_projection: _Entry = None
    wiener_residual_variance_weights: _Entry = None
    wiener_residual_variance_noise: _Entry = None


class _ArraysV7(_Arrays):
    # Absent (the default) when the bands were not registered; never null.
    band_transforms: _Entry = None


class _CalibrationHeaderV6(Document):
    """The header of a calibration file of format version 6 (and, with their own arrays, 1 to 5)."""

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
    noise_model: Any = None  # checked by noise_model_of: NoiseModel's own document (spherejax.noise_document)


class _CalibrationHeader(_CalibrationHeaderV6):
    """The header of a calibration file (the docstring of spherejax.io), fields in checking order."""

    arrays: Annotated[_ArraysV7, Expect(f"an object describing {list(CALIBRATION_ARRAYS)}")]
    # How the bands were registered (`calibrate`): absent or null when they were not.
    band_registration: JsonObject | None = None


class _CalibrationHeaderV1(_CalibrationHeaderV6):
    arrays: Annotated[_ArraysV1, Expect(f"an object describing {list(_OLDER_CALIBRATION_ARRAYS[1])}")]


class _CalibrationHeaderV2(_CalibrationHeaderV6):
    arrays: Annotated[_ArraysV2, Expect(f"an object describing {list(_OLDER_CALIBRATION_ARRAYS[2])}")]


class _CalibrationHeaderV5(_CalibrationHeaderV6):
    arrays: Annotated[_ArraysV5, Expect(f"an object describing {list(_OLDER_CALIBRATION_ARRAYS[5])}")]


#: The header's document of each older format version (the current one: _CalibrationHeader).
_OLDER_HEADERS = {1: _CalibrationHeaderV1, 2: _CalibrationHeaderV2, 3: _CalibrationHeaderV2, 4: _CalibrationHeaderV2,
                  5: _CalibrationHeaderV5, 6: _CalibrationHeaderV6}


def _check_calibration_header(path, header) -> None:
    """Check the header's fields, format and version first (a newer file may differ in the rest)."""
    if not isinstance(header, dict):
        raise CalibrationFileError(path, f"has a header of {_show(header)}", "a JSON object")
    error = located(CalibrationFileError, path)
    version = _check_format(header, CALIBRATION_FORMAT, CALIBRATION_FORMAT_VERSION, error=error, where="header")
    model = _OLDER_HEADERS.get(version, _CalibrationHeader)
    check_document(model, header, error=error, where="header")
    noise_model_of(path, header)


#: The shape of `EstimatorCovariance.residual`, which the bands do not decide (NoiseModel's document
#: checks the per-band shapes).
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
        model = NoiseModel.from_json(doc, bands=len(header["band_centres_nm"]))
        estimator = model.estimator_covariance
        if estimator is not None and tuple(estimator.residual.shape) != _RESIDUAL_SHAPE:
            raise ValueError(
                f"estimator_covariance.residual has shape {tuple(estimator.residual.shape)}, expected {_RESIDUAL_SHAPE}"
            )
    except ValueError as error:  # from_json's, one line naming the key (spherejax.noise_document)
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
    listed = [name for name in VARIANCE_ARRAYS if name in names]
    if listed and len(listed) != len(VARIANCE_ARRAYS):
        raise CalibrationFileError(
            path, f"header.arrays lists {listed} of the kernel residual's variance but not "
            f"{[name for name in VARIANCE_ARRAYS if name not in listed]}",
            f"all of {list(VARIANCE_ARRAYS)} or none",
        )
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
    points = 0
    if RESIDUAL_ARRAYS[0] in names:
        _check_residual_shapes(path, len(bands), *(arrays[name].shape for name in RESIDUAL_ARRAYS))
        points = arrays["wiener_residual_inducing"].shape[0]
    try:
        # From the shapes alone, before the checksum reads any array: 32 768 inducing points are
        # refused at once. 4-byte floats, the least the engine computes in (a float64 calibration
        # is checked again in its own dtype when its `Calibration` is built).
        check_sizes(len(bands), points, 4, arrays["dark"].shape[:2])
    except ValueError as error:
        raise CalibrationFileError(path, f"does not hold a valid calibration: {error}") from None
    if VARIANCE_ARRAYS[0] in names:
        _check_variance_shapes(path, points, *(arrays[name].shape for name in VARIANCE_ARRAYS))
    if "band_transforms" in names and tuple(arrays["band_transforms"].shape) != (len(bands), 2, 3):
        raise CalibrationFileError(
            path, f"array 'band_transforms' has shape {list(arrays['band_transforms'].shape)}",
            f"one 2 x 3 affine map per band: [{len(bands)}, 2, 3]",
        )



def _check_no_residual(path, centre: np.ndarray, whitening: np.ndarray) -> None:
    """With m = 0 inducing points (an affine estimator) the residual's centre and whitening are
    zeros: anything else would be read as nothing, silently."""
    for name, array in zip(RESIDUAL_ARRAYS, (centre, whitening)):
        if np.asarray(array).any():
            raise CalibrationFileError(
                path, f"array {name!r} is not zero with no inducing point (m = 0)",
                "zeros for an affine estimator's kernel residual",
            )


def _check_residual_shapes(path, bands: int, centre, whitening, inducing, weights) -> None:
    """The kernel residual's arrays fit B bands and one m (the docstring of spherejax.io)."""
    m = inducing[0] if len(inducing) == 2 else -1
    expected = {"wiener_residual_centre": (bands,), "wiener_residual_whitening": (bands, bands),
                "wiener_residual_inducing": (m, bands), "wiener_residual_weights": (N_WAVELENGTHS, m)}
    for name, shape in zip(RESIDUAL_ARRAYS, (centre, whitening, inducing, weights)):
        if tuple(shape) != expected[name] or m < 0:
            raise CalibrationFileError(
                path, f"array {name!r} has shape {list(shape)}",
                f"a kernel residual of the {bands} bands: centre ({bands},), whitening ({bands}, {bands}), "
                f"inducing (m, {bands}) and weights (31, m), m >= 0 (0: an affine estimator)",
            )


def _check_variance_shapes(path, m: int, components, prior, projection, weights, noise) -> None:
    """The residual variance's arrays fit the residual's m inducing points (m >= 1: an affine
    estimator has no variance), the 31 wavelengths, one rank r <= 31 and one q <= m (E15)."""
    expected_text = (f"a kernel residual's variance for its {m} inducing points: components (r, 31), prior (r,), "
                     f"projection ({m}, q), weights (r, q) and noise (31,), 1 <= r <= 31, 0 <= q <= {m}")
    if m == 0:
        raise CalibrationFileError(
            path, f"array {VARIANCE_ARRAYS[0]!r} holds a kernel residual's variance with no inducing point (m = 0)",
            "no variance arrays for an affine estimator",
        )
    r = components[0] if len(components) == 2 else -1
    q = projection[1] if len(projection) == 2 else -1
    expected = {VARIANCE_ARRAYS[0]: (r, N_WAVELENGTHS), VARIANCE_ARRAYS[1]: (r,), VARIANCE_ARRAYS[2]: (m, q),
                VARIANCE_ARRAYS[3]: (r, q), VARIANCE_ARRAYS[4]: (N_WAVELENGTHS,)}
    for name, shape in zip(VARIANCE_ARRAYS, (components, prior, projection, weights, noise)):
        if tuple(shape) != expected[name] or not 1 <= r <= N_WAVELENGTHS or not 0 <= q <= m:
            raise CalibrationFileError(path, f"array {name!r} has shape {list(shape)}", expected_text)


def check_variance_values(path, prior: np.ndarray, noise: np.ndarray) -> None:
    """The residual variance's prior s^2 and noise are variances: finite and >= 0 (E15). One line
    naming the dataset, the first value found outside and what was expected."""
    for name, values in ((VARIANCE_ARRAYS[1], prior), (VARIANCE_ARRAYS[4], noise)):
        values = np.asarray(values, np.float64)
        bad = np.flatnonzero(~(values >= 0))  # NaN too
        if bad.size:
            raise CalibrationFileError(
                path, f"array {name!r} holds {values.flat[bad[0]]:.6g} at index {int(bad[0])} ({bad.size} entries "
                "not finite and >= 0)", "variances: finite numbers >= 0",
            )


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
