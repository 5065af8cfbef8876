"""Estimation of 31-sample reflectance from 16-band camera responses, by method.

Zou et al. (2019) reconstruct reflectance with a 31 x 16 matrix computed from 144 colour targets
of known reflectance by Wiener estimation (Section 2 and their ref. [21]). The estimators here are
affine in the response, r = W v + r0 (E1), or that plus a kernel regression of what it leaves
(E8-E15), which dyed materials need (their reflectances lie on a curved set, Kubelka-Munk).
Real responses carry an offset (a residual dark level, stray light) and noise that differs by
band, and a lab's targets never match its samples exactly; both methods model that. As
colour-science's `colour.recovery` does, one module per method, named after its reference where
the code cites one, and a mapping from the method's name to its function.

The modules, each importing only those listed above it:

  estimator         what a fit returns and how it is applied, with no fitting: `WienerEstimator`
                    (E1), `KernelResidual` and `ResidualKernelEstimator` (E8-E10),
                    `CrossValidation` (one method's held-out errors, the report an estimator
                    carries), `wiener` (applies any of them). The pipeline, the engine and
                    calibration files need only this module.
  _targets          the checks of the colour targets a fit takes (responses (n, B), reflectances
                    (n, 31)) and their weighted means, shared by the fits.
  regression        "training": a ridge regression on the targets, no knowledge of the system
                    (E2), `training_estimator`.
  haneishi2000      "model": the system (sensitivity, offset, per-band noise) estimated from the
                    targets and the linear minimum mean-square-error estimator through it
                    (Haneishi et al. 2000; Shen & Xin 2006) (E3-E7), `model_estimator`,
                    `wiener_from_system`.
  cross_validation  the folds (groups held out in turn, k-means clusters of spectrally alike
                    targets, or targets drawn at random), each affine method's regularisers
                    chosen on them (`Candidate`), their ranking, `estimate_system`.
  gp_hyperparameters the kernel estimator's lengthscales (one per whitened direction) and each
                    residual component's signal and noise, by marginal likelihood (E14,
                    optimistix), `fit_hyperparameters`.
  kernel_residual   "kernel": the fit of the residual kernel estimator on an affine mean: its
                    components, inducing points, weights and own variance, the count of inducing
                    points and the rank chosen by held-out accuracy (E9-E15), `kernel_gain`.
  local_regression  "local": locally weighted regression of the affine residual, cross-validated
                    and reported beside the others, never chosen (its cost per pixel).
  covariance        the sampling covariance of an affine estimator from its training set (C1).
  _offset_free      the offset-free baseline estimators (no r0): the training form's sigma^2 by
                    leave-one-out and the uncentred model-based matrix of a known system; not
                    among this package's names (`spherejax.wiener_estimation` re-exports them).

This package's own module chooses and fits: `fit_estimator(responses, reflectances, method=...)`
(also `fit_wiener`, the paper's name, Wiener estimation) cross-validates the affine methods and,
where the targets show a real gain (`KERNEL_MIN_GAIN`, `KERNEL_MIN_Z`, from
`KERNEL_MIN_TARGETS` targets), takes the kernel estimator on the best of them;
`fit_kernel_estimator` fits the kernel estimator whatever its gain. `METHODS` maps each affine
method's name to its cross-validated fit, `METHOD_NAMES` ("auto" and the names of `METHODS`) are
the affine choices and `ESTIMATOR_NAMES` those and "kernel", checked by `validate_method`.
"""

from __future__ import annotations

import dataclasses
import types

import jax.numpy as jnp
import numpy as np

from .. import _checks
from ..grid import N_WAVELENGTHS
from .covariance import EstimatorCovariance, estimator_covariance
from .cross_validation import (
    DEFAULT_FOLDS,
    Candidate,
    cross_validate_model,
    cross_validate_training,
    estimate_system,
    fold_labels,
    fold_weights,
    random_fold_labels,
    rank_candidates,
    _weights_of,
)
from ._targets import _check_determined, _check_noise_variance, _check_sensitivity, _check_training
from .estimator import (
    CrossValidation,
    KernelResidual,
    ResidualKernelEstimator,
    ResidualVariance,
    WienerEstimator,
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
    INDUCING_POINT_COUNTS,
    RANKS,
    cross_validate_kernel,
    kernel_gain,
)
from .local_regression import cross_validate_local
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


