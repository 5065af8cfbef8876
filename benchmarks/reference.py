"""The numpy + colour-science reference of `spherejax.correct`, the synthetic inputs it and
spherejax are timed on, and the check that their outputs agree: what every speed figure of
spherejax is a ratio to (benchmarks/README.md)."""

from __future__ import annotations

import warnings

import numpy as np

# colour-science warns at import that matplotlib is missing; plotting is not used here.
warnings.filterwarnings("ignore", message=".*Matplotlib.* related API features are not available")

import colour  # noqa: E402

import spherejax  # noqa: E402
from spherejax import band_resampling, spectra  # noqa: E402
from spherejax.polynomial import PAPER_TABLE_2  # noqa: E402

BANDS = 16
SATURATION = 16383.0  # 14-bit ADC full scale
PATCH_SIZE = 35  # the paper's 35 x 35 pixel averaging region
SEED = 20190816  # fixed so every run times the same cube

# Bytes the path must move per pixel (docs/design.md, "Performance model"): read raw uint16, dark and
# white float32; write reflectance (31) and Lab (3) float32 and the uint8 quality mask.
BYTES_PER_PIXEL = BANDS * 2 + BANDS * 4 * 2 + (31 + 3) * 4 + 1  # = 297

REFLECTANCE_TOLERANCE = 1e-4
LAB_TOLERANCE = 1e-2


# --------------------------------------------------------------------------------------------
# Inputs


def stage2_coeffs() -> np.ndarray:
    """The paper's Table 2 as a (16, 4) float32 array, columns c1, c2, c3, c4."""
    return np.asarray(PAPER_TABLE_2, dtype=np.float32)


def camera_sensitivity() -> np.ndarray:
    """(16, 31): Gaussian filters, centres 400..700 step 20, FWHM 10 nm, on 400..700 step 10.

    Each row sums to 1, so a perfect diffuser (reflectance 1) gives response 1 in every band:
    the units of flat-fielded responses, which is what the Wiener matrix is applied to.
    """
    sigma = 10.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    centres = spherejax.BAND_CENTRES_NM[:, None].astype(np.float64)
    wavelengths = spherejax.WAVELENGTHS_NM[None, :].astype(np.float64)
    filters = np.exp(-0.5 * ((wavelengths - centres) / sigma) ** 2)
    return filters / filters.sum(axis=1, keepdims=True)


def wiener_estimator() -> tuple[np.ndarray, np.ndarray]:
    """(W (31, 16), r0 (31,)) float32: the affine Wiener estimator r = W v + r0 trained on every
    reflectance spherejax ships. A plain matrix (what `fit_wiener` returned before the
    estimator became affine) is taken with a zero offset."""
    reflectances = spectra.all_reflectances()
    responses = reflectances @ camera_sensitivity().T
    estimator = spherejax.fit_wiener(responses, reflectances)
    matrix = getattr(estimator, "matrix", estimator)
    offset = getattr(estimator, "offset", np.zeros(matrix.shape[0]))
    return np.asarray(matrix, dtype=np.float32), np.asarray(offset, dtype=np.float32)


def wiener_matrix() -> np.ndarray:
    """(31, 16) float32: the matrix W of `wiener_estimator` (its offset left out)."""
    return wiener_estimator()[0]


def vignetting(size: int) -> np.ndarray:
    """(size, size, 1) smooth cos^4-like falloff, 1 at the centre and about 0.7 in the corners."""
    axis = np.linspace(-1.0, 1.0, size, dtype=np.float32)
    radius2 = axis[:, None] ** 2 + axis[None, :] ** 2
    return (1.0 / (1.0 + 0.2 * radius2) ** 2)[..., None]


