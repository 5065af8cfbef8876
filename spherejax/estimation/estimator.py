"""The affine reflectance estimator that every method fits, applying it, and the checks and
weighted moments the methods share.

Every estimator is affine in the response, so that `correct` stays one matrix product per pixel:

    r = W v + r0,      W (31, B), r0 (31,)                                         (E1)

Apply with `wiener(v, estimator)` (or a plain (31, B) matrix): reflectance (..., 31).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _checks
from ..grid import N_WAVELENGTHS

_HIGHEST = jax.lax.Precision.HIGHEST


@dataclasses.dataclass(frozen=True)
class CrossValidation:
    """Cross-validated errors of one method at its chosen regularisers (hashable: it rides in
    the estimator's static part).

    method: "training" or "model". spectral_rms: rms over held-out targets and wavelengths of
    r - r_hat. delta_e_d65: mean CIEDE2000 (D65, 2°) of the held-out targets. settings: the
    chosen regularisers as (name, value) pairs. folds: how the targets were split.
    """

    method: str
    spectral_rms: float
    delta_e_d65: float
    settings: tuple[tuple[str, object], ...]
    folds: str

    def as_dict(self) -> dict:
        return {
            "method": self.method, "spectral_rms": self.spectral_rms, "delta_e_d65": self.delta_e_d65,
            "settings": dict(self.settings), "folds": self.folds,
        }


class WienerEstimator(eqx.Module):
    """An affine reflectance estimator r = W v + r0 (E1), a pytree.

    matrix: W, (31, B). offset: r0, (31,). method: "training" or "model" ("matrix" for a plain
    matrix taken by `as_estimator`) (static).
    cross_validation: the cross-validated errors of every method tried, the chosen one first
    (static; empty when the estimator was built with fixed regularisers).
    """

    matrix: jax.Array
    offset: jax.Array
    method: str = eqx.field(static=True, default="training")
    cross_validation: tuple[CrossValidation, ...] = eqx.field(static=True, default=())

    def __check_init__(self):
        if self.matrix.ndim != 2 or self.matrix.shape[0] != N_WAVELENGTHS:
            raise ValueError(f"matrix: expected shape (31, B) (31 wavelengths x B bands), got {tuple(self.matrix.shape)}")
        _checks.require_shape("offset", self.offset, (N_WAVELENGTHS,), "one value per wavelength")

    def __call__(self, v):
        return wiener(v, self)


def as_estimator(estimator) -> WienerEstimator:
    """A WienerEstimator, or a plain (31, B) matrix taken as one with a zero offset."""
    if isinstance(estimator, WienerEstimator):
        return estimator
    W = _checks.as_array("W", estimator)
    if W.ndim != 2 or W.shape[0] != N_WAVELENGTHS:
        raise ValueError(f"W: expected shape (31, B) (31 wavelengths x the bands), got {tuple(W.shape)}")
    return WienerEstimator(W, jnp.zeros(N_WAVELENGTHS, W.dtype), method="matrix")


def wiener(v, W):
    """Reconstruct reflectance from responses: r = W v + r0 per pixel (E1).

    Args:
      v: corrected responses, shape (..., B).
      W: a `WienerEstimator` (from `fit_wiener`), a plain matrix (31, B) (r0 = 0), or a
        `kernel_residual.ResidualKernelEstimator` (its affine mean plus its residual, E8).

    Returns:
      reflectance, shape (..., 31), 400..700 nm step 10.
    """
    from .kernel_residual import ResidualKernelEstimator  # it builds on this module

    v = _checks.band_array("v", v)
    if isinstance(W, ResidualKernelEstimator):
        dtype = _checks.float_dtype(v, W.matrix)
        return wiener(v.astype(dtype), W.affine) + W.kernel(v.astype(dtype))
    estimator = as_estimator(W)
    W = estimator.matrix
    _checks.require_shape("W", W, (N_WAVELENGTHS, v.shape[-1]), "31 wavelengths x the bands of v")
    dtype = _checks.float_dtype(v, W)
    return jnp.matmul(v.astype(dtype), W.astype(dtype).T, precision=_HIGHEST) + estimator.offset.astype(dtype)


# ---------------------------------------------------------------------------------------------
# Argument checks


def _check_training(responses, reflectances):
    responses = _checks.as_array("responses", responses)
    reflectances = _checks.as_array("reflectances", reflectances)
    if responses.ndim != 2:
        raise ValueError(
            f"responses: expected shape (n, B) (targets, bands), got {tuple(responses.shape)}"
        )
    _checks.require_shape(
        "reflectances",
        reflectances,
        (responses.shape[0], N_WAVELENGTHS),
        "one 400..700 nm spectrum per target, same n as responses",
    )
    if responses.shape[0] < 2:
        raise ValueError(
            f"responses: {responses.shape[0]} target(s) cannot train a Wiener matrix; expected "
            "at least 2 (the paper uses 144)"
        )
    dtype = _checks.float_dtype(responses, reflectances)
    return responses.astype(dtype), reflectances.astype(dtype)


def _check_sensitivity(sensitivity, V):
    """A known sensitivity M as an array (B, 31) in V's dtype, for responses V (n, B)."""
    M = _checks.as_array("sensitivity", sensitivity)
    _checks.require_shape("sensitivity", M, (V.shape[1], N_WAVELENGTHS), "bands of responses x 31 wavelengths")
    return M.astype(V.dtype)


def _check_noise_variance(noise_variance):
    if _checks.is_concrete(noise_variance) and not float(noise_variance) >= 0:
        raise ValueError(f"noise_variance: expected a value >= 0, got {noise_variance!r}")


def _check_determined(V, R, what: str) -> None:
    """Refuse targets that cannot determine an estimator (concrete data only): non-finite
    values, or responses or reflectances that do not vary."""
    if not (_checks.is_concrete(V) and _checks.is_concrete(R)):
        return
    V_np, R_np = np.asarray(V), np.asarray(R)
    for name, x in (("responses", V_np), ("reflectances", R_np)):
        bad = ~np.isfinite(x)
        if bad.any():
            row = int(np.argwhere(bad)[0][0])
            raise ValueError(f"{name}: target {row} has a non-finite value; expected finite {what} data")
    if not np.any(np.ptp(V_np, axis=0) > 0):
        raise ValueError(
            f"responses: all {V_np.shape[0]} targets give the same response; expected targets of "
            f"different colours to fit {what}"
        )
    if not np.any(np.ptp(R_np, axis=0) > 0):
        raise ValueError(
            f"reflectances: all {R_np.shape[0]} targets have the same reflectance; expected targets "
            f"of different colours to fit {what}"
        )


# ---------------------------------------------------------------------------------------------
# Weighted moments: every fit takes per-target weights w (n,) in {0, 1}, so that the folds of a
# cross-validation are the same computation with other weights (vmapped, one compilation).


def _weighted_centre(X, w):
    """(mean (d,), centred rows scaled by sqrt(w) (n, d)) of X (n, d) under weights w (n,)."""
    mean = jnp.sum(w[:, None] * X, axis=0) / jnp.sum(w)
    return mean, (X - mean) * jnp.sqrt(w)[:, None]


def _symmetric_solve(A, B):
    """A^-1 B for a symmetric positive (semi-)definite A (k, k), through its eigendecomposition
    so that a (numerically) singular direction gets a zero weight instead of a blow-up."""
    eigenvalues, Q = jnp.linalg.eigh(A)
    floor = jnp.max(eigenvalues) * jnp.finfo(A.dtype).eps * A.shape[0]
    inverse = jnp.where(eigenvalues > floor, 1.0 / jnp.where(eigenvalues > floor, eigenvalues, 1.0), 0.0)
    return jnp.matmul(Q * inverse, jnp.matmul(Q.T, B, precision=_HIGHEST), precision=_HIGHEST)


__all__ = ["CrossValidation", "WienerEstimator", "as_estimator", "wiener"]
