"""Correction Stage II of Zou et al. (2019): the per-band polynomial in v_s and p_s.

Stage I assumes Lambertian reflection; real samples are not Lambertian, stray light couples bright
and dark regions, and so a residual background effect remains. Section 4 models it per band with

    v_tilde = c1 p v + c2 v + c3 p + c4                                   (Eq. 18 / Eq. 23)

where v is the flat-fielded response (Eq. 10) and p the white-patch ratio (Eq. 15). Coefficients
are ordered (c1, c2, c3, c4) on the last axis of a (B, 4) array. Identity coefficients
(c1, c2, c3, c4) = (1, 0, 0, 0) reduce Stage II to Stage I (v_tilde = p v).

`fit_stage2` with loss "l2" is the least-squares problem of Eq. 19-22, solved per band.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from . import _checks

#: Stage II coefficients that make Stage II equal Stage I, per band: c1 = 1, c2 = c3 = c4 = 0.
IDENTITY_COEFFS = (1.0, 0.0, 0.0, 0.0)

#: Zou et al. (2019), Table 2: the coefficients fitted on the authors' instrument, (16, 4) ordered
#: c1..c4 for bands 1..16 (400..700 nm step 20). The paper prints one row per coefficient; here
#: they are columns, as `stage2` expects. A reference value, not a calibration for another system.
PAPER_TABLE_2 = np.array(
    [
        [0.8966, 0.8787, 0.9083, 0.9168, 0.9240, 0.9438, 0.9155, 0.9293,
         0.9445, 0.9123, 0.9155, 0.9249, 0.9118, 0.9309, 0.9276, 0.9452],
        [0.1158, 0.1337, 0.1000, 0.0901, 0.0824, 0.0613, 0.0934, 0.0792,
         0.0608, 0.0979, 0.0931, 0.0837, 0.0972, 0.0751, 0.0778, 0.0562],
        [0.2062, 0.2034, 0.2169, 0.1507, 0.1354, 0.0837, 0.1243, 0.0849,
         0.0782, 0.1105, 0.1059, 0.0793, 0.1000, 0.0803, 0.0951, 0.1040],
        [-0.2229, -0.2193, -0.2329, -0.1617, -0.1468, -0.0913, -0.1374, -0.0943,
         -0.0868, -0.1228, -0.1172, -0.0878, -0.1097, -0.0868, -0.1009, -0.1085],
    ]
).T
PAPER_TABLE_2.setflags(write=False)

#: Accepted values of `fit_stage2`'s `loss`.
LOSSES = ("l2",)

#: The polynomial has four coefficients, so a band needs at least this many usable samples.
MIN_SAMPLES = 4


def identity_coeffs(bands: int = 16, dtype=jnp.float32):
    """Stage II coefficients that leave Stage I untouched: c1 = 1, c2 = c3 = c4 = 0.

    Returns shape (bands, 4) in `dtype`; `stage2(v, p, identity_coeffs())` equals `stage1(v, p)`.
    """
    return jnp.tile(jnp.asarray(IDENTITY_COEFFS, dtype=dtype), (bands, 1))


def stage2_unchecked(v, p, coeffs):
    """Eq. 23 on validated float arrays of one dtype; see `stage2`."""
    c_1, c_2, c_3, c_4 = coeffs[:, 0], coeffs[:, 1], coeffs[:, 2], coeffs[:, 3]
    return (c_1 * p + c_2) * v + c_3 * p + c_4


def stage2(v, p, coeffs):
    """Stage II corrected response v_tilde = (c1 p + c2) v + c3 p + c4 (Eq. 23).

    Args:
      v: flat-fielded response v_s (Eq. 10), shape (..., B).
      p: white-patch ratio p_s (Eq. 15), shape (B,) or broadcastable to `v`.
      coeffs: shape (B, 4), ordered c1, c2, c3, c4 (the paper's Table 2, transposed).

    Returns:
      v_tilde, shape of `v`.
    """
    v, p = _checks.response_and_ratio(v, p)
    coeffs = _checks.as_array("coeffs", coeffs)
    bands = v.shape[-1]
    _checks.require_shape("coeffs", coeffs, (bands, 4), f"c1..c4 for each of the {bands} bands")
    dtype = _checks.float_dtype(v, p, coeffs)
    return stage2_unchecked(v.astype(dtype), p.astype(dtype), coeffs.astype(dtype))


def _design_matrix(v, p):
    """M = (p ⊙ v, v, p, 1) of Eq. 20 for one band; v, p shape (n,) -> (n, 4)."""
    return jnp.stack([p * v, v, p, jnp.ones_like(v)], axis=-1)


def _fit_band_l2(v, p, target):
    """Closed-form fit of one band (Eq. 21-22) using only the finite samples.

    Eq. 22 writes the normal equations (MᵀM)⁻¹Mᵀv_tilde; they square the condition number, and
    the columns p⊙v and v are nearly collinear because p stays close to 1, so the same minimiser
    is computed with an SVD-based least-squares solve instead. Non-finite samples get weight 0 (a
    zero row leaves the minimiser unchanged); a band with fewer than 4 usable samples is NaN.
    """
    usable = jnp.isfinite(v) & jnp.isfinite(p) & jnp.isfinite(target)
    v = jnp.where(usable, v, 0.0)
    p = jnp.where(usable, p, 0.0)
    target = jnp.where(usable, target, 0.0)
    rows = jnp.where(usable[:, None], _design_matrix(v, p), 0.0)
    coeffs, _, rank, _ = jnp.linalg.lstsq(rows, target)
    enough = (jnp.sum(usable) >= MIN_SAMPLES) & (rank == 4)
    return jnp.where(enough, coeffs, jnp.nan)


def fit_stage2(v, p, target, loss: str = "l2"):
    """Fit the Stage II coefficients of every band (Eq. 19-22).

    The training set of Section 4: small patches i on backgrounds j give v^{ij} (Eq. 10) and
    p^{ij} (Eq. 15); the target is the Stage I response of the same patch on the reference
    background, p^{i,jref} v^{i,jref}, repeated for every j (Eq. 19).

    Args:
      v: normalised responses, shape (n, B), n = n_p * n_b samples (35 x 35 px averages).
      p: white-patch ratios, shape (n, B).
      target: target responses v_tilde, shape (n, B).
      loss: "l2", the closed form of Eq. 22.

    Returns:
      coeffs, shape (B, 4), ordered c1..c4. A band with fewer than 4 finite samples, or whose
      samples do not determine the four coefficients (rank < 4), is NaN.
    """
    if not isinstance(loss, str) or loss not in LOSSES:
        raise ValueError(f"loss: unknown loss {loss!r}; expected one of {list(LOSSES)}")
    v = _checks.as_array("v", v)
    p = _checks.as_array("p", p)
    target = _checks.as_array("target", target)
    if v.ndim != 2:
        raise ValueError(f"v: expected shape (n, B) (samples, bands), got {tuple(v.shape)}")
    _checks.require_shape("p", p, v.shape, "one white-patch ratio per sample and band, like v")
    _checks.require_shape("target", target, v.shape, "one target per sample and band, like v")
    if v.shape[0] < MIN_SAMPLES:
        raise ValueError(
            f"v: {v.shape[0]} samples cannot determine the 4 coefficients c1..c4; expected at "
            f"least {MIN_SAMPLES} rows"
        )
    dtype = _checks.float_dtype(v, p, target)
    fit = jax.vmap(_fit_band_l2, in_axes=(1, 1, 1))
    return fit(v.astype(dtype), p.astype(dtype), target.astype(dtype))


__all__ = ["IDENTITY_COEFFS", "LOSSES", "PAPER_TABLE_2", "identity_coeffs", "stage2", "fit_stage2"]