#: "auto" takes the kernel estimator only where its cross-validated spectral rms is at least this
#: fraction below the best affine method's (on the same folds), and `KERNEL_MIN_Z` says the
#: targets show it together. Why 2 %: the gain must pay for up to 3x the affine estimator's time
#: per pixel in `correct` (`kernel_residual.INDUCING_POINT_COUNTS`) and for what it may cost on a
#: material other than its targets' (0.86-1.08x the affine estimator's rms over the 56 pairs of
#: the Kubelka-Munk and `target_families` sets, within 5 % of the published Wiener estimator on
#: 52: benchmarks/bench_wiener.py). At
#: 5 %, as before, auto refused gains that held on new samples: shade_card's cross-validation
#: showed 3.2 % (z 4.4) for a kernel estimator that lowered 200 new samples' rms by 11 %, and real
#: materials' forced kernel estimators gained 1-5 % where auto took the affine one.
KERNEL_MIN_GAIN = 0.02

#: ... and where the targets' paired differences (each target's held-out squared error, affine
#: minus kernel) have a mean at least this many standard errors above zero: a gain the targets
#: show together, not a few of them by chance (2: about 1 in 40 for a gain that is not there, the
#: targets taken as independent).
KERNEL_MIN_Z = 2.0

#: "auto" tries the kernel estimator from this many targets on. Below it, a fold holds out fewer
#: than 10 targets (5 folds): too few for a per-target comparison to tell a 5 % gain, and the
#: regression of residuals on so few has little to learn.
KERNEL_MIN_TARGETS = 50


#: "auto" cross-validates the local method (reported only) up to this many targets: its
#: cross-validation costs every target a weighted fit over the others at 17 bandwidths, n^2 work
#: (0.3-0.5 s at 200 targets, 2.3 s at 500 on 2 cores; 4 000 would take minutes).
LOCAL_MAX_TARGETS = 1000


