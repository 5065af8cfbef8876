"""The reflectance estimators as a calibration holds and applies them, whatever fitted them:
pytrees (equinox) and `wiener`, which applies any of them. Nothing here fits; the fitting modules
of this package build these types, and everything that only applies an estimator (the pipeline,
the engine, calibration files) needs no more than this module.

The affine estimator, which every method fits (`WienerEstimator`):

    r = W v + r0,      W (31, B), r0 (31,)                                         (E1)

and the residual kernel estimator (`ResidualKernelEstimator`, fitted by
`spherejax.estimation.kernel_residual`, which has the whole model E8-E12): the affine one plus a
kernel regression of what it leaves,

    r = W v + r0 + A k(v),  k_j(v) = exp(-|S'(v - mu) - z'_j|^2 / 2)              (E8-E10)

with the lengthscale folded into S' = S / l and z'_j = z_j / l (`KernelResidual`).
`CrossValidation` is the report of one method's held-out errors that an estimator carries.

Apply with `wiener(v, estimator)` (or a plain (31, B) matrix): reflectance (..., 31).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import _checks
from ..grid import N_WAVELENGTHS

_HIGHEST = jax.lax.Precision.HIGHEST


@dataclasses.dataclass(frozen=True)
class CrossValidation:
    """Cross-validated errors of one method at its chosen regularisers (hashable: it rides in
    the estimator's static part).

    method: "training", "model" or "kernel". spectral_rms: rms over held-out targets and wavelengths of
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


class ResidualVariance(eqx.Module):
    """The kernel residual's own uncertainty at a response (E15), a pytree: the predictive
    variance of the Gaussian-process reading of (E11) (deterministic training conditional,
    Quinonero-Candela & Rasmussen 2005, Eq. 20), per residual component j = 1..r:

        var_j(v) = s_j^2 (1 - |g|^2) + sum_i C_ji g_i^2,   g = X^T k(v)             (E15)

    with k(v) (m,) the kernel features of (E10), X (m, q) such that X X^T = K_mm^-1 and
    X^T (K_mn K_nm) X diagonal (gamma_i), C_ji = sigma_j^2 / (lambda_j + gamma_i), s_j^2 and
    sigma_j^2 the component's signal and noise variances and lambda_j = sigma_j^2 / s_j^2 its
    ridge (E13-E14). Far from the targets k(v) -> 0 and var_j -> s_j^2 (the prior: the
    estimator knows nothing there); at a target it falls to about the noise over the targets near it.

    components: P (r, 31), the residual's principal directions (E13): reflectance covariance
    sum_j var_j P_j P_j^T. prior: s_j^2 (r,). projection: X (m, q). weights: C (r, q).
    noise: (31,) the per-wavelength variance of a target's reflectance about the fit (its noise
    sigma_j^2 through P, and the part of the residual beyond rank r), in reflectance squared.
    """

    # Arrays as jax.Arrays whatever the caller passes (NumPy included), as Calibration's fields: a
    # calibration's arrays then all name their device, which its plan's route needs (_engine.plan).
    components: jax.Array = eqx.field(converter=jnp.asarray)
    prior: jax.Array = eqx.field(converter=jnp.asarray)
    projection: jax.Array = eqx.field(converter=jnp.asarray)
    weights: jax.Array = eqx.field(converter=jnp.asarray)
    noise: jax.Array = eqx.field(converter=jnp.asarray)

    def __check_init__(self):
        if self.components.ndim != 2 or self.components.shape[1] != N_WAVELENGTHS:
            raise ValueError(f"components: expected shape (r, 31), got {tuple(self.components.shape)}")
        rank = self.components.shape[0]
        _checks.require_shape("prior", self.prior, (rank,), "one value per component")
        if self.projection.ndim != 2:
            raise ValueError(f"projection: expected shape (m, q), got {tuple(self.projection.shape)}")
        _checks.require_shape("weights", self.weights, (rank, self.projection.shape[1]), "components x q")
        _checks.require_shape("noise", self.noise, (N_WAVELENGTHS,), "one value per wavelength")

    def astype(self, dtype) -> ResidualVariance:
        return ResidualVariance(*(x.astype(dtype) for x in (self.components, self.prior, self.projection,
                                                             self.weights, self.noise)))

    def component_variance(self, features):
        """var_j (..., r) of (E15) for kernel features k (..., m), never below 0."""
        dtype = features.dtype
        g = jnp.matmul(features, self.projection.astype(dtype), precision=_HIGHEST)
        g2 = g * g
        known = jnp.sum(g2, axis=-1, keepdims=True)
        variance = (self.prior.astype(dtype) * (1.0 - known)
                    + jnp.matmul(g2, self.weights.astype(dtype).T, precision=_HIGHEST))
        return jnp.maximum(variance, 0.0)

    def reflectance_variance(self, features):
        """The residual's variance per wavelength (..., 31) for kernel features k (..., m)."""
        P = self.components.astype(features.dtype)
        return jnp.matmul(self.component_variance(features), P * P, precision=_HIGHEST)


class KernelResidual(eqx.Module):
    """The residual term A k(v) of (E8-E10), a pytree: what a calibration adds to its affine
    estimator (`spherejax.Calibration.wiener_residual`).

    centre: mu (B,). whitening: S' (B, B), rows applied to v - mu: the whitening with each
    direction's lengthscale folded in (E9-E10). inducing: z' (m, B). weights: A (31, m).
    variance: its `ResidualVariance` (E15), or None (a residual fitted before the estimator
    carried its uncertainty). Called on responses (..., B): the residual (..., 31).
    """

    # jax.Arrays whatever the caller passes (ResidualVariance says why): built from NumPy arrays, a
    # residual left its calibration without a device, and `correct` took the slow whole-program
    # route (a fresh copy of the frames and fresh output pages every call: 1.7x the time at 64
    # inducing points, measured on 2 Zen 4 cores).
    centre: jax.Array = eqx.field(converter=jnp.asarray)
    whitening: jax.Array = eqx.field(converter=jnp.asarray)
    inducing: jax.Array = eqx.field(converter=jnp.asarray)
    weights: jax.Array = eqx.field(converter=jnp.asarray)
    variance: ResidualVariance | None = None

    def __check_init__(self):
        if self.centre.ndim != 1:
            raise ValueError(f"centre: expected shape (B,), one value per band, got {tuple(self.centre.shape)}")
        bands = self.centre.shape[0]
        _checks.require_shape("whitening", self.whitening, (bands, bands), "bands x bands")
        if self.inducing.ndim != 2 or self.inducing.shape[1] != bands:
            raise ValueError(f"inducing: expected shape (m, {bands}), got {tuple(self.inducing.shape)}")
        _checks.require_shape("weights", self.weights, (N_WAVELENGTHS, self.inducing.shape[0]), "31 x inducing points")
        if self.variance is not None and self.variance.projection.shape[0] != self.inducing.shape[0]:
            raise ValueError(f"variance.projection: expected {self.inducing.shape[0]} rows (one per inducing point), "
                             f"got {tuple(self.variance.projection.shape)}")

    @property
    def bands(self) -> int:
        return int(self.centre.shape[0])

    def astype(self, dtype) -> KernelResidual:
        return KernelResidual(*(x.astype(dtype) for x in (self.centre, self.whitening, self.inducing, self.weights)),
                              variance=None if self.variance is None else self.variance.astype(dtype))

    def features(self, v):
        """k(v) (..., m) of (E10) for responses v (..., B), in v's float dtype."""
        dtype = v.dtype
        return kernel_features(v, self.centre.astype(dtype), self.whitening.astype(dtype), self.inducing.astype(dtype))

    def reflectance_variance(self, v):
        """The residual's own variance per wavelength (..., 31) at responses v (..., B) (E15);
        zeros without a `variance`."""
        if self.variance is None:
            return jnp.zeros((*v.shape[:-1], N_WAVELENGTHS), v.dtype)
        return self.variance.reflectance_variance(self.features(v))

    def __call__(self, v):
        """A k(v) (..., 31) for responses v (..., B), in v's float dtype."""
        return jnp.matmul(self.features(v), self.weights.astype(v.dtype).T, precision=_HIGHEST)


class ResidualKernelEstimator(eqx.Module):
    """r = W v + r0 + A k(v) (E8-E10), a pytree: `affine` (a `WienerEstimator`, W (31, B) and
    r0 (31,)) and `kernel` (its `KernelResidual`).

    method: "kernel" (static). cross_validation: every method tried, the chosen one first
    (static), as `WienerEstimator.cross_validation`.
    """

    affine: WienerEstimator
    kernel: KernelResidual
    method: str = eqx.field(static=True, default="kernel")
    cross_validation: tuple[CrossValidation, ...] = eqx.field(static=True, default=())

    def __check_init__(self):
        bands = self.affine.matrix.shape[1]
        if self.kernel.bands != bands:
            raise ValueError(f"kernel: expected a residual of the affine estimator's {bands} bands, got {self.kernel.bands}")

    @property
    def matrix(self) -> jax.Array:
        """The affine mean's W (31, B)."""
        return self.affine.matrix

    @property
    def offset(self) -> jax.Array:
        """The affine mean's r0 (31,)."""
        return self.affine.offset

    def __call__(self, v):
        return wiener(v, self)


def kernel_features(v, centre, whitening, inducing):
    """k(v) (..., m) of (E9-E10) with the lengthscale folded into `whitening` and `inducing`:
    exp(-|S'(v - mu) - z'_j|^2 / 2), |a - b|^2 expanded as |a|^2 - 2 a.b + |b|^2 (matrix products)
    and clipped at 0 against round-off."""
    u = jnp.matmul(v - centre, whitening.T, precision=_HIGHEST)
    squared = (jnp.sum(u * u, axis=-1, keepdims=True) - 2.0 * jnp.matmul(u, inducing.T, precision=_HIGHEST)
               + jnp.sum(inducing * inducing, axis=-1))
    return jnp.exp(-0.5 * jnp.maximum(squared, 0.0))


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
        `ResidualKernelEstimator` (its affine mean plus its residual, E8).

    Returns:
      reflectance, shape (..., 31), 400..700 nm step 10.
    """
    v = _checks.band_array("v", v)
    if isinstance(W, ResidualKernelEstimator):
        dtype = _checks.float_dtype(v, W.matrix)
        return wiener(v.astype(dtype), W.affine) + W.kernel(v.astype(dtype))
    estimator = as_estimator(W)
    W = estimator.matrix
    _checks.require_shape("W", W, (N_WAVELENGTHS, v.shape[-1]), "31 wavelengths x the bands of v")
    dtype = _checks.float_dtype(v, W)
    return jnp.matmul(v.astype(dtype), W.astype(dtype).T, precision=_HIGHEST) + estimator.offset.astype(dtype)


__all__ = [
    "CrossValidation",
    "KernelResidual",
    "ResidualKernelEstimator",
    "ResidualVariance",
    "WienerEstimator",
    "as_estimator",
    "kernel_features",
    "wiener",
]
