"""Consistency of patches measured on several backgrounds (Zou et al. 2019, Tables 1 and 3-6).

A correction is judged by how little a patch's corrected response and reflectance change with
the background it lies on. These are the figures of `spherejax.evaluate`, written as pure JAX
functions so that they can be jitted and differentiated with respect to everything upstream
(Stage II coefficients, Wiener matrix, white-patch weights). Sums over backgrounds and pairs are
array reductions; the pairs (j, j') are a static index list built from J.

Conventions: P patches, J backgrounds, channels last.
  responses: (P, J, B), region-averaged response of patch i on background j in each band.
  reflectance: (P, J, 31), at 400..700 nm step 10.
  present: (P, J) bool, True where patch i was measured on background j. Absent entries may
    hold anything, NaN included; present entries are expected to be finite (a NaN there
    propagates into the result, as a bad value should).
float32 unless an input is float64.

Figures (i patch, j background, b band, λ wavelength; n_i = number of backgrounds of patch i):
  response_std, Tables 1 and 3: per band, the mean over patches with n_i >= 1 of the
    population standard deviation (ddof 0) of v_ijb over the backgrounds present,
        s_ib = sqrt( (1/n_i) sum_j (v_ijb - vbar_ib)^2 ),  vbar_ib = (1/n_i) sum_j v_ijb;
    the tables' "Average" is the mean of this over the bands.
  pairwise_spectral_rms, Tables 4 and 5: for each patch with n_i >= 2, the mean over the pairs
    j < j' of present backgrounds of sqrt( (1/31) sum_λ (r_ijλ - r_ij'λ)^2 ); then the mean over
    those patches.
  pairwise_delta_e, Tables 4 and 5: the same averages of CIEDE2000 (Sharma, Wu, Dalal 2005,
    doi:10.1002/col.20070) between the CIELAB of r_ij and r_ij' under an illuminant (ASTM E308,
    `colorimetry.reflectance_to_lab`).
Each is NaN when no patch qualifies (no measurement; fewer than two backgrounds for every patch).

Gradients are finite wherever the value is. Two places need care (safe-where, see
`colorimetry`): absent entries are replaced by finite values before any arithmetic, because
masking only the result still multiplies NaN by a zero cotangent, which is NaN; and a zero
distance (identical responses or reflectances) goes through `colorimetry._safe_sqrt`, whose
gradient there is 0 instead of sqrt's infinite one (0 is a subgradient of the std and the rms
at a minimum).

Reference: Zou, Shen, Li, Zhu, Xin, "Lighting Deviation Correction for Integrating-Sphere
Multispectral Imaging Systems", Sensors 19(16), 3501 (2019), doi:10.3390/s19163501, Section 5.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from . import _checks
from .colorimetry import DEFAULT_OBSERVER, _safe_sqrt, delta_e_2000, reflectance_to_lab
from .grid import N_WAVELENGTHS


def _check(name: str, x, channels: int | None, what: str, present, *, per_channel: bool = False):
    """Validate a (P, J, C) array and its presence flags; returns (x as float, present)."""
    x = _checks.as_array(name, x)
    present = _checks.as_array("present", present)
    if x.ndim != 3:
        raise ValueError(f"{name}: expected shape (P, J, {what}), got {tuple(x.shape)}")
    if channels is not None:
        _checks.require_last_axis(name, x, channels, what)
    if present.dtype != jnp.bool_:
        raise ValueError(f"present: expected a boolean array, got dtype {present.dtype}")
    shapes = [tuple(x.shape[:2])] + ([tuple(x.shape)] if per_channel else [])
    if tuple(present.shape) not in shapes:
        expected = " or ".join(str(s) for s in shapes)
        raise ValueError(
            f"present: expected shape {expected} (one flag per patch and background of {name}), "
            f"got {tuple(present.shape)}"
        )
    return x.astype(_checks.float_dtype(x)), present


def _masked_mean(values, mask, axis):
    """Mean of `values` over `axis` where `mask`; NaN where the mask selects nothing."""
    count = jnp.sum(mask, axis=axis).astype(values.dtype)
    total = jnp.sum(jnp.where(mask, values, 0.0), axis=axis)
    some = count > 0
    return jnp.where(some, total / jnp.where(some, count, 1.0), jnp.nan)


def _pairs(backgrounds: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (j, j') of every pair of backgrounds with j < j', each (J (J - 1) / 2,)."""
    return np.triu_indices(backgrounds, k=1)


def _mean_over_pairs(distance, pair_present):
    """Mean over present pairs per patch, then over patches with at least one pair.

    distance, pair_present: (P, n_pairs).
    """
    per_patch = _masked_mean(distance, pair_present, axis=1)  # (P,), NaN for no pair
    has_pairs = jnp.any(pair_present, axis=1)
    # The NaN of patches without pairs is masked out here; it never reached a gradient, since
    # _masked_mean's division is itself guarded.
    return _masked_mean(per_patch, has_pairs, axis=0)


