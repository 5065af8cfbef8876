"""The local estimator ("local"): an affine estimator corrected, for each response, by a ridge
regression of what it leaves on the training targets weighted by their distance to that response.

Why. The affine estimators (E1) fit one map to all the targets; a family of dyed materials has
reflectances on a curved set (Kubelka-Munk, `spherejax.kubelka_munk`), which a single affine map
cannot follow but an affine map fitted to the targets near each response can. The colour
measurement literature does this: Shen, Cai, Shao & Xin (2007), "Reflectance reconstruction for
multispectral imaging by adaptive Wiener estimation", Optics Express 15(23), 15545
(https://opg.optica.org/abstract.cfm?uri=oe-15-23-15545), compute each sample's Wiener
estimate from training samples selected adaptively for it; a locally weighted linear regression with Gaussian weights in CIELAB, tested
on a colour chart and textile samples, is in Optics Express 27(4), 5165 (2019)
(https://www.osapublishing.org/oe/fulltext.cfm?uri=oe-27-4-5165). Here the distance is measured
in the whitened training responses (E9 of `kernel_residual`): no colorimetric conversion of the
query, every direction scaled by the targets' spread along it.

Model, for a response v (B,), training targets (v_i, r_i), i = 1..n (or the k nearest), and an
affine mean m(v) = W v + r0 (the affine estimator "auto" chose; or none, m = 0):

    u       = S (v - mu),  u_i = S (v_i - mu)                 whitened (E9): mu the training
                                                             responses' mean, S = Lambda^-1/2 Q^T
                                                             of their covariance
    w_i     = exp(-|u_i - u|^2 / (2 h^2))                    Gaussian weights, bandwidth h in
                                                             whitened units                (E13)
    e_i     = r_i - m(v_i)                                    what the mean leaves
    (a, b)  = argmin sum_i w_i |e_i - a - b^T (u_i - u)|^2 + lambda (sum_i w_i) |b|^2        (E14)
    r(v)    = m(v) + a

the ridge lambda on the slope only, a variance in whitened units (the sigma^2 of the training
form, E2, per unit weight): scaled by the weights' sum, the fit does not change when every weight
is multiplied by one constant, so they are computed divided by the nearest target's (exp(0) = 1
for it), and no bandwidth underflows them all. Solved in the weights' centred form: with
x_i = u_i - u, xbar = sum w_i x_i / sum w_i and X_c the rows x_i - xbar,

    G = X_c^T diag(w) X_c + lambda (sum w) I  (B x B, symmetric positive definite for lambda > 0)
    z = G^-1 (-xbar)                                                                          (E15)
    r(v) = m(v) + sum_i alpha_i e_i,   alpha_i = w_i (1 / sum w + (x_i - xbar) . z)

the intercept of (E14) without the (B+1) x (B+1) system, whose intercept row couples to the
slope (centring on the weighted means separates them), and without the 31 x B slope: the
correction is a weighted sum of the targets' residuals. With h -> infinity every w_i = 1 and
(E14) is one ridge regression on all the targets; without a mean that is the training form
(`regression`, E2) in whitened units, sigma^2 = lambda. With lambda = 0 the weights'
sum alpha reproduces any affine function of the responses (sum alpha_i (A v_i + c) = A v + c
wherever the weighted targets span the responses), so the mean then changes nothing.

Why the mean: without it, the ridge shrinks the slope that carries the whole signal (reflectance
follows the responses nearly affinely), and where a response lies beyond its neighbours the
slope fitted to a few of them extrapolates wildly. Measured on the Kubelka-Munk families
(`km_family_responses(seed=0, n=200)`, applied to seed=1's 200 targets): without the mean, at
the bandwidth and ridge that cross-validation chose, 2.4x and 14x the affine estimator's
spectral rms on two of the four families, from a few targets (one at 0.17 rms), and any ridge
of 1 or more made all four at least 45x worse than the affine estimator (it shrinks towards the
neighbours' mean reflectance); with the mean, 0.46-1.00 of the affine estimator's over the
whole grid of h in 0.5..8 and lambda in 1e-6..100.

h and lambda are chosen by cross-validation over `LOCAL_BANDWIDTH_GRID` x `LOCAL_RIDGE_GRID`
(`cross_validate_local`, held out over a `cross_validation` fold split, the mean refitted in
each fold). Measured on the same families (200 targets, the affine estimator "auto" takes as
the mean, h and lambda cross-validated over 5 folds drawn at random, float64): 0.48-0.64 of the
affine estimator's spectral rms on seed=1's targets (over k-means folds, 0.57-0.67; in float32
0.49-0.60 and 0.57-0.65); h = 1.41, or 1 on two families with k-means folds, inside the grid;
lambda from the unregularised plateau (1e-7) to 0.1.

Applying it costs, per pixel, a pass over the training targets (`local_multiply_adds_per_pixel`):
about 45,000 multiply-adds with all of 200 targets and 16 bands (83x the affine estimator's
34 B = 544), about 10,000 with the 25 nearest (`neighbours`), which on the same families gave
0.48-0.64 of the affine estimator's spectral rms, as all 200 did.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _checks
from ..grid import N_WAVELENGTHS
from ._targets import _check_training
from .cross_validation import Candidate, _best, _delta_e_d65
from .estimator import _HIGHEST, CrossValidation
from .small_solve import spd_solve

#: Candidate bandwidths h of (E13), in whitened response units (1 = one standard deviation of the
#: training responses along each principal direction; two targets lie about sqrt(2 B) = 5.7 apart,
#: B = 16, and a target's nearest neighbour about 1.1-1.4 in the Kubelka-Munk families). From
#: 0.25, where a target's nearest neighbour alone carries weight, to 64, where every weight is
#: within 1 % of 1 and (E14) is one global ridge regression of the mean's residuals: the grid holds
#: both ends, so cross-validation can choose a global fit where the targets show no curvature.
LOCAL_BANDWIDTH_GRID = tuple(float(2.0 ** (k / 2.0)) for k in range(-4, 13))

#: Candidate ridges lambda of (E14), a variance in whitened units (the training responses'
#: covariance is the identity in them): from 1e-7, unregularised in effect (on the Kubelka-Munk
#: families the held-out rms is the same to three digits from 1e-12 to 1e-4, so an optimum at
#: 1e-7 is that plateau, not a grid too short), to 100, a slope shrunk nearly to zero (the mean
#: plus the neighbours' weighted mean residual).
LOCAL_RIDGE_GRID = tuple(float(10.0 ** (k / 2.0)) for k in range(-14, 5))

#: Eigenvalues of the training responses' covariance below this fraction of the largest are taken
#: as this fraction in the whitening (E9): the floor of `kernel_residual.whitening_of`, so that
#: both estimators measure distance alike. Measured on the Kubelka-Munk families (as in the module
#: docstring): floors of 1e-5 to 1e-2 moved the spectral rms by -0.08 to +0.04 of the affine
#: estimator's, no floor better on all four; a floor of 1 (isotropic distances) made all four
#: worse by 0.15-0.22.
_WHITENING_FLOOR = 1e-8


# ---------------------------------------------------------------------------------------------
# The cost of applying it


def local_multiply_adds_per_pixel(n: int, B: int, neighbours: int | None = None) -> int:
    """Multiply-adds per pixel to apply (E13-E15) with its affine mean, n training targets and B
    bands, k = `neighbours` of them (all n when None); against 34 B for an affine estimator (the
    count `kernel_residual` compares with).

    Counted: the mean W v + r0 31 B; whitening B^2; the squared distances to all n targets n B
    (the k nearest are then selected by comparisons, not counted); the weighted mean xbar k B; the
    symmetric G k B (B + 1) / 2; its Cholesky factorisation B^3 / 6 and two triangular solves
    2 B^2; alpha k (B + 1); the correction 31 k. Plus k exponentials, not counted.
    """
    k = n if neighbours is None else min(int(neighbours), n)
    return int(N_WAVELENGTHS * B + B * B + n * B + k * B + k * B * (B + 1) // 2 + B**3 // 6 + 2 * B * B
               + k * (B + 1) + N_WAVELENGTHS * k)


# ---------------------------------------------------------------------------------------------
# The estimate


def _whitening(V):
    """(mu (B,), S (B, B)) of (E9) from the training responses V (n, B), in V's dtype: S =
    Lambda^-1/2 Q^T of their covariance, eigenvalues floored at `_WHITENING_FLOOR` x the largest
    (as `kernel_residual.whitening_of`, in JAX so that `local_estimate` runs under jit).

    From the singular value decomposition of the centred responses, not the eigendecomposition
    of their covariance: forming the covariance squares the condition number, and in float32 the
    small eigenvalues of a family's responses (about 1e-6 of the largest on the Kubelka-Munk
    families) then come out with errors of tens of per cent. Measured (wool, 80 targets, the
    affine mean, h = 1, lambda = 0.1): held-out estimates in float32 against float64 differed by
    up to 2.8e-4 in reflectance with the covariance's eigendecomposition, 2.5e-6 with the SVD."""
    n, B = V.shape
    mu = jnp.mean(V, axis=0)
    # Fewer targets than bands: the directions they do not span come with the full V^T factor
    # and a singular value of 0 (then floored).
    _, singular, Qt = jnp.linalg.svd(V - mu, full_matrices=n < B)
    eigenvalues = jnp.zeros(B, V.dtype).at[: singular.shape[0]].set(singular**2 / n)
    largest = jnp.maximum(jnp.max(eigenvalues), jnp.finfo(V.dtype).tiny)
    eigenvalues = jnp.maximum(eigenvalues, _WHITENING_FLOOR * largest)
    return mu, Qt / jnp.sqrt(eigenvalues)[:, None]


