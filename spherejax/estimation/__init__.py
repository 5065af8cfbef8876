"""Estimation of 31-sample reflectance from 16-band camera responses, by method.

Zou et al. (2019) reconstruct reflectance with a 31 x 16 matrix computed from 144 colour targets
of known reflectance by Wiener estimation (Section 2 and their ref. [21]). Every estimator here is
affine in the response, r = W v + r0 (E1), so that `correct` stays one matrix product per pixel.
Real responses carry an offset (a residual dark level, stray light) and noise that differs by
band, and a lab's targets never match its samples exactly; both methods model that. As
colour-science's `colour.recovery` does, one module per method, named after its reference where
the code cites one, and a mapping from the method's name to its function:

  estimator         `WienerEstimator` (E1), `wiener` (apply it), `CrossValidation` (a report).
  regression        "training": a ridge regression on the targets, no knowledge of the system
                    (E2), `training_estimator`.
  haneishi2000      "model": the system (sensitivity, offset, per-band noise) estimated from the
                    targets and the linear minimum mean-square-error estimator through it
                    (Haneishi et al. 2000; Shen & Xin 2006) (E3-E7), `model_estimator`,
                    `wiener_from_system`.
  cross_validation  the folds (groups held out in turn, or k-means clusters of spectrally alike
                    targets), each method's regularisers chosen on them, the "auto" choice,
                    `estimate_system`.
  covariance        the sampling covariance of an estimator from its training set (C1).
  kernel_residual   "kernel": an affine estimator plus a kernel regression of its residuals
                    on targets of the material measured (E8-E11), `fit_kernel_estimator`; not
                    affine, so not yet one of `METHODS` (the correction applies affine
                    estimators only).

`fit_wiener(responses, reflectances, method=...)` fits one: `METHODS` maps each method's name to
its cross-validated fit, and `METHOD_NAMES` ("auto" and the names of `METHODS`) are the names any
caller accepts, checked by `validate_method`.
"""

from __future__ import annotations

import dataclasses
import types

import jax.numpy as jnp
import numpy as np

from .. import _checks
from .covariance import EstimatorCovariance, estimator_covariance
from .cross_validation import (
    DEFAULT_FOLDS,
    Candidate,
    cross_validate_model,
    cross_validate_training,
    estimate_system,
    fold_labels,
    fold_weights,
    rank_candidates,
    _weights_of,
)
from .estimator import (
    CrossValidation,
    WienerEstimator,
    _check_determined,
    _check_noise_variance,
    _check_sensitivity,
    _check_training,
    as_estimator,
    wiener,
)
from .haneishi2000 import (
    MARKOV_PRIOR_CORRELATION,
    PRIOR_SHRINKAGE_GRID,
    SENSITIVITY_PENALTIES,
    SENSITIVITY_PENALTY_GRID,
    markov_correlation,
    model_estimator,
    wiener_from_system,
)
from .kernel_residual import (
    INDUCING_POINTS,
    KERNEL_LENGTHSCALE_GRID,
    KERNEL_RIDGE_GRID,
    KernelResidual,
    ResidualKernelEstimator,
    cross_validate_kernel,
)
from .regression import RELATIVE_NOISE_GRID, _training_fit, training_estimator

#: Method name -> its fit at regularisers chosen by cross-validation (`cross_validation`):
#: f(V, R, weights, folds_text, *, offset, sensitivity) -> `Candidate`. Read-only.
METHODS = types.MappingProxyType({
    "training": cross_validate_training,
    "model": cross_validate_model,
})

#: The method names a caller may give (`fit_wiener`'s method, `calibrate`'s wiener_method, the
#: command line's --wiener-method): "auto" (every method of `METHODS`, the one with the least
#: cross-validated spectral rms kept) and each name of `METHODS`.
METHOD_NAMES = ("auto", *METHODS)


#: The estimators a calibration can be made with (`calibrate_session`'s wiener_method, the command
#: line's --wiener-method): the affine methods (`METHOD_NAMES`) and "kernel", the residual kernel
#: estimator on the affine one "auto" chooses (`fit_kernel_estimator`).
ESTIMATOR_NAMES = (*METHOD_NAMES, "kernel")