def response_std(responses, present):
    """Mean over patches of each band's response standard deviation across backgrounds.

    Tables 1 and 3 of Zou et al. (2019); see the module docstring for the formula.

    Args:
      responses: (P, J, B) region-averaged responses of P patches on J backgrounds.
      present: (P, J) bool, True where the patch was measured on the background; or
        (P, J, B) for presence per band (a band whose value is missing on its own).

    Returns:
      (B,): per band, the mean over patches measured on at least one background of the
      population standard deviation (ddof 0) over the backgrounds present. A patch measured on
      one background counts with 0. The tables' "Average" is `jnp.mean` of this.
    """
    responses, present = _check("responses", responses, None, "B", present, per_channel=True)
    mask = present if present.ndim == 3 else jnp.broadcast_to(present[..., None], responses.shape)
    v = jnp.where(mask, responses, 0.0)  # safe-where: absent entries may be NaN
    count = jnp.sum(mask, axis=1).astype(v.dtype)  # (P, B)
    measured = count > 0
    count_safe = jnp.where(measured, count, 1.0)
    # Deviations are taken from the first background present before the mean is formed: the
    # std is unchanged, identical responses give exactly 0 (a mean of equal numbers need not
    # equal them to the last bit), and small differences between responses near 1 lose less.
    first = jnp.take_along_axis(v, jnp.argmax(mask, axis=1)[:, None, :], axis=1)  # (P, 1, B)
    d = jnp.where(mask, v - first, 0.0)
    d_bar = jnp.sum(d, axis=1) / count_safe  # (P, B)
    deviation = jnp.where(mask, d - d_bar[:, None, :], 0.0)
    s = _safe_sqrt(jnp.sum(deviation**2, axis=1) / count_safe)  # (P, B), ddof 0
    return _masked_mean(s, measured, axis=0)


def pairwise_spectral_rms(reflectance, present):
    """Mean spectral rms difference between a patch's reflectances on pairs of backgrounds.

    Tables 4 and 5 of Zou et al. (2019); see the module docstring for the formula.

    Args:
      reflectance: (P, J, 31) at 400..700 nm step 10.
      present: (P, J) bool, True where the patch was measured on the background.

    Returns:
      Scalar: for each patch the mean over pairs j < j' of present backgrounds of the rms over
      the 31 wavelengths of r_j - r_j', then the mean over patches with at least two
      backgrounds (NaN if none has).
    """
    reflectance, present = _check(
        "reflectance", reflectance, N_WAVELENGTHS, "31 wavelengths, 400..700 nm step 10", present
    )
    r = jnp.where(present[..., None], reflectance, 0.0)  # safe-where: absent entries may be NaN
    j, j_p = _pairs(r.shape[1])
    rms = _safe_sqrt(jnp.mean((r[:, j] - r[:, j_p]) ** 2, axis=-1))  # (P, n_pairs)
    return _mean_over_pairs(rms, present[:, j] & present[:, j_p])


def pairwise_delta_e(reflectance, present, illuminant: str = "D65", *, observer: str = DEFAULT_OBSERVER):
    """Mean CIEDE2000 difference between a patch's colours on pairs of backgrounds.

    Tables 4 and 5 of Zou et al. (2019); see the module docstring for the formula.

    Args:
      reflectance: (P, J, 31) at 400..700 nm step 10.
      present: (P, J) bool, True where the patch was measured on the background.
      illuminant: "D65", "A" or "F2" for CIELAB (ASTM E308 weights, perfect-diffuser white).
      observer: colour-matching functions (`colorimetry.OBSERVERS`).

    Returns:
      Scalar: for each patch the mean over pairs j < j' of present backgrounds of ΔE00 between
      the CIELAB of r_j and r_j', then the mean over patches with at least two backgrounds (NaN
      if none has).
    """
    reflectance, present = _check(
        "reflectance", reflectance, N_WAVELENGTHS, "31 wavelengths, 400..700 nm step 10", present
    )
    # Safe-where: absent entries become black, whose Lab (0, 0, 0) has finite gradients (the
    # Lab cube root and CIEDE2000's zero-chroma cases are guarded in colorimetry).
    r = jnp.where(present[..., None], reflectance, 0.0)
    lab = reflectance_to_lab(r, illuminant, observer=observer)  # (P, J, 3)
    j, j_p = _pairs(r.shape[1])
    return _mean_over_pairs(delta_e_2000(lab[:, j], lab[:, j_p]), present[:, j] & present[:, j_p])


__all__ = ["response_std", "pairwise_spectral_rms", "pairwise_delta_e"]
