"""Cross-validation: the folds, the held-out scores, the regularisers of each method chosen by
them, and the "auto" choice between the methods.

The regularisers (sigma^2 of the training form; the penalty and its weight on M and the
shrinkage s of the model form) and, for "auto", the method are chosen by cross-validation: whole
groups of targets are held out where the caller names groups (material, chart); otherwise k folds
whose members are spectrally alike (a k-means clustering of the reflectances), so that every
held-out fold holds colours the rest of the targets does not span. A random k-fold split scores
how well an estimator interpolates within the training material, which is what a training-based
fit is best at and what does not carry to another material (the reason this module chooses as it
does).

Each method's `cross_validate_*` function (the values of `spherejax.estimation.METHODS`) takes
the checked responses V (n, B) and reflectances R (n, 31), the folds' training weights (F, n)
(`fold_weights`) and their description, and returns a `Candidate`: the method's held-out errors
at its chosen regularisers and the fit at those regularisers on all the targets, computed when
called. `rank_candidates` orders them for the "auto" choice.
"""

from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..number_text import json_ready
from ._targets import _check_determined, _check_training
from .estimator import _HIGHEST, CrossValidation
from .haneishi2000 import (
    PRIOR_SHRINKAGE_GRID,
    SENSITIVITY_PENALTIES,
    SENSITIVITY_PENALTY_GRID,
    _model_fit,
    _penalty_root,
    _sensitivity_fit,
)
from .regression import RELATIVE_NOISE_GRID, _training_fit

#: Folds of the cross-validation when no groups are given.
DEFAULT_FOLDS = 5


# ---------------------------------------------------------------------------------------------
# The folds


def _kmeans_labels(X: np.ndarray, k: int, iterations: int = 50) -> np.ndarray:
    """Deterministic k-means labels of the rows of X (n, d): farthest-point initialisation from
    the row nearest the mean, then Lloyd iterations. Hand-written because it is twenty lines and
    must be deterministic and dependency-free (scikit-learn's is neither needed nor shipped)."""
    centres = [X[np.argmin(np.sum((X - X.mean(axis=0)) ** 2, axis=1))]]
    for _ in range(1, k):
        distance = np.min([np.sum((X - c) ** 2, axis=1) for c in centres], axis=0)
        centres.append(X[np.argmax(distance)])
    centres = np.stack(centres)
    labels = np.zeros(len(X), np.int64)
    for _ in range(iterations):
        labels_new = np.argmin(np.sum((X[:, None] - centres[None]) ** 2, axis=2), axis=1)
        if np.array_equal(labels_new, labels) and _ > 0:
            break
        labels = labels_new
        for j in range(k):
            if np.any(labels == j):
                centres[j] = X[labels == j].mean(axis=0)
    return labels


def fold_labels(reflectances, groups=None, folds: int = DEFAULT_FOLDS) -> tuple[np.ndarray, str]:
    """(label per target (n,), a description) of the cross-validation split.

    With `groups` (n,) (any hashable labels, e.g. material or chart names) each group is held out
    in turn. Without, `folds` clusters of spectrally alike targets (k-means on the reflectances'
    shapes, r / mean(r), so that a dark and a light sample of one hue fall together).
    """
    R = np.asarray(reflectances, np.float64)
    n = R.shape[0]
    if groups is not None:
        groups = np.asarray(groups)
        if groups.shape != (n,):
            raise ValueError(f"groups: expected one label per target, shape ({n},), got {groups.shape}")
        names, labels = np.unique(groups, return_inverse=True)
        if len(names) < 2:
            raise ValueError(
                f"groups: all {n} targets are in one group ({names[0]!r}); expected at least 2 groups "
                "to hold out in turn, or groups=None for k-fold cross-validation"
            )
        return labels.astype(np.int64), f"leave one group out ({len(names)} groups)"
    if not isinstance(folds, (int, np.integer)) or folds < 2:
        raise ValueError(f"folds: expected an integer >= 2, got {folds!r}")
    k = min(int(folds), n)
    shape = R / np.maximum(R.mean(axis=1, keepdims=True), 1e-6)
    return _kmeans_labels(shape, k), f"{k} folds of spectrally alike targets (k-means)"


