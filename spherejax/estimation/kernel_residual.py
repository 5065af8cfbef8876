"""The residual kernel estimator ("kernel"): an affine estimator plus a kernel regression of what it
leaves, learnt from targets of the material being measured.

Why. Every other estimator here is affine in the response (E1). Dyed materials are not: in a family
of one substrate and its dyes, K/S is linear in the dye concentrations and reflectance is not
(Kubelka-Munk, `spherejax.kubelka_munk`), so a family's reflectances lie on a curved set that no
affine map from responses follows, while the responses stay linear in reflectance. Labs calibrate
with targets of the material they measure (Zou et al. 2019: "the color targets and the measured
sample are made of similar materials"), and there a regression that bends with that set recovers
what the affine map leaves. Built on the affine estimator as its mean, it falls back to that
estimator away from the training responses (its kernel vanishes there).

Model, for a response v (B,):

    u       = S (v - mu)                                     whitened, S (B, B) from the training
                                                             responses' covariance (E9)
    k_j(v)  = exp(-|u - z_j|^2 / (2 l^2)),  j = 1..m          Gaussian (RBF) kernel on m inducing
                                                             points z_j (E10)
    r(v)    = W v + r0 + A k(v)                               the affine mean (E1) plus the
                                                             residual (E8)

with W, r0 the affine estimator chosen as `fit_wiener` chooses it, z_j the centres of m k-means
clusters of the whitened training responses (m = min(n, `INDUCING_POINTS`)), and A (31, m) the
subset-of-regressors fit of the residuals E = R - (V W^T + r0) of the n targets (Rasmussen &
Williams 2006, Section 8.3.1; Quiñonero-Candela & Rasmussen 2005):

    A^T = (K_mn D K_nm + lambda K_mm + eps I)^-1 K_mn D E      (E11)

K_nm (n, m) the kernel between targets and inducing points, K_mm (m, m) between inducing points,
D the targets' weights (a cross-validation fold's), lambda the ridge (the noise-to-signal ratio of
a Gaussian-process reading of E11) and eps a jitter of 1e-8 x m for K_mm's round-off, then cut to
its best approximation of rank `RESIDUAL_RANK` (8; Eckart-Young, the singular value decomposition
cut after 8 terms)                                                                       (E12)

so that applying it is 8 multiply-adds per inducing point and 8 x 34 for the outputs. The
lengthscale l and lambda are chosen by the same cross-validation as the affine regularisers
(`KERNEL_LENGTHSCALE_GRID` x `KERNEL_RIDGE_GRID`); stored, l is folded into S and z_j (S / l,
z_j / l), so that applying it is two matrix products and an exponential per pixel:
B m + 8 m + 8 x 34 + B^2 multiply-adds and m exponentials (the fused CPU kernel,
spherejax._engine.fused.residual_constants), against the affine 34 B.

This module fits it: the whitening (E9), the inducing points, the weights (E11-E12) and the
lengthscale and ridge by cross-validation (`cross_validate_kernel`, over the folds of
`spherejax.estimation.cross_validation`). What it fits, `ResidualKernelEstimator` (the affine
`WienerEstimator` and its `KernelResidual`) and `kernel_features` (E9-E10), live in
`spherejax.estimation.estimator` beside the affine estimator, since applying an estimator
(`estimation.wiener`, the pipeline, calibration files) needs no fitting; they are re-exported
here.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .cross_validation import Candidate, _best, _delta_e_d65, _kmeans_labels
from .estimator import _HIGHEST, CrossValidation, KernelResidual, ResidualKernelEstimator, kernel_features

#: Inducing points m of the residual (E10). The per-pixel cost grows with m (3 B m + 31 m
#: multiply-adds), the accuracy with it up to the full regression (m = n). Measured on the four
#: Kubelka-Munk families (`kubelka_munk.km_family_responses`, 200 targets, 200 other recipes held
#: out, spherejax's default k-means folds), held-out spectral rms against the affine estimator's:
#: m = 32 0.83-0.89, m = 64 0.61-0.80, m = 200 (every target) 0.51-0.61 (one-off runs, k-means
#: folds). 64 keeps most of the gain at a third of the full regression's cost per pixel.
INDUCING_POINTS = 64

#: The rank of the residual's weights A (31, m): the fit keeps the best approximation of this rank
#: (E12), so that applying A is 8 m + 8 x 34 multiply-adds a pixel instead of 34 m, which with the
#: fused CPU kernel's lanes over pixels (spherejax._engine.fused.RESIDUAL_RANK, the same 8) keeps a
#: kernel calibration's `correct` within 3x the affine one's (benchmarks/bench_wiener.py). Measured
#: on the Kubelka-Munk families (as for INDUCING_POINTS, one-off runs), held-out spectral rms
#: against the affine estimator's: rank 4 0.66-0.82, rank 8 0.62-0.80, rank 16 0.61-0.80, full
#: rank (31) 0.61-0.80; on the other families the same at every rank (at most 1.02-1.023).
RESIDUAL_RANK = 8

#: Candidate lengthscales l of (E10), in whitened response units (1 = one standard deviation of
#: the training responses along each principal direction). None beyond 4: two targets lie about
#: sqrt(2 B) = 5.7 apart in these units (B = 16), so a lengthscale of 8 or 16 makes the kernel
#: nearly flat over the whole family, a global smooth fit that no longer falls back to the affine
#: mean away from the targets, which is what keeps the estimator from harming other materials.
#: Measured (Kubelka-Munk families, float64, where such fits are well conditioned; float32 mostly
#: refused them as ill-conditioned): cross-validation chose 16 on two families, which then made
#: the other families' spectral rms up to 1.31x the affine estimator's; capped at 4, at most
#: 1.021x, with the same gain within the family to within 0.04 (benchmarks/bench_wiener.py).
KERNEL_LENGTHSCALE_GRID = (0.5, 1.0, 2.0, 4.0)

#: Candidate ridges lambda of (E11), relative to the kernel's unit variance.
KERNEL_RIDGE_GRID = (1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0)

#: Eigenvalues of the training responses' covariance below this fraction of the largest are
#: taken as this fraction in the whitening (E9): a direction in which the targets do not vary
#: must not become a unit of distance.
_WHITENING_FLOOR = 1e-8


# ---------------------------------------------------------------------------------------------
# The fit


def whitening_of(V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mu (B,), S (B, B)) of (E9) from the training responses V (n, B), float64: S = Lambda^-1/2 Q^T
    of the covariance's eigendecomposition, eigenvalues floored at `_WHITENING_FLOOR` x the largest.
    Computed from all the targets, every fold alike: it uses no reflectance."""
    V = np.asarray(V, np.float64)
    mu = V.mean(axis=0)
    covariance = np.atleast_2d(np.cov((V - mu).T, bias=True))
    eigenvalues, Q = np.linalg.eigh(covariance)
    largest = max(float(eigenvalues.max()), np.finfo(np.float64).tiny)
    eigenvalues = np.maximum(eigenvalues, _WHITENING_FLOOR * largest)
    return mu, (Q / np.sqrt(eigenvalues)).T