def validate_method(method, name: str = "method", names: tuple[str, ...] = METHOD_NAMES) -> str:
    """`method` if it is one of `names` (default `METHOD_NAMES`); else ValueError naming `name`,
    the value and the choices, e.g. "method: expected one of ('auto', 'training', 'model'), got
    'wiener'"."""
    if not isinstance(method, str) or method not in names:
        raise ValueError(f"{name}: expected one of {names}, got {method!r}")
    return method


def fit_wiener(
    responses,
    reflectances,
    noise_variance=None,
    *,
    method: str = "auto",
    groups=None,
    folds: int = DEFAULT_FOLDS,
    sensitivity=None,
    offset: bool = True,
) -> WienerEstimator:
    """An affine reflectance estimator r = W v + r0 from targets of known reflectance.

    Args:
      responses: corrected camera responses of the targets, shape (n, B) (144 targets in the
        paper; Stage II responses in the full method).
      reflectances: their measured reflectances, shape (n, 31), 400..700 nm step 10.
      noise_variance: sigma^2 of the training form (>= 0, response units squared); given, it
        fixes the method to "training" with no cross-validation (the first release's call).
      method: "auto" (default: the method and regularisers with the lowest cross-validated
        spectral rms), "training" (E2) or "model" (E3-E7) (`METHOD_NAMES`).
      groups: optional label per target (n,), e.g. material or chart: cross-validation then holds
        out one group at a time. None: `folds` clusters of spectrally alike targets.
      folds: the number of folds without groups.
      sensitivity: a known sensitivity M (B, 31) for the model form (with "auto" the model form
        uses it; only b and K_n are then estimated).
      offset: False fits the training form without r0 (the first release's form).

    Returns:
      WienerEstimator: .matrix (31, B), .offset (31,), .method, .cross_validation (each method
      tried, the chosen one first, with its held-out spectral rms and mean ΔE00 under D65).

    The fits run on the responses divided by the power of two nearest their rms (exact, so
    flat-fielded responses give the same bits), which keeps responses in any units, 1e-30 to
    1e30, inside float32's range; W and the reported sigma^2 are in the caller's units.

    Raises:
      ValueError: on shapes, non-finite data, or targets that do not vary (nothing to fit).
    """
    V, R = _check_training(responses, reflectances)
    method = validate_method(method)
    if noise_variance is not None:
        if method == "model":
            raise ValueError("noise_variance: applies to the training form; got it with method='model'")
        _check_noise_variance(noise_variance)
        W, r0 = _training_fit(V, R, jnp.ones(V.shape[0], V.dtype), jnp.asarray(noise_variance, V.dtype), offset)
        return WienerEstimator(W, r0, method="training")
    if not (_checks.is_concrete(V) and _checks.is_concrete(R)):
        raise ValueError(
            "fit_wiener: choosing regularisers by cross-validation needs concrete data, not traced "
            "values; call it outside jit/grad, or use training_estimator / model_estimator with "
            "fixed regularisers inside"
        )
    _check_determined(V, R, "a Wiener estimator")
    scale, V, R, weights, folds_text, ranked = _affine_candidates(V, R, method, groups, folds, sensitivity, offset)
    W, r0 = ranked[0].fit()
    reports = tuple(_in_response_units(candidate.cross_validation, scale) for candidate in ranked)
    return WienerEstimator(W / scale, r0, method=ranked[0].cross_validation.method, cross_validation=reports)


def _affine_candidates(V, R, method, groups, folds, sensitivity, offset):
    """(scale, V / scale, R, fold weights (F, n), folds' description, the affine methods'
    Candidates ranked, the best first) for checked targets V (n, B), R (n, 31)."""
    # Fit in units where the responses' rms is about 1: responses of 1e30 (or 1e-30) would
    # overflow (underflow) the squares of the fits in float32. A power of two, so that scaling is
    # exact and responses near 1 (flat-fielded ones) give the same bits as unscaled.
    scale = _unit_scale(V)
    V = V / scale
    M = None if sensitivity is None else _check_sensitivity(sensitivity, V) / scale
    labels, folds_text = fold_labels(R, groups, folds)
    weights = _weights_of(labels)
    names = tuple(METHODS) if method == "auto" else (method,)
    ranked = rank_candidates(
        METHODS[name](V, R, weights, folds_text, offset=offset, sensitivity=M) for name in names
    )
    return scale, V, R, weights, folds_text, ranked