def random_fold_labels(n: int, folds: int = DEFAULT_FOLDS, seed: int = 0) -> tuple[np.ndarray, str]:
    """(label per target (n,), a description) of `folds` folds of targets drawn at random: the
    rank of each target in a permutation seeded by `seed`, modulo the folds (fold sizes differ by
    at most one; the same split for the same n every time).

    The split of the kernel estimator (`kernel_residual`), which is for samples of the targets'
    own material: they lie among the targets, not beyond them as the colours a k-means fold holds
    out do (`fold_labels`)."""
    if not isinstance(folds, (int, np.integer)) or folds < 2:
        raise ValueError(f"folds: expected an integer >= 2, got {folds!r}")
    k = min(int(folds), n)
    labels = np.random.default_rng(seed).permutation(n) % k
    return labels.astype(np.int64), f"{k} folds of targets drawn at random (seed {seed})"


def fold_weights(reflectances, groups=None, folds: int = DEFAULT_FOLDS) -> np.ndarray:
    """Training weights (F, n) of the F folds of `fold_labels`: 0 where a target is held out."""
    labels, _ = fold_labels(reflectances, groups, folds)
    return _weights_of(labels)


def _weights_of(labels: np.ndarray) -> np.ndarray:
    """(F, n) training weights, one row per distinct fold label: 0 where the target is held out."""
    return (labels[None, :] != np.unique(labels)[:, None]).astype(np.float64)


# ---------------------------------------------------------------------------------------------
# Held-out estimates and their scores


def _held_out(predict, V, R, weights):
    """Held-out estimates (n, 31) of `predict(w) -> (W, r0)` over the folds `weights` (F, n):
    each target estimated by the fit of the fold that held it out (folds partition the targets)."""
    W, r0 = jax.vmap(predict)(weights)  # (F, 31, B), (F, 31)
    estimates = jnp.einsum("fwb,nb->fnw", W, V, precision=_HIGHEST) + r0[:, None, :]
    return jnp.sum((1.0 - weights)[..., None] * estimates, axis=0)


@functools.partial(jax.jit, static_argnames=("offset",))
def _training_cv(V, R, weights, noise_variances, offset: bool = True):
    """Held-out estimates (L, n, 31) of (E2) for each candidate sigma^2 (L,)."""
    return jax.vmap(lambda s2: _held_out(lambda w: _training_fit(V, R, w, s2, offset), V, R, weights))(noise_variances)


@jax.jit
def _sensitivity_cv(V, R, weights, penalty_weights, L):
    """Held-out rms response error (K,) of (E3) for each candidate penalty weight (K,)."""

    def score(penalty_weight):
        def predict(w):
            M, b, _ = _sensitivity_fit(V, R, w, penalty_weight, L)
            return jnp.matmul(R, M.T, precision=_HIGHEST) + b

        predictions = jax.vmap(predict)(weights)  # (F, n, B)
        held_out = (1.0 - weights)[..., None]
        return jnp.sqrt(jnp.sum(held_out * (predictions - V[None]) ** 2) / jnp.sum(held_out) / V.shape[1])

    return jax.vmap(score)(penalty_weights)


@jax.jit
def _model_cv(V, R, weights, penalty_weight, shrinkages, L, sensitivity=None):
    """Held-out estimates (S, n, 31) of (E3-E7) for each candidate shrinkage (S,)."""
    return jax.vmap(
        lambda s: _held_out(lambda w: _model_fit(V, R, w, penalty_weight, s, L, sensitivity), V, R, weights)
    )(shrinkages)