def _weighted_neighbours(u, U, E, mask, bandwidth, neighbours: int | None):
    """(x (k, B), w (k,), e (k, 31)): the training targets as seen from the whitened query u (B,)
    (x_i = u_i - u), their weights (E13) and their residuals E (n, 31); only targets with mask 1
    (a fold's training set) take part, and of them the k = `neighbours` nearest when given."""
    X = U - u
    d2 = jnp.sum(X * X, axis=1)
    in_fold = mask > 0
    if neighbours is not None:
        _, nearest = jax.lax.top_k(jnp.where(in_fold, -d2, -jnp.inf), neighbours)
        X, d2, E, in_fold = X[nearest], d2[nearest], E[nearest], in_fold[nearest]
    # Divided by the nearest target's weight, which (E14) does not see (its ridge is scaled by the
    # weights' sum): exp(-d^2 / 2h^2) alone underflows to 0 for every target once h is small
    # beside the distances. Without gradient for the same reason: the estimate does not depend
    # on the divisor, only the rounding does.
    d2_min = jax.lax.stop_gradient(jnp.min(jnp.where(in_fold, d2, jnp.inf)))
    # Held-out targets' distances are replaced before exp, not after: the masked branch of a
    # where still carries its gradient, and exp(+inf) there would make it NaN.
    exponent = jnp.where(in_fold, d2 - d2_min, 0.0) / (2.0 * bandwidth * bandwidth)
    w = jnp.where(in_fold, jnp.exp(-exponent), 0.0)
    return X, w, E