def fit_estimator(
    responses,
    reflectances,
    noise_variance=None,
    *,
    method: str = "auto",
    groups=None,
    folds: int = DEFAULT_FOLDS,
    sensitivity=None,
    offset: bool = True,
    inducing_points: int | None = None,
) -> WienerEstimator | ResidualKernelEstimator:
    """A reflectance estimator from targets of known reflectance: affine (r = W v + r0, E1) or,
    where its targets show what an affine map cannot follow, the residual kernel estimator
    (r = W v + r0 + A k(v), E8-E15). `fit_wiener` is this function.

    Args:
      responses: corrected camera responses of the targets, shape (n, B) (144 targets in the
        paper; Stage II responses in the full method).
      reflectances: their measured reflectances, shape (n, 31), 400..700 nm step 10.
      noise_variance: sigma^2 of the training form (>= 0, response units squared); given, it
        fixes the method to "training" with no cross-validation.
      method: "auto" (default): every affine method at its cross-validated regularisers, the one
        with the least held-out spectral rms kept, and, from `KERNEL_MIN_TARGETS` targets on,
        the kernel estimator on it, taken only where its held-out spectral rms is at least
        `KERNEL_MIN_GAIN` lower and the per-target differences at least `KERNEL_MIN_Z` standard
        errors above zero; "training" (E2) or "model" (E3-E7), affine; "kernel": the kernel
        estimator whatever its gain (`ESTIMATOR_NAMES`).
      groups: optional label per target (n,), e.g. material or chart: cross-validation then holds
        out one group at a time. None: `folds` clusters of spectrally alike targets.
      folds: the number of folds without groups.
      sensitivity: a known sensitivity M (B, 31) for the model form (with "auto" the model form
        uses it; only b and K_n are then estimated).
      offset: False fits the training form without r0 (affine only).
      inducing_points: m of the kernel estimator: None (default) chooses it by held-out
        accuracy among `INDUCING_POINT_COUNTS`; an integer >= 1 fixes it.

    Returns:
      WienerEstimator (.matrix (31, B), .offset (31,)) or ResidualKernelEstimator (.affine, its
      mean, and .kernel); either way .method (the one chosen) and .cross_validation: every
      method tried with its held-out spectral rms and mean ΔE00 under D65, the chosen one first;
      the kernel's settings include its gain over the best affine method and the paired z.
      `wiener(v, estimator)` applies either.

    The fits run on the responses divided by the power of two nearest their rms (exact, so
    flat-fielded responses give the same bits), which keeps responses in any units, 1e-30 to
    1e30, inside float32's range; W and the reported sigma^2 are in the caller's units.

    Raises:
      ValueError: on shapes, non-finite data, or targets that do not vary (nothing to fit).
    """
    V, R = _check_training(responses, reflectances)
    method = validate_method(method, names=ESTIMATOR_NAMES)
    if noise_variance is not None:
        if method != "training" and method != "auto":
            raise ValueError(f"noise_variance: applies to the training form; got it with method={method!r}")
        _check_noise_variance(noise_variance)
        W, r0 = _training_fit(V, R, jnp.ones(V.shape[0], V.dtype), jnp.asarray(noise_variance, V.dtype), offset)
        return WienerEstimator(W, r0, method="training")
    if method == "kernel":
        if not offset:
            raise ValueError("offset: the kernel estimator's affine mean has an offset; got offset=False with method='kernel'")
        return fit_kernel_estimator(responses, reflectances, groups=groups, folds=folds, sensitivity=sensitivity,
                                    inducing_points=inducing_points)
    if not (_checks.is_concrete(V) and _checks.is_concrete(R)):
        raise ValueError(
            "fit_wiener: choosing regularisers by cross-validation needs concrete data, not traced "
            "values; call it outside jit/grad, or use training_estimator / model_estimator with "
            "fixed regularisers inside"
        )
    _check_determined(V, R, "a Wiener estimator")
    _check_inducing_points(inducing_points)
    scale, V, R, weights, folds_text, ranked = _affine_candidates(V, R, method, groups, folds, sensitivity, offset)
    affine_reports = tuple(_in_response_units(candidate.cross_validation, scale, V.shape[1]) for candidate in ranked)
    if method == "auto" and offset and V.shape[0] >= KERNEL_MIN_TARGETS:
        kernel_weights, kernel_text = _kernel_folds(V, weights, folds_text, groups, folds)
        kernel = _kernel_candidate(V, R, kernel_weights, kernel_text, ranked[0], inducing_points)
        # The local method (`local_regression`) is cross-validated beside the others on the
        # kernel estimator's folds and reported, never taken: applying it costs every pixel a
        # weighted fit over the targets (~45 000 multiply-adds at 200 targets, 80x the affine
        # estimator's 31 B), far beyond the kernel contract's 3x.
        local = ()
        if V.shape[0] <= LOCAL_MAX_TARGETS:
            local = (cross_validate_local(V, R, kernel_weights, kernel_text, mean=ranked[0]).cross_validation,)
        settings = dict(kernel.cross_validation.settings)
        if settings["gain"] >= KERNEL_MIN_GAIN and settings["paired_z"] >= KERNEL_MIN_Z:
            return _kernel_estimator(kernel, (*affine_reports, *local), ranked[0], scale)
        affine_reports = (*affine_reports, kernel.cross_validation, *local)
    W, r0 = ranked[0].fit()
    return WienerEstimator(W / scale, r0, method=ranked[0].cross_validation.method, cross_validation=affine_reports)


#: `fit_estimator` under the paper's name (Wiener estimation; docs/design.md).
fit_wiener = fit_estimator


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
    inducing_points: int | None = None,
) -> ResidualKernelEstimator:
    """The residual kernel estimator r = W v + r0 + A k(v) (E8-E11) from targets of known
    reflectance: the affine estimator `fit_wiener` would choose as its mean, and a kernel
    regression of what it leaves, its lengthscale and ridge chosen by the same cross-validation.

    Args:
      responses: (n, B). reflectances: (n, 31). groups, folds, sensitivity: as `fit_wiener`.
      mean: the affine method of the mean, "auto" (default), "training" or "model".
      inducing_points: m, the kernel's centres: None (default) chooses it by held-out accuracy
        among `INDUCING_POINT_COUNTS`; an integer >= 1 fixes it (per-pixel cost about (B + r) m
        multiply-adds and m exponentials, `kernel_residual.residual_multiply_adds`).

    Returns:
      ResidualKernelEstimator; .cross_validation: the kernel's held-out errors first (its
      settings name the mean, lengthscale, ridge, m, its gain over the mean and the paired z of
      `kernel_gain`), then every affine method tried.

    Raises:
      ValueError: as `fit_wiener`, and on inducing_points < 1.
    """
    V, R = _check_training(responses, reflectances)
    method = validate_method(mean, "mean")
    _check_inducing_points(inducing_points)
    if not (_checks.is_concrete(V) and _checks.is_concrete(R)):
        raise ValueError("fit_kernel_estimator: cross-validation needs concrete data, not traced values")
    _check_determined(V, R, "a kernel estimator")
    scale, V, R, weights, folds_text, ranked = _affine_candidates(V, R, method, groups, folds, sensitivity, True)
    kernel = _kernel_candidate(V, R, *_kernel_folds(V, weights, folds_text, groups, folds), ranked[0], inducing_points)
    affine_reports = tuple(_in_response_units(candidate.cross_validation, scale, V.shape[1]) for candidate in ranked)
    return _kernel_estimator(kernel, affine_reports, ranked[0], scale)