def _choose_sensitivity_penalty(V, R, weights) -> tuple[str, float]:
    """The penalty and weight of (E3) that best predict held-out targets' responses."""
    grid = jnp.asarray(SENSITIVITY_PENALTY_GRID, V.dtype)
    best = None
    for penalty in SENSITIVITY_PENALTIES:
        scores = np.asarray(_sensitivity_cv(V, R, jnp.asarray(weights, V.dtype), grid, _penalty_root(penalty, V.dtype)))
        scores = np.where(np.isfinite(scores), scores, np.inf)
        k = int(np.argmin(scores))
        if best is None or scores[k] < best[0]:
            best = (scores[k], penalty, float(SENSITIVITY_PENALTY_GRID[k]))
    return best[1], best[2]


def _best(estimates, R) -> tuple[int, float]:
    """(index, rms) of the candidate whose held-out estimates (L, n, 31) are nearest R (n, 31)."""
    rms = np.sqrt(np.mean((estimates - np.asarray(R, np.float64)) ** 2, axis=(1, 2)))
    rms = np.where(np.isfinite(rms), rms, np.inf)
    k = int(np.argmin(rms))
    return k, float(rms[k])


@jax.jit
def _mean_delta_e_d65(estimates, R):
    """Mean CIEDE2000 (D65, 2°) between estimated (n, 31) and true (n, 31) reflectances."""
    from ..colorimetry import delta_e_2000, reflectance_to_lab

    return jnp.mean(delta_e_2000(reflectance_to_lab(estimates, "D65"), reflectance_to_lab(R, "D65")))


def _delta_e_d65(estimates, R) -> float:
    # The shortest decimal of the precision it was computed in (a report's JSON states it so).
    return json_ready(np.asarray(_mean_delta_e_d65(jnp.asarray(estimates, R.dtype), R)))


# ---------------------------------------------------------------------------------------------
# Each method at its cross-validated regularisers, and the "auto" choice

# Jitted once for the final fit of each method: run op by op, each LAPACK call and reduction
# would compile on its own (seconds in all, against milliseconds of work).
_training_fit_jit = jax.jit(_training_fit, static_argnames=("offset",))
_model_fit_jit = jax.jit(_model_fit)
# The same over rows of fold weights (`Candidate.fit_folds`).
_training_fit_folds = jax.jit(jax.vmap(_training_fit, in_axes=(None, None, 0, None, None)), static_argnums=(4,))
_model_fit_folds = jax.jit(jax.vmap(_model_fit, in_axes=(None, None, 0, None, None, None, None)))


class Candidate(NamedTuple):
    """One method at its chosen regularisers: `cross_validation` its held-out errors, `fit()`
    its (W (31, B), r0 (31,)) on all the targets (computed only when called), and, for an affine
    method, `fit_folds(weights)` the same fit at the same regularisers on each row of fold
    weights (F, n): (W (F, 31, B), r0 (F, 31)), the folds of an estimator built on it
    (`kernel_residual`)."""

    cross_validation: CrossValidation
    fit: Callable[[], tuple]
    fit_folds: Callable[[jax.Array], tuple[jax.Array, jax.Array]] | None = None


def cross_validate_training(V, R, weights, folds_text: str, *, offset: bool = True, sensitivity=None) -> Candidate:
    """The training form (E2) at the sigma^2 of `RELATIVE_NOISE_GRID` (times the response
    variance) with the least held-out spectral rms; `sensitivity` is not used by this form."""
    V_np = np.asarray(V, np.float64)
    power = np.mean((V_np - V_np.mean(axis=0)) ** 2) if offset else np.mean(V_np**2)
    candidates = (power * np.asarray(RELATIVE_NOISE_GRID)).astype(V.dtype)
    estimates = np.asarray(_training_cv(V, R, jnp.asarray(weights, V.dtype), jnp.asarray(candidates), offset), np.float64)
    k, rms = _best(estimates, R)
    result = CrossValidation(
        method="training", spectral_rms=rms, delta_e_d65=_delta_e_d65(estimates[k], R),
        settings=(("noise_variance", json_ready(candidates[k])), ("offset", bool(offset))), folds=folds_text,
    )
    sigma2 = jnp.asarray(candidates[k])
    return Candidate(
        result, functools.partial(_training_fit_jit, V, R, jnp.ones(V.shape[0], V.dtype), sigma2, offset),
        lambda weights: _training_fit_folds(V, R, weights, sigma2, offset),
    )