def _centred_system(X, w):
    """(sum w, xbar (B,), X_c (k, B), X_c^T diag(w) X_c (B, B)) of (E15)."""
    total = jnp.sum(w)
    xbar = jnp.matmul(w, X, precision=_HIGHEST) / total
    Xc = X - xbar
    return total, xbar, Xc, jnp.matmul((Xc * w[:, None]).T, Xc, precision=_HIGHEST)


def _correction_at_ridge(system, w, E, ridge):
    """sum_i alpha_i e_i (31,) of (E15) at the ridge lambda, from `_centred_system`'s arrays."""
    total, xbar, Xc, gram = system
    G = gram + (ridge * total) * jnp.eye(gram.shape[0], dtype=gram.dtype)
    # Not jax.scipy.linalg.cho_solve: batched LAPACK calls can hang jaxlib < 0.12 (small_solve).
    z = spd_solve(G, -xbar)
    alpha = w * (1.0 / total + jnp.matmul(Xc, z, precision=_HIGHEST))
    return jnp.matmul(alpha, E, precision=_HIGHEST)


def _affine(V, mean):
    """m(V) (n, 31) of the mean (W (31, B), r0 (31,)) (zeros for no mean)."""
    W, r0 = mean
    return jnp.matmul(V, W.T, precision=_HIGHEST) + r0