def inducing_points_of(U: np.ndarray, m: int) -> np.ndarray:
    """m inducing points (m, B) for whitened responses U (n, B): all of them when n <= m, else the
    centres of a deterministic k-means (`cross_validation._kmeans_labels`) of U."""
    U = np.asarray(U, np.float64)
    if len(U) <= m:
        return U.copy()
    labels = _kmeans_labels(U, m)
    return np.stack([U[labels == j].mean(axis=0) for j in np.unique(labels)])


def _residual_weights(K_nm, K_mm, E, w, ridge):
    """A (31, m) of (E11) for residuals E (n, 31) under weights w (n,), at rank `RESIDUAL_RANK`
    or less (E12)."""
    m = K_mm.shape[0]
    Kw = K_nm * w[:, None]
    gram = jnp.matmul(Kw.T, K_nm, precision=_HIGHEST) + ridge * K_mm + 1e-8 * m * jnp.eye(m, dtype=K_mm.dtype)
    rhs = jnp.matmul(Kw.T, E, precision=_HIGHEST)
    return _at_rank(jnp.linalg.solve(gram, rhs).T, RESIDUAL_RANK)


def _at_rank(A, rank: int):
    """The best approximation of A (31, m) of rank `rank` or less in the Frobenius norm
    (Eckart-Young): its singular value decomposition cut after `rank` terms."""
    if min(A.shape) <= rank:
        return A
    U, singular, Vt = jnp.linalg.svd(A, full_matrices=False)
    return jnp.matmul(U[:, :rank] * singular[:rank], Vt[:rank], precision=_HIGHEST)