def _kernel_candidate(V, R, weights, folds_text, mean: Candidate, inducing_points) -> Candidate:
    """The kernel estimator's `Candidate` on the affine `mean`, cross-validated over its folds
    (`weights`, `folds_text`: `_kernel_folds`)."""
    return cross_validate_kernel(V, R, weights, folds_text, mean,
                                 inducing_points=None if inducing_points is None else int(inducing_points))


def _kernel_folds(V, weights, folds_text, groups, folds):
    """(fold weights (F, n), description) of the kernel estimator's cross-validation (and the
    local method's): the affine methods' where groups are given (a group held out whole), else
    `folds` folds of targets drawn at random (`random_fold_labels`).

    Why not the affine methods' k-means folds: they hold out clusters of alike colours, which
    asks how an estimator extrapolates to colours the targets lack, the question for an affine
    estimator that must serve samples unlike its targets. The kernel estimator is for samples of
    the targets' material, which lie among them: on the Kubelka-Munk families (200 targets) the
    k-means folds showed a gain of 3-8 % for a kernel estimator that lowered the spectral rms of
    200 new samples of the family by 30-38 %; folds drawn at random showed 21-38 %."""
    if groups is None:
        labels, folds_text = random_fold_labels(V.shape[0], folds)
        weights = _weights_of(labels)
    return weights, folds_text


def _check_inducing_points(inducing_points) -> None:
    if inducing_points is None:
        return
    if not isinstance(inducing_points, (int, np.integer)) or isinstance(inducing_points, bool) or inducing_points < 1:
        raise ValueError(f"inducing_points: expected an integer >= 1, got {inducing_points!r}")


def _kernel_estimator(kernel: Candidate, affine_reports, mean: Candidate, scale: float):
    """The ResidualKernelEstimator of the kernel `Candidate` fitted on responses / scale, in the
    caller's response units, its report first."""
    W, r0, mu, S, Z, A, variance = kernel.fit()
    # Back to the caller's response units: u = S (v / scale - mu) = (S / scale) (v - scale mu).
    # The variance (E15) is in reflectance units and the kernel's features, which the scale
    # does not change.
    affine = WienerEstimator(W / scale, r0, method=mean.cross_validation.method, cross_validation=affine_reports)
    return ResidualKernelEstimator(
        affine, KernelResidual(mu * scale, S / scale, Z, A, variance=variance),
        cross_validation=(kernel.cross_validation, *affine_reports),
    )


def _unit_scale(V) -> float:
    """The power of two nearest the rms of V (1 if V is all zero)."""
    rms = float(np.sqrt(np.mean(np.square(np.asarray(V, np.float64)))))
    return 1.0 if not rms > 0 else float(2.0 ** np.round(np.log2(rms)))


def _in_response_units(report: CrossValidation, scale: float, bands: int) -> CrossValidation:
    """An affine method's report of a fit on responses / scale of B bands, with sigma^2 back in
    the caller's units and the multiply-adds per pixel of applying it (31 B: every report says
    what its estimator costs a pixel)."""
    settings = tuple((k, v * scale**2 if k == "noise_variance" else v) for k, v in report.settings)
    return dataclasses.replace(report, settings=(*settings, ("cost_per_pixel", N_WAVELENGTHS * bands)))


__all__ = [
    "DEFAULT_FOLDS",
    "ESTIMATOR_NAMES",
    "INDUCING_POINT_COUNTS",
    "RANKS",
    "KernelResidual",
    "ResidualKernelEstimator",
    "ResidualVariance",
    "cross_validate_kernel",
    "fit_estimator",
    "fit_kernel_estimator",
    "kernel_gain",
    "KERNEL_MIN_GAIN",
    "KERNEL_MIN_TARGETS",
    "KERNEL_MIN_Z",
    "LOCAL_MAX_TARGETS",
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