def local_estimate(v, V, R, *, bandwidth, ridge, neighbours: int | None = None, whitening=None, mean=None):
    """Reflectance (..., 31) of responses v (..., B) by the local regression (E13-E15) on the
    training targets V (n, B), R (n, 31). Jittable and differentiable in v.

    Args:
      v: responses, shape (..., B), in the units of V.
      V, R: the training targets' responses (n, B) and reflectances (n, 31), 400..700 nm.
      bandwidth: h > 0 of (E13), whitened units; jnp.inf weighs every target alike.
      ridge: lambda >= 0 of (E14). 0 needs B + 1 targets of non-negligible weight that span the
        responses (else G is singular and the estimate NaN).
      neighbours: k, only the k nearest targets take part (1 <= k <= n, static); None: all.
      whitening: (mu (B,), S (B, B)) of (E9); None computes them from V (`_whitening`). The
        estimate depends on S only through distances and |b|, which an orthogonal change of S
        leaves alone: eigenvector signs do not matter.
      mean: (W (31, B), r0 (31,)), the affine estimator the regression corrects; None for none
        (a plain local linear regression, whose ridge then shrinks towards a flat estimate; see
        the module docstring for why a mean should be given).

    Returns:
      reflectance (..., 31) in the dtype of v, V and R (float32 unless one is float64). float32
      agrees with float64 to about 1e-6 where the local problem is well conditioned; at a narrow
      bandwidth and a small ridge, a response far from its neighbours is an extrapolation whose
      weights alpha cancel, and float32 resolves it to about 1e-3 only (tests/test_local_regression.py).
    """
    V, R = _check_training(V, R)
    v = _checks.band_array("v", v)
    _checks.require_last_axis("v", v, V.shape[1], f"the bands of the training responses, B = {V.shape[1]}")
    dtype = _checks.float_dtype(v, V, R)
    v, V, R = v.astype(dtype), V.astype(dtype), R.astype(dtype)
    if neighbours is not None:
        if isinstance(neighbours, bool) or not isinstance(neighbours, (int, np.integer)) or not 1 <= neighbours <= V.shape[0]:
            raise ValueError(f"neighbours: expected an integer in 1..{V.shape[0]} (the targets) or None, got {neighbours!r}")
        neighbours = int(neighbours)
    if _checks.is_concrete(bandwidth) and not float(bandwidth) > 0:
        raise ValueError(f"bandwidth: expected a value > 0 (whitened response units), got {bandwidth!r}")
    if _checks.is_concrete(ridge) and not float(ridge) >= 0:
        raise ValueError(f"ridge: expected a value >= 0, got {ridge!r}")
    if mean is None:
        W, r0 = jnp.zeros((R.shape[1], V.shape[1]), dtype), jnp.zeros(R.shape[1], dtype)
    else:
        W, r0 = (_checks.as_array(name, x).astype(dtype) for name, x in zip(("mean W", "mean r0"), mean))
        _checks.require_shape("mean W", W, (R.shape[1], V.shape[1]), "31 wavelengths x the bands")
        _checks.require_shape("mean r0", r0, (R.shape[1],), "one offset per wavelength")
    mu, S = _whitening_jit(V) if whitening is None else (jnp.asarray(x, dtype) for x in whitening)
    estimates = _estimate(v.reshape(-1, V.shape[1]), V, R, W, r0, mu, S, jnp.asarray(bandwidth, dtype),
                          jnp.asarray(ridge, dtype), neighbours)
    return estimates.reshape(*v.shape[:-1], R.shape[1])


# Jitted: run op by op, each of the vmapped solve's pieces would compile on its own (seconds).
_whitening_jit = jax.jit(_whitening)


@functools.partial(jax.jit, static_argnames=("neighbours",))
def _estimate(queries, V, R, W, r0, mu, S, bandwidth, ridge, neighbours: int | None):
    """(E13-E15) for queries (m, B) on the checked targets, mean W (31, B), r0 (31,)."""
    mean = (W, r0)
    U = jnp.matmul(V - mu, S.T, precision=_HIGHEST)
    E = R - _affine(V, mean)
    u = jnp.matmul(queries - mu, S.T, precision=_HIGHEST)
    mask = jnp.ones(V.shape[0], V.dtype)

    def one(u_q):
        X, w, E_k = _weighted_neighbours(u_q, U, E, mask, bandwidth, neighbours)
        return _correction_at_ridge(_centred_system(X, w), w, E_k, ridge)

    return _affine(queries, mean) + jax.vmap(one)(u)