@jax.jit
def _final_fit(V, R, W, r0, U, Z, ridge):
    """A (31, m) of (E11) on all the targets, whitened responses U and inducing points Z with the
    lengthscale folded in."""
    E = R - (jnp.matmul(V, W.T, precision=_HIGHEST) + r0)
    eye = jnp.eye(U.shape[1], dtype=U.dtype)
    K_nm, K_mm = kernel_features(U, 0.0, eye, Z), kernel_features(Z, 0.0, eye, Z)
    return _residual_weights(K_nm, K_mm, E, jnp.ones(V.shape[0], V.dtype), ridge)


@jax.jit
def _kernel_cv(V, R, U, Z, weights, W, r0, lengthscales, ridges):
    """Held-out estimates (L, K, n, 31) for each lengthscale (L,) and ridge (K,) over the folds
    `weights` (F, n): each target estimated by the fit of the fold that held it out, on the
    affine mean of that fold, W (F, 31, B) and r0 (F, 31); and the mean's own held-out
    estimates (n, 31)."""
    affine = jnp.einsum("fwb,nb->fnw", W, V, precision=_HIGHEST) + r0[:, None, :]  # (F, n, 31)
    residuals = R[None] - affine
    held_out = 1.0 - weights

    def at(lengthscale, ridge):
        K_nm = kernel_features(U / lengthscale, 0.0, jnp.eye(U.shape[1], dtype=U.dtype), Z / lengthscale)
        K_mm = kernel_features(Z / lengthscale, 0.0, jnp.eye(U.shape[1], dtype=U.dtype), Z / lengthscale)
        A = jax.vmap(lambda E, w: _residual_weights(K_nm, K_mm, E, w, ridge))(residuals, weights)  # (F, 31, m)
        estimates = affine + jnp.einsum("fwm,nm->fnw", A, K_nm, precision=_HIGHEST)
        return jnp.sum(held_out[..., None] * estimates, axis=0)

    grid = jax.vmap(lambda l: jax.vmap(lambda k: at(l, k))(ridges))(lengthscales)
    return grid, jnp.sum(held_out[..., None] * affine, axis=0)