def cross_validate_model(V, R, weights, folds_text: str, *, offset: bool = True, sensitivity=None) -> Candidate:
    """The model form (E3-E7) at the penalty of (E3) that best predicts held-out responses and
    the shrinkage of (E5) with the least held-out spectral rms; with a known `sensitivity`
    (B, 31) only the shrinkage is chosen. `offset` is not used by this form (it always has r0)."""
    if sensitivity is None:
        penalty, penalty_weight = _choose_sensitivity_penalty(V, R, weights)
        settings = (("penalty", penalty), ("penalty_weight", penalty_weight))
    else:
        penalty, penalty_weight = "ridge", 1.0  # unused with a known sensitivity
        settings = (("sensitivity", "given"),)
    shrinkages = jnp.asarray(PRIOR_SHRINKAGE_GRID, V.dtype)
    estimates = np.asarray(_model_cv(
        V, R, jnp.asarray(weights, V.dtype), jnp.asarray(penalty_weight, V.dtype), shrinkages,
        _penalty_root(penalty, V.dtype), sensitivity,
    ), np.float64)
    k, rms = _best(estimates, R)
    shrinkage = float(PRIOR_SHRINKAGE_GRID[k])
    result = CrossValidation(
        method="model", spectral_rms=rms, delta_e_d65=_delta_e_d65(estimates[k], R),
        settings=(*settings, ("shrinkage", shrinkage)), folds=folds_text,
    )
    arguments = (jnp.asarray(penalty_weight, V.dtype), jnp.asarray(shrinkage, V.dtype), _penalty_root(penalty, V.dtype), sensitivity)
    return Candidate(
        result, functools.partial(_model_fit_jit, V, R, jnp.ones(V.shape[0], V.dtype), *arguments),
        lambda weights: _model_fit_folds(V, R, weights, *arguments),
    )


def rank_candidates(candidates) -> list[Candidate]:
    """The "auto" choice: candidates by held-out spectral rms, the least first (a stable sort:
    a tie keeps the order they were tried in)."""
    return sorted(candidates, key=lambda candidate: candidate.cross_validation.spectral_rms)


# ---------------------------------------------------------------------------------------------
# The system of the model form, its penalty chosen by cross-validation


def estimate_system(responses, reflectances, *, penalty_weight=None, penalty: str | None = None, groups=None, folds: int = DEFAULT_FOLDS):
    """The system (E3-E4) as the model-based form sees it: (M (B, 31), b (B,), K_n (B,)).

    penalty_weight / penalty None choose them by cross-validated prediction of the held-out
    targets' responses (`_choose_sensitivity_penalty`).
    """
    V, R = _check_training(responses, reflectances)
    _check_determined(V, R, "a sensitivity")
    if penalty_weight is None or penalty is None:
        folds_w = fold_weights(R, groups, folds)
        penalty, penalty_weight = _choose_sensitivity_penalty(V, R, folds_w)
    w = jnp.ones(V.shape[0], V.dtype)
    return _sensitivity_fit(V, R, w, jnp.asarray(penalty_weight, V.dtype), _penalty_root(penalty, V.dtype))


__all__ = [
    "DEFAULT_FOLDS",
    "Candidate",
    "CrossValidation",
    "cross_validate_model",
    "cross_validate_training",
    "estimate_system",
    "fold_labels",
    "fold_weights",
    "random_fold_labels",
    "rank_candidates",
]