class LocalFit(NamedTuple):
    """What applying the local estimator needs, in the units of the responses it was fitted on:
    the training responses V (n, B) and reflectances R (n, 31), the whitening mu (B,), S (B, B),
    the bandwidth h and ridge lambda, the neighbours k (None: all) and the affine mean (W (31, B),
    r0 (31,)) or None. `estimate(v)` applies it (`local_estimate`). Fitted on V / scale, it is
    applied to v / scale (or with V, mu times scale, S / scale and W / scale)."""

    responses: jax.Array
    reflectances: jax.Array
    mu: jax.Array
    S: jax.Array
    bandwidth: float
    ridge: float
    neighbours: int | None = None
    mean: tuple[jax.Array, jax.Array] | None = None

    def estimate(self, v):
        """Reflectance (..., 31) of responses v (..., B)."""
        return local_estimate(v, self.responses, self.reflectances, bandwidth=self.bandwidth, ridge=self.ridge,
                              neighbours=self.neighbours, whitening=(self.mu, self.S), mean=self.mean)


# ---------------------------------------------------------------------------------------------
# Cross-validation


@functools.partial(jax.jit, static_argnames=("neighbours",))
def _local_cv(V, R, masks, folds, W, r0, bandwidths, ridges, neighbours: int | None = None):
    """Estimates (H, L, n, 31) of every target i from the training targets `masks[i]` (n, n) of
    the fold `folds[i]` that holds it out, on that fold's mean W (F, 31, B), r0 (F, 31), for each
    bandwidth (H,) and ridge (L,). The distances, weights and G of each target and bandwidth are
    shared by the ridges."""
    mu, S = _whitening(V)
    U = jnp.matmul(V - mu, S.T, precision=_HIGHEST)
    fitted = jnp.einsum("fwb,nb->fnw", W, V, precision=_HIGHEST) + r0[:, None, :]  # (F, n, 31)
    residuals = R[None] - fitted

    def target(arguments):
        u, mask, fold, own = arguments

        def at_bandwidth(h):
            X, w, E_k = _weighted_neighbours(u, U, residuals[fold], mask, h, neighbours)
            system = _centred_system(X, w)
            return jax.vmap(lambda lam: own + _correction_at_ridge(system, w, E_k, lam))(ridges)

        return jax.vmap(at_bandwidth)(bandwidths)

    own = fitted[folds, jnp.arange(V.shape[0])]  # each target's mean estimate, by its fold's mean
    # Batches of targets: all n at once would hold H n^2 B distances (for n = 1000, 2 GB).
    estimates = jax.lax.map(target, (U, masks, folds, own), batch_size=64)  # (n, H, L, 31)
    return jnp.moveaxis(estimates, 0, 2), own