def cross_validate_kernel(V, R, weights, folds_text: str, affine, *, inducing_points: int = INDUCING_POINTS):
    """The residual kernel estimator on the affine `Candidate` `affine` (its mean), at the
    lengthscale and ridge of the grids with the least held-out spectral rms over the folds
    `weights` (F, n); returns a `cross_validation.Candidate` whose `fit()` gives the estimator's
    arrays (W, r0, mu, S / l, z / l, A) on all the targets and whose report's settings hold, with
    the mean, lengthscale, ridge and m, the mean's own held-out spectral rms on the same folds
    ("mean_spectral_rms") and the kernel's gain over it and paired z (`kernel_gain`).

    The affine mean is refitted in each fold (`affine.fit_folds`), so the held-out errors are
    those of the whole estimator, and the mean's on the same folds are what the gain is over.
    """
    dtype = V.dtype
    mu, S = whitening_of(V)
    U = (np.asarray(V, np.float64) - mu) @ S.T
    Z = inducing_points_of(U, inducing_points)
    weights = jnp.asarray(weights, dtype)
    W_folds, r0_folds = affine.fit_folds(weights)
    estimates, mean_held_out = (np.asarray(x, np.float64) for x in _kernel_cv(
        V, R, jnp.asarray(U, dtype), jnp.asarray(Z, dtype), weights, W_folds, r0_folds,
        jnp.asarray(KERNEL_LENGTHSCALE_GRID, dtype), jnp.asarray(KERNEL_RIDGE_GRID, dtype),
    ))
    grid = estimates.reshape(-1, *estimates.shape[2:])
    k, rms = _best(grid, R)
    lengthscale = KERNEL_LENGTHSCALE_GRID[k // len(KERNEL_RIDGE_GRID)]
    ridge = KERNEL_RIDGE_GRID[k % len(KERNEL_RIDGE_GRID)]
    gain, z = kernel_gain(mean_held_out, grid[k], R)
    R64 = np.asarray(R, np.float64)
    result = CrossValidation(
        method="kernel", spectral_rms=rms, delta_e_d65=_delta_e_d65(grid[k], R),
        settings=(("mean", affine.cross_validation.method), ("lengthscale", lengthscale), ("ridge", ridge),
                  ("inducing_points", int(len(Z))),
                  ("mean_spectral_rms", float(np.sqrt(np.mean((mean_held_out - R64) ** 2)))),
                  ("gain", gain), ("paired_z", z)),
        folds=folds_text,
    )

    def fit():
        W, r0 = affine.fit()
        U_l, Z_l = jnp.asarray(U / lengthscale, dtype), jnp.asarray(Z / lengthscale, dtype)
        A = _final_fit(V, R, W, r0, U_l, Z_l, jnp.asarray(ridge, dtype))
        return W, r0, jnp.asarray(mu, dtype), jnp.asarray(S / lengthscale, dtype), Z_l, A

    return Candidate(result, fit)


#: `kernel_gain`'s z is kept within +-this (a report's JSON holds no infinity).
_Z_LIMIT = 1e6


def kernel_gain(mean_held_out, kernel_held_out, reflectances) -> tuple[float, float]:
    """(gain, z) of the kernel estimator over its affine mean from their held-out estimates
    (n, 31) of the targets' reflectances (n, 31): gain = 1 - rms_kernel / rms_mean (spectral rms
    over targets and wavelengths), z = the mean of the per-target differences of mean squared
    error (mean - kernel) over its standard error (sample standard deviation / sqrt(n)), within
    +-1e6: 1e6 when every difference is the same positive number, 0 when none differs."""
    R = np.asarray(reflectances, np.float64)
    mean = np.mean((np.asarray(mean_held_out, np.float64) - R) ** 2, axis=1)
    kernel = np.mean((np.asarray(kernel_held_out, np.float64) - R) ** 2, axis=1)
    gain = 1.0 - np.sqrt(kernel.mean() / mean.mean()) if mean.mean() > 0 else 0.0
    difference = mean - kernel
    spread = np.std(difference, ddof=1) / np.sqrt(len(difference)) if len(difference) > 1 else 0.0
    average = difference.mean()
    z = np.clip(average / spread, -_Z_LIMIT, _Z_LIMIT) if spread > 0 else (_Z_LIMIT if average > 0 else 0.0)
    return float(gain), float(z)


__all__ = [
    "INDUCING_POINTS",
    "KERNEL_LENGTHSCALE_GRID",
    "KERNEL_RIDGE_GRID",
    "KernelResidual",
    "RESIDUAL_RANK",
    "ResidualKernelEstimator",
    "cross_validate_kernel",
    "inducing_points_of",
    "kernel_gain",
    "kernel_features",
    "whitening_of",
]