def fit_kernel_estimator(
    responses,
    reflectances,
    *,
    mean: str = "auto",
    groups=None,
    folds: int = DEFAULT_FOLDS,
    sensitivity=None,
    inducing_points: int = INDUCING_POINTS,
) -> ResidualKernelEstimator:
    """The residual kernel estimator r = W v + r0 + A k(v) (E8-E11) from targets of known
    reflectance: the affine estimator `fit_wiener` would choose as its mean, and a kernel
    regression of what it leaves, its lengthscale and ridge chosen by the same cross-validation.

    Args:
      responses: (n, B). reflectances: (n, 31). groups, folds, sensitivity: as `fit_wiener`.
      mean: the affine method of the mean, "auto" (default), "training" or "model".
      inducing_points: m, the kernel's centres (per-pixel cost 3 B m + 31 m multiply-adds).

    Returns:
      ResidualKernelEstimator; .cross_validation: the kernel's held-out errors first (its
      settings name the mean, lengthscale, ridge and m), then every affine method tried.

    Raises:
      ValueError: as `fit_wiener`, and on inducing_points < 1.
    """
    V, R = _check_training(responses, reflectances)
    method = validate_method(mean, "mean")
    if not isinstance(inducing_points, (int, np.integer)) or inducing_points < 1:
        raise ValueError(f"inducing_points: expected an integer >= 1, got {inducing_points!r}")
    if not (_checks.is_concrete(V) and _checks.is_concrete(R)):
        raise ValueError("fit_kernel_estimator: cross-validation needs concrete data, not traced values")
    _check_determined(V, R, "a kernel estimator")
    scale, V, R, weights, folds_text, ranked = _affine_candidates(V, R, method, groups, folds, sensitivity, True)
    kernel = cross_validate_kernel(V, R, weights, folds_text, ranked[0], inducing_points=int(inducing_points))
    W, r0, mu, S, Z, A = kernel.fit()
    affine_reports = tuple(_in_response_units(candidate.cross_validation, scale) for candidate in ranked)
    # Back to the caller's response units: u = S (v / scale - mu) = (S / scale) (v - scale mu).
    affine = WienerEstimator(W / scale, r0, method=ranked[0].cross_validation.method, cross_validation=affine_reports)
    return ResidualKernelEstimator(
        affine, KernelResidual(mu * scale, S / scale, Z, A), cross_validation=(kernel.cross_validation, *affine_reports),
    )


def _unit_scale(V) -> float:
    """The power of two nearest the rms of V (1 if V is all zero)."""
    rms = float(np.sqrt(np.mean(np.square(np.asarray(V, np.float64)))))
    return 1.0 if not rms > 0 else float(2.0 ** np.round(np.log2(rms)))


def _in_response_units(report: CrossValidation, scale: float) -> CrossValidation:
    """A report of a fit on responses / scale, with sigma^2 back in the caller's units."""
    settings = tuple((k, v * scale**2 if k == "noise_variance" else v) for k, v in report.settings)
    return dataclasses.replace(report, settings=settings)


__all__ = [
    "DEFAULT_FOLDS",
    "ESTIMATOR_NAMES",
    "INDUCING_POINTS",
    "KERNEL_LENGTHSCALE_GRID",
    "KERNEL_RIDGE_GRID",
    "KernelResidual",
    "ResidualKernelEstimator",
    "cross_validate_kernel",
    "fit_kernel_estimator",
    "MARKOV_PRIOR_CORRELATION",
    "METHODS",
    "METHOD_NAMES",
    "PRIOR_SHRINKAGE_GRID",
    "RELATIVE_NOISE_GRID",
    "SENSITIVITY_PENALTIES",
    "SENSITIVITY_PENALTY_GRID",
    "Candidate",
    "CrossValidation",
    "EstimatorCovariance",
    "WienerEstimator",
    "as_estimator",
    "cross_validate_model",
    "cross_validate_training",
    "estimate_system",
    "estimator_covariance",
    "fit_wiener",
    "fold_labels",
    "fold_weights",
    "markov_correlation",
    "model_estimator",
    "rank_candidates",
    "training_estimator",
    "validate_method",
    "wiener",
    "wiener_from_system",
]