def sample_reflectance(size: int, rng: np.random.Generator) -> np.ndarray:
    """(size, size, 16) in 0.05..0.95: 32 x 32 px tiles of measured spectra at the band centres.

    Real spectra rather than noise so the Wiener step sees the band correlations it was trained
    for; tiles so the image has edges like a patterned background.
    """
    at_bands = spectra.all_reflectances()[:, ::2]  # 31 samples -> the 16 band centres
    tiles = -(-size // 32)
    choice = rng.integers(0, at_bands.shape[0], size=(tiles, tiles))
    tiled = np.repeat(np.repeat(at_bands[choice], 32, axis=0), 32, axis=1)[:size, :size]
    return np.clip(tiled, 0.05, 0.95).astype(np.float32)


def patch_mask(size: int) -> np.ndarray:
    """(size, size) bool: the 35 x 35 reference white patch, 8 px in from the top-left corner."""
    mask = np.zeros((size, size), dtype=bool)
    mask[8 : 8 + PATCH_SIZE, 8 : 8 + PATCH_SIZE] = True
    return mask


def make_inputs(size: int, seed: int = SEED) -> dict:
    """Synthetic but plausible frames: dark, white standard, one raw sample cube, the patch mask.

    The sample darkens the sphere by q = 0.97 (Eq. 9-15), so the white patch reads 0.97 of the
    white standard and p should come out near 1 / 0.97. A few pixels are driven to saturation so
    the quality-mask path is exercised and compared too.
    """
    rng = np.random.default_rng(seed)
    shape = (size, size, BANDS)
    dark = (100.0 + rng.normal(0.0, 3.0, shape)).astype(np.float32)
    white_signal = 12000.0 * vignetting(size) * rng.uniform(0.9, 1.1, BANDS).astype(np.float32)
    white = (dark + white_signal + rng.normal(0.0, 30.0, shape)).astype(np.float32)

    patch = patch_mask(size)
    reflectance = sample_reflectance(size, rng)
    reflectance[patch] = 1.0  # the patch is the same material as the white standard
    q_s = 0.97
    raw = dark + q_s * white_signal * reflectance + rng.normal(0.0, 20.0, shape)
    hot = rng.random((size, size)) < 1e-4
    raw[hot, rng.integers(0, BANDS)] = SATURATION
    raw = np.clip(np.rint(raw), 0, SATURATION).astype(np.uint16)
    return {"raw": raw, "dark": dark, "white": white, "patch": patch}


def make_calibration(inputs: dict, coeffs: np.ndarray, wiener: np.ndarray, wiener_offset=None) -> spherejax.Calibration:
    """The calibration of `make_inputs`; wiener_offset r0 (31,), None = zeros."""
    return spherejax.Calibration(
        dark=inputs["dark"],
        white=inputs["white"],
        patch=inputs["patch"],
        coeffs=coeffs,
        wiener=wiener,
        illuminant="D65",
        saturation=SATURATION,
        wiener_offset=np.zeros(31, np.float32) if wiener_offset is None else wiener_offset,
    )


# --------------------------------------------------------------------------------------------
# The reference: numpy + colour-science


def kernel_residual(v_tilde, centre, whitening, inducing, weights, rows: int = 1 << 16) -> np.ndarray:
    """The kernel residual A k(v) (..., 31) of an estimator that has one (E9-E10 of
    spherejax/estimation/kernel_residual.py), written out in numpy float32:
    k_j(v) = exp(-|S (v - mu) - z_j|^2 / 2), the squared distance taken directly (not expanded),
    in chunks of `rows` pixels so that the (pixels, m) kernel stays small. NaN v gives NaN."""
    v = np.asarray(v_tilde, np.float32)
    flat = v.reshape(-1, v.shape[-1])
    out = np.empty((len(flat), weights.shape[0]), np.float32)
    for start in range(0, len(flat), rows):
        u = (flat[start:start + rows] - centre) @ whitening.T  # (rows, d)
        squared = np.sum((u[:, None, :] - inducing[None]) ** 2, axis=2)  # (rows, m)
        out[start:start + rows] = np.exp(-0.5 * squared) @ weights.T
    return out.reshape(*v.shape[:-1], weights.shape[0])


def reference_correct(raw, dark, white, patch, coeffs, wiener, xyz_weights, whitepoint_xy, wiener_offset=None,
                      residual=None) -> dict:
    """The `correct` path in numpy, float32 throughout except inside colour-science.

    wiener_offset: the estimator's offset r0 (31,), None = zeros.
    residual: the estimator's kernel residual as (centre (B,), whitening (d, B), inducing (m, d),
      weights (31, m)) float32 (a calibration's "wiener_residual_*" arrays), None or m = 0 for an
      affine estimator.

    Returns a dict with reflectance (H, W, 31), lab (H, W, 3) and valid (H, W) bool. Bad pixels
    (saturated, non-finite, white <= dark) and every pixel of an image whose patch ratio is not
    finite are NaN, as in spherejax.
    """
    raw_f = raw.astype(np.float32)
    saturated = np.any(raw_f >= SATURATION, axis=-1)
    nonfinite = np.any(~np.isfinite(raw_f), axis=-1)
    white_signal = white - dark
    no_flat_field = np.any(~(white_signal > 0), axis=-1)
    valid = ~(saturated | nonfinite | no_flat_field)

    # Eq. 10. Where white <= dark the division is meaningless; those pixels are NaN below anyway.
    sample_signal = raw_f - dark
    with np.errstate(divide="ignore", invalid="ignore"):
        v = sample_signal / white_signal

    # Eq. 14-15 over the usable pixels of the patch only, as spherejax does.
    in_patch = patch & valid
    p = white_signal[in_patch].sum(axis=0) / sample_signal[in_patch].sum(axis=0)  # (16,)
    if not np.all(np.isfinite(p)):
        valid = np.zeros_like(valid)

    # Eq. 23, coefficients (B, 4) ordered c1..c4.
    c_1, c_2, c_3, c_4 = coeffs.T
    v_tilde = (c_1 * p + c_2) * v + c_3 * p + c_4
    v_tilde[~valid] = np.nan

    reflectance = v_tilde @ wiener.T  # (H, W, 31)
    if wiener_offset is not None:
        reflectance += wiener_offset  # the affine estimate W v + r0; NaN rows stay NaN
    if residual is not None and residual[2].shape[0] > 0:
        reflectance += kernel_residual(v_tilde, *residual)
    xyz = reflectance @ xyz_weights  # ASTM E308, Y = 100 for the perfect diffuser
    # colour-science works in float64 internally (its default float dtype); that is how a user
    # would call it, so it is left that way and only the result is cast back.
    lab = colour.XYZ_to_Lab(xyz / 100.0, whitepoint_xy).astype(np.float32)
    return {"reflectance": reflectance, "lab": lab, "valid": valid}


def numpy_registration(raw, dark, white, maps, saturation):
    """Bands in register in NumPy (`spherejax.band_resampling` is the definition).

    raw (H, W, B), dark and white (H, W, B) float32 in each band's own geometry, maps (B, 2, 3)
    from the reference band's pixel coordinates to each band's (x = column, y = row).
    Returns (u' (H, W, B) float32, the registered white signal s' (H, W, B) float32, bits (H, W)
    uint8): Eq. 10's flat-fielded response resampled bilinearly and multiplied back by s', so
    that `reference_correct(u', 0, s', patch & (bits == 0), ...)` is the registered correction;
    flagged pixels hold -s' (spherejax's kernels mark them BELOW_DARK, then take these bits).
    """
    height, width, bands = raw.shape
    raw_f = raw.astype(np.float32)
    signal = white - dark
    unusable = ~(signal > 0) | ~np.isfinite(signal)
    saturated = np.isfinite(raw_f) & (raw_f >= saturation)
    nonfinite = ~np.isfinite(raw_f)
    good = ~(unusable | saturated | nonfinite)
    v = np.where(good, (raw_f - dark) / np.where(unusable, 1, signal), 0).astype(np.float32)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    out, s_out = np.empty_like(v), np.empty_like(v)
    bits = np.zeros((height, width), np.uint8)
    for b in range(bands):
        m = maps[b].astype(np.float32)
        xs, ys = m[0, 0] * x + m[0, 1] * y + m[0, 2], m[1, 0] * x + m[1, 1] * y + m[1, 2]
        tol = band_resampling.COVERAGE_TOLERANCE_PX
        covered = (xs >= -tol) & (xs <= width - 1 + tol) & (ys >= -tol) & (ys <= height - 1 + tol)
        xs, ys = np.clip(xs, 0, width - 1), np.clip(ys, 0, height - 1)
        x0 = np.minimum(np.floor(xs), width - 2).astype(int)
        y0 = np.minimum(np.floor(ys), height - 2).astype(int)
        fx, fy = xs - x0, ys - y0
        taps = [(y0, x0, (1 - fy) * (1 - fx)), (y0, x0 + 1, (1 - fy) * fx), (y0 + 1, x0, fy * (1 - fx)),
                (y0 + 1, x0 + 1, fy * fx)]
        value = sum(w * v[r, c, b] for r, c, w in taps)
        white_value = sum(w * np.where(unusable, 0, signal)[r, c, b] for r, c, w in taps)
        touched = {name: np.zeros((height, width), bool) for name in ("sat", "nonfinite", "white")}
        for r, c, w in taps:
            touched["sat"] |= saturated[r, c, b] & (w > 0)
            touched["nonfinite"] |= nonfinite[r, c, b] & (w > 0)
            touched["white"] |= unusable[r, c, b] & (w > 0)
        bits |= np.where(touched["sat"], 1, 0).astype(np.uint8) | np.where(touched["nonfinite"], 2, 0).astype(np.uint8)
        bits |= np.where(touched["white"], 4, 0).astype(np.uint8) | np.where(~covered, 32, 0).astype(np.uint8)
        out[..., b] = value
        s_out[..., b] = np.where(covered & ~touched["white"], white_value, 1)
    frames = np.where((bits == 0)[..., None], out, -1) * s_out
    return frames.astype(np.float32), s_out.astype(np.float32), bits


def reference_constants() -> tuple[np.ndarray, np.ndarray]:
    """D65 ASTM E308 weights (31, 3) float32 and the white point as CIE xy for colour-science."""
    xyz_weights = np.asarray(spherejax.tristimulus_weights("D65"), dtype=np.float32)
    white_xyz = spherejax.white_point_xyz("D65")
    return xyz_weights, colour.XYZ_to_xy(white_xyz / 100.0)


# --------------------------------------------------------------------------------------------
# Agreement


def compare(result: spherejax.CorrectionResult, reference: dict) -> dict:
    """Max abs differences over valid pixels; raises AssertionError when out of tolerance."""
    valid = np.asarray(result.valid)
    if not np.array_equal(valid, reference["valid"]):
        raise AssertionError(
            f"quality masks differ: spherejax marks {int((~valid).sum())} bad pixels, the "
            f"reference {int((~reference['valid']).sum())}"
        )
    if not valid.any():
        raise AssertionError("no valid pixel to compare: the patch ratio came out non-finite")
    reflectance_diff = float(np.max(np.abs(np.asarray(result.reflectance)[valid] - reference["reflectance"][valid])))
    lab_diff = float(np.max(np.abs(np.asarray(result.lab)[valid] - reference["lab"][valid])))
    bad = []
    if not reflectance_diff <= REFLECTANCE_TOLERANCE:  # `not <=` so NaN fails too
        bad.append(f"reflectance max |diff| {reflectance_diff:.3g} > {REFLECTANCE_TOLERANCE:g}")
    if not lab_diff <= LAB_TOLERANCE:
        bad.append(f"Lab max |diff| {lab_diff:.3g} > {LAB_TOLERANCE:g}")
    if bad:
        raise AssertionError("spherejax and the reference disagree: " + "; ".join(bad))
    return {
        "reflectance_max_abs_diff": reflectance_diff,
        "lab_max_abs_diff": lab_diff,
        "valid_pixels": int(valid.sum()),
        "bad_pixels": int((~valid).sum()),
    }