def held_out_local_estimates(V, R, weights, *, mean=None, bandwidths=LOCAL_BANDWIDTH_GRID, ridges=LOCAL_RIDGE_GRID,
                             neighbours: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Held-out estimates (H, L, n, 31), float64, of the targets V (n, B), R (n, 31) over the fold
    weights (F, n) (1: in the fold's training set, 0: held out; every target held out by exactly
    one fold, as `cross_validation.fold_weights` and `random_fold_labels` make them) for each
    bandwidth (H,) and ridge (L,), and the mean's own held-out estimates (n, 31): each target
    estimated from the training targets of the fold that held it out and nothing else (its own
    reflectance and those of the targets held out with it get weight 0), on the mean refitted in
    that fold (`mean.fit_folds`, an affine `cross_validation.Candidate`; None: no mean, zeros).
    The whitening is the same in every fold: it uses all the responses and no reflectance, as
    the kernel estimator's does."""
    V, R = _check_training(V, R)
    weights = np.asarray(weights, np.float64)
    if weights.ndim != 2 or weights.shape[1] != V.shape[0]:
        raise ValueError(f"weights: expected shape (F, {V.shape[0]}) (folds, targets), got {weights.shape}")
    held_out = 1.0 - weights
    if not (np.all((weights == 0) | (weights == 1)) and np.all(held_out.sum(axis=0) == 1)):
        raise ValueError("weights: expected 0/1 fold weights holding out every target in exactly one fold")
    folds = np.argmax(held_out, axis=0)
    masks = weights[folds]  # row i: the training set of i's fold
    smallest = int(masks.sum(axis=1).min())
    if neighbours is not None and (isinstance(neighbours, bool) or not 1 <= int(neighbours) <= smallest):
        raise ValueError(f"neighbours: expected an integer in 1..{smallest} (a fold's training targets), got {neighbours!r}")
    dtype = V.dtype
    fold_weights = jnp.asarray(weights, dtype)
    if mean is None:
        W = jnp.zeros((weights.shape[0], R.shape[1], V.shape[1]), dtype)
        r0 = jnp.zeros((weights.shape[0], R.shape[1]), dtype)
    else:
        W, r0 = (jnp.asarray(x, dtype) for x in mean.fit_folds(fold_weights))
    estimates, own = _local_cv(V, R, jnp.asarray(masks, dtype), jnp.asarray(folds), W, r0, jnp.asarray(bandwidths, dtype),
                               jnp.asarray(ridges, dtype), None if neighbours is None else int(neighbours))
    return np.asarray(estimates, np.float64), np.asarray(own, np.float64)


def cross_validate_local(V, R, weights, folds_text: str, *, mean=None, bandwidths=LOCAL_BANDWIDTH_GRID,
                         ridges=LOCAL_RIDGE_GRID, neighbours: int | None = None) -> Candidate:
    """The local estimator (E13-E15) on the affine `Candidate` `mean` (None: no mean) at the
    bandwidth and ridge of the grids with the least held-out spectral rms over the folds `weights`
    (F, n) (`held_out_local_estimates`).

    Returns a `cross_validation.Candidate`. Its report (method "local") holds the spectral rms and
    mean ΔE00 (D65) of the held-out estimates at the chosen point and the settings: "mean" (the
    mean's method or "none"), "bandwidth", "ridge", "neighbours" (k, or n for all),
    "cost_per_pixel" (`local_multiply_adds_per_pixel`), "mean_spectral_rms" (the mean's own
    held-out spectral rms on the same folds, what the local correction gains over), and where the
    choice lies in each grid ("bandwidth_index" of "bandwidths", "ridge_index" of "ridges",
    0-based: an index at either end says the grid may not hold the optimum). Its `fit()` gives
    the `LocalFit` on all the targets, the mean's `fit()` with it.
    """
    V, R = _check_training(V, R)
    estimates, own = held_out_local_estimates(V, R, weights, mean=mean, bandwidths=bandwidths, ridges=ridges,
                                              neighbours=neighbours)
    H, L = estimates.shape[:2]
    k, rms = _best(estimates.reshape(H * L, *estimates.shape[2:]), R)
    i, j = divmod(k, L)
    bandwidth, ridge = float(bandwidths[i]), float(ridges[j])
    n, B = V.shape
    R64 = np.asarray(R, np.float64)
    result = CrossValidation(
        method="local", spectral_rms=rms, delta_e_d65=_delta_e_d65(estimates[i, j], R),
        settings=(("mean", "none" if mean is None else mean.cross_validation.method), ("bandwidth", bandwidth),
                  ("ridge", ridge), ("neighbours", n if neighbours is None else int(neighbours)),
                  ("cost_per_pixel", local_multiply_adds_per_pixel(n, B, neighbours)),
                  ("mean_spectral_rms", float(np.sqrt(np.mean((own - R64) ** 2)))),
                  ("bandwidth_index", i), ("bandwidths", H), ("ridge_index", j), ("ridges", L)),
        folds=folds_text,
    )

    def fit() -> LocalFit:
        mu, S = _whitening(V)
        fitted_mean = None if mean is None else tuple(jnp.asarray(x, V.dtype) for x in mean.fit())
        return LocalFit(V, R, mu, S, bandwidth, ridge, None if neighbours is None else int(neighbours), fitted_mean)

    return Candidate(result, fit)


__all__ = [
    "LOCAL_BANDWIDTH_GRID",
    "LOCAL_RIDGE_GRID",
    "LocalFit",
    "cross_validate_local",
    "held_out_local_estimates",
    "local_estimate",
    "local_multiply_adds_per_pixel",
]
