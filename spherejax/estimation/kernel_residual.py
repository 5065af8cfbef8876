"""The residual kernel estimator ("kernel"): an affine estimator plus a Gaussian-process regression
of what it leaves, learnt from targets of the material being measured.

Why. Every other estimator here is affine in the response (E1). Real materials are not: a dyed
family's reflectances lie on a curved set (Kubelka-Munk, `spherejax.kubelka_munk`), and real
targets add fluorescent whitening, surface reflection and texture (`spherejax.target_families`),
none of which an affine map from responses follows. Labs calibrate with targets of the material
they measure (Zou et al. 2019), and there a regression that bends with that set recovers what the
affine map leaves. Built on the affine estimator as its mean, it falls back to that estimator away
from the training responses (its kernel vanishes there).

Model, for a response v (B,):

    u       = S (v - mu)                                     whitened, S (B, B) from the training
                                                             responses' covariance (E9)
    k_j(v)  = exp(-sum_k (u_k - z_jk)^2 / (2 l_k^2))          Gaussian kernel with one lengthscale
                                                             per whitened direction (ARD) on m
                                                             inducing points z_j (E10)
    r(v)    = W v + r0 + A k(v)                               the affine mean (E1) plus the
                                                             residual (E8)

with W, r0 the affine estimator `fit_wiener` chooses (r0 also takes the residuals' mean). The
residuals E = R - (V W^T + r0) of the n targets are taken in their r principal components
(E13: E - mean ~ C P, P (r, 31) the leading right singular vectors, C = (E - mean) P^T), each
component a Gaussian process of its own signal variance s_j^2 and noise sigma_j^2 on the shared
kernel; the lengthscales l, s and sigma maximise the targets' marginal likelihood (E14,
`gp_hyperparameters`, optimistix). The weights are the subset-of-regressors fit of each
component (Rasmussen & Williams 2006, Section 8.3.1; Quinonero-Candela & Rasmussen 2005):

    a_j = (K_mn K_nm + lambda_j K_mm + eps I)^-1 K_mn c_j,   lambda_j = sigma_j^2 / s_j^2     (E11)
    A   = sum_j P_j^T a_j^T   (31, m), of rank r                                            (E12)

K_nm (n, m) the kernel between targets and inducing points, K_mm (m, m) between inducing points,
eps a jitter of 1e-8 x m. With every target an inducing point (m = n), (E11) is the exact
Gaussian-process posterior mean. The inducing points are targets chosen by forward selection
(`inducing_order`: orthogonal least squares, Chen, Cowan & Grant 1991; each next the target whose
kernel column, orthogonal to the chosen ones', explains most of the components C, each in units
of its noise), a nested order, so that every count m is a prefix of it. m and r are chosen by
held-out accuracy (`INDUCING_POINT_COUNTS`, `RANKS`) among those the speed bound admits
(`within_speed_bound`).

Why forward selection and not an unsupervised choice. Pivoted Cholesky of the kernel matrix
(Fine & Scheinberg 2001; the round before this one) spreads the points over every direction the
kernel sees, the camera's noise directions included; the residual of a dyed family changes fast
in a few places. Held out (200 targets, 200 others, ratio to the best affine estimator's rms), m
= 64: Kubelka-Munk cotton / wool / polyester / paper 0.51 / 0.55 / 0.53 / 0.65 by forward
selection against 0.57 / 0.61 / 0.70 / 0.67 by pivoted Cholesky; at m = 96 0.46 / 0.50 / 0.49 /
0.65, where every target an inducing point (m = 200) gives 0.43 / 0.51 / 0.48 / 0.61; at m =
64 the shade-card, fluorescent and gloss families within 0.7 % of every target's and the mixed
one within 2.1 % (`target_families`).

Applying it is two matrix products and an exponential per pixel, B m + r m + r x 34 + B^2
multiply-adds and m exponentials (the fused CPU kernel, spherejax._engine.fused.residual_constants,
with l folded into S and z), against the affine 34 B. Its own uncertainty at a response, the
predictive variance of (E11) (E15), rides with it (`ResidualVariance`).

This module fits it: the whitening (E9), the hyperparameters (E14), the inducing points, the
weights (E11-E12), m and r by cross-validation (`cross_validate_kernel`, over the folds of
`spherejax.estimation.cross_validation`), and the variance (E15). What it fits,
`ResidualKernelEstimator` (the affine `WienerEstimator` and its `KernelResidual`) and
`kernel_features` (E9-E10), live in `spherejax.estimation.estimator` beside the affine estimator,
since applying an estimator needs no fitting; they are re-exported here.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..grid import N_WAVELENGTHS
from .cross_validation import Candidate, _delta_e_d65
from .estimator import (
    CrossValidation,
    KernelResidual,
    ResidualKernelEstimator,
    ResidualVariance,
    kernel_features,
)
from .gp_hyperparameters import fit_hyperparameters

#: The inducing-point counts m the cross-validation chooses among (those up to the number of
#: targets: every target an inducing point where there are fewer than the largest), with the
#: ranks `RANKS`, as far as the speed bound admits them (`within_speed_bound`).
INDUCING_POINT_COUNTS = (16, 32, 48, 64)

#: The speed bound: a kernel calibration's `correct` at most 3x its affine twin's (the kernel
#: contract). The fused CPU kernel applies each inducing point at the multiply-add rate of the core
#: (kernel/fused_correct.h, residual_of: B multiply-adds for its sum, 5 for its exponential and r
#: for the weights; 0.56-0.60 ns a pixel a point at rank 8 on a Zen 4 core against 0.54 for those
#: multiply-adds alone), so no exact kernel applies more points in that time: the bound is on the
#: multiply-adds a pixel (`residual_operations`), at most those of `SPEED_BOUND_POINTS` points at
#: rank `SPEED_BOUND_RANK`, which for 16 bands admits m <= 48 at rank 8 and m <= 64 at rank 4.
#: Through `correct` (2 Zen 4 cores, 1024^2 x 16, `python benchmarks/bench_kernel_contract.py
#: --residuals 64r4,80r8,96r4,128r8`, benchmarks/README.md), against the affine twin on AVX-512 /
#: AVX2 / generic code: 64 points at rank 4 2.61 / 2.79 / 2.58x; beyond the bound, 64 at rank 8
#: 2.88 / 3.01 / 2.76x, 80 at rank 8 3.12 / 3.29 / 3.00x, 128 at rank 8 3.96 / 4.20 / 3.77x (the
#: affine call at 55-59 % of the copy floor: the faster it is, the larger these ratios). What
#: the bound costs, held out (200 targets, 200 others; ratio to the best affine estimator's rms;
#: forward selection, rank 8): Kubelka-Munk cotton / wool / polyester / paper 0.58 / 0.60 / 0.57
#: / 0.69 at m = 48 and 0.51 / 0.55 / 0.53 / 0.65 at m = 64, against 0.43 / 0.51 / 0.48 / 0.61
#: with every target (m = 200); the shade-card, fluorescent and gloss families within 2.2 % of
#: every target's at m = 48, the mixed one within 3.4 %.
SPEED_BOUND_POINTS, SPEED_BOUND_RANK = 64, 4

#: Forward selection (`inducing_order`) considers at most this many targets as inducing points:
#: its working matrix is n x this many float64 (80 MB for 10 000 targets).
SELECTION_CANDIDATES = 1000

#: Multiply-adds of one exponential in the fused kernel (its polynomial of degree 5 and the
#: product with 2^n): part of `residual_operations`.
EXPONENTIAL_MULTIPLY_ADDS = 6

#: The ranks r of the residual (E12-E13) the cross-validation chooses among. The fused CPU kernel
#: applies A at rank 8 or less (spherejax._engine.fused.RESIDUAL_RANK, the same 8): 8 m + 8 x 34
#: multiply-adds a pixel instead of 34 m. Measured with the earlier single-lengthscale fit on the
#: Kubelka-Munk families: rank 4 0.66-0.82, rank 8 0.62-0.80, full rank 0.61-0.80 of the affine
#: estimator's rms; with the per-component noise of (E14) the components beyond 8 are mostly
#: noise (rank 31 at m = 200: 1.50 and 0.63 on cotton and wool, against 0.44 and 0.40 at rank 8).
RANKS = (4, 8)

#: The largest rank (the kernel's).
RESIDUAL_RANK = max(RANKS)

#: Among the counts and ranks within this fraction of the least held-out spectral rms, the
#: cheapest is taken: a point of accuracy that the folds cannot tell from noise is not worth the
#: time per pixel.
CHEAPER_WITHIN = 0.01

#: Eigenvalues of the training responses' covariance below this fraction of the largest are
#: taken as this fraction in the whitening (E9): a direction in which the targets do not vary
#: must not become a unit of distance (the lengthscales of E14 then decide how much it counts).
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


def _kernel(X, Y) -> np.ndarray:
    """exp(-|x_i - y_j|^2 / 2) (n, m), float64, for rows already divided by the lengthscales."""
    squared = np.sum(X * X, axis=1)[:, None] + np.sum(Y * Y, axis=1)[None, :] - 2.0 * X @ Y.T
    return np.exp(-0.5 * np.maximum(squared, 0.0))


def inducing_order(X: np.ndarray, Y: np.ndarray, m: int) -> np.ndarray:
    """The indices (min(m, n),) of the targets X (n, d) (whitened, divided by the lengthscales)
    that forward selection picks first for the targets' values Y (n, r) (each column in units of
    its noise): each next the target whose kernel column k_i = k(X, x_i), made orthogonal to the
    columns chosen before, explains most of Y (the largest |q_i^T Y|^2 / |q_i|^2: orthogonal least
    squares, Chen, Cowan & Grant 1991, IEEE Trans. Neural Networks 2(2)). A nested order; it
    stops early where the remaining columns lie within round-off of the chosen ones' span.
    O(n c m) time and n c memory for c = min(n, `SELECTION_CANDIDATES`) candidates: beyond that
    many targets the candidates are that many of them drawn at random (fixed seed), every target
    still counting in the fit they are chosen by."""
    X = np.asarray(X, np.float64)
    candidates = np.arange(len(X))
    if len(X) > SELECTION_CANDIDATES:
        candidates = np.sort(np.random.default_rng(0).choice(len(X), SELECTION_CANDIDATES, replace=False))
    remaining = _kernel(X, X[candidates])  # column i: k_i, made orthogonal to the chosen columns step by step
    unexplained = np.array(Y, np.float64, copy=True, ndmin=2).reshape(len(X), -1)
    original = np.sum(remaining * remaining, axis=0)
    squared = original.copy()
    order: list[int] = []
    for _ in range(min(int(m), len(candidates))):
        # A column within round-off of the span (its norm a 1e-10 part of what it was) is never
        # taken: its direction is noise.
        usable = squared > 1e-10 * original
        usable[order] = False
        if not usable.any():
            break
        score = np.where(usable, np.sum((remaining.T @ unexplained) ** 2, axis=1) / np.where(usable, squared, 1.0), -1.0)
        i = int(np.argmax(score))
        order.append(i)
        q = remaining[:, i] / np.sqrt(squared[i])
        unexplained -= np.outer(q, q @ unexplained)
        remaining -= np.outer(q, q @ remaining)
        squared = np.sum(remaining * remaining, axis=0)
    return candidates[np.asarray(order, np.int64)]


def residual_operations(bands: int, inducing_points: int, rank: int) -> int:
    """Multiply-adds per pixel of applying a kernel residual, its exponentials counted
    (`residual_multiply_adds` and `EXPONENTIAL_MULTIPLY_ADDS` each): what the fused kernel's time
    follows (`SPEED_BOUND_POINTS`)."""
    return residual_multiply_adds(bands, inducing_points, rank) + EXPONENTIAL_MULTIPLY_ADDS * int(inducing_points)


def within_speed_bound(bands: int, inducing_points: int, rank: int) -> bool:
    """Whether m inducing points at rank r keep `correct` within the speed bound for B bands: at
    most the multiply-adds of `SPEED_BOUND_POINTS` at `SPEED_BOUND_RANK` (`residual_operations`)."""
    return residual_operations(bands, inducing_points, rank) <= residual_operations(
        bands, SPEED_BOUND_POINTS, SPEED_BOUND_RANK)


def _components(E, w, rank):
    """(mean (31,), P (rank, 31), C (n, rank)) of residuals E (n, 31) under 0/1 weights w (n,):
    the weighted mean and leading principal directions (E13)."""
    count = max(w.sum(), 1.0)
    mean = (w[:, None] * E).sum(axis=0) / count
    centred = E - mean
    _, _, Vt = np.linalg.svd(np.sqrt(w)[:, None] * centred, full_matrices=False)
    P = Vt[:rank]
    return mean, P, centred @ P.T


def _component_weights(K_nm, K_mm, C, w, ridges):
    """a (r, m) of (E11) for components C (n, r) of targets with 0/1 weights w (n,), one ridge a
    component."""
    m = K_mm.shape[0]
    Kw = K_nm * w[:, None]
    gram = Kw.T @ K_nm + 1e-8 * m * np.eye(m)
    rhs = Kw.T @ C
    return np.stack([np.linalg.solve(gram + ridge * K_mm, rhs[:, j]) for j, ridge in enumerate(ridges)])


def residual_variance(K_nm, K_mm, P, signal, noise, ridges, beyond) -> ResidualVariance:
    """`ResidualVariance` (E15) of the fit on kernel features K_nm (n, m), K_mm (m, m), components
    P (r, 31) with signal s^2 (r,), noise sigma^2 (r,) and ridges lambda (r,); beyond (31,): the
    per-wavelength variance of the residual beyond rank r. X solves the generalised eigenproblem
    K_mn K_nm x = gamma K_mm x with X^T K_mm X = I (through K_mm's Cholesky factor)."""
    m = K_mm.shape[0]
    L = np.linalg.cholesky(K_mm + 1e-8 * m * np.eye(m))
    Linv_Kmn = np.linalg.solve(L, K_nm.T)
    gamma, Q = np.linalg.eigh(Linv_Kmn @ Linv_Kmn.T)
    gamma = np.maximum(gamma, 0.0)
    X = np.linalg.solve(L.T, Q)
    weights = noise[:, None] / (ridges[:, None] + gamma[None, :])
    per_wavelength_noise = (P * P).T @ noise + beyond
    return ResidualVariance(*(jnp.asarray(x) for x in (P, signal, X, weights, per_wavelength_noise)))


def cross_validate_kernel(V, R, weights, folds_text: str, affine, *, inducing_points: int | None = None):
    """The residual kernel estimator on the affine `Candidate` `affine` (its mean), at the count of
    inducing points and rank with the least held-out spectral rms over the folds `weights` (F, n)
    (the cheapest within `CHEAPER_WITHIN` of it); returns a `cross_validation.Candidate` whose
    `fit()` gives the estimator's arrays (W, r0, mu, S', z', A, variance) on all the targets.

    inducing_points: None (default) chooses m among `INDUCING_POINT_COUNTS` within the speed
    bound (`within_speed_bound`); an integer fixes it (at most the number of targets; every rank
    is then tried, whatever it costs).

    The hyperparameters (E14) are fitted once, on all the targets, and shared by the folds (a fit
    per fold would cost five; they are 16 lengthscales and 2 r variances, which the held-out
    reflectances hardly move); the affine mean, the residual's mean and components and the
    weights are refitted in each fold, so the held-out errors are those of the estimator on
    targets it did not see. The report's settings hold the mean, m, r, the lengthscales (whitened
    units), the ridges, each component's noise variance ("noise", E14, as many as the largest
    rank), every (m, r) tried with its held-out rms, the mean's own held-out spectral
    rms on the same folds ("mean_spectral_rms"), the gain over it and paired z (`kernel_gain`), and
    the multiply-adds per pixel of applying the estimator, affine mean (31 B) and residual
    ("cost_per_pixel"; the m exponentials come on top)."""
    dtype = V.dtype
    V64, R64 = np.asarray(V, np.float64), np.asarray(R, np.float64)
    n, bands = V64.shape
    folds = np.asarray(weights, np.float64)
    held_out = 1.0 - folds
    mu, S = whitening_of(V64)
    U = (V64 - mu) @ S.T

    W, r0 = (np.asarray(x, np.float64) for x in affine.fit())
    E = R64 - (V64 @ W.T + r0)
    rank_max = min(RESIDUAL_RANK, n - 1, 31)
    _, _, C_all = _components(E, np.ones(n), rank_max)
    hyper = fit_hyperparameters(U, C_all)
    ridges = np.asarray(hyper.ridge, np.float64)
    X = U / hyper.lengthscales

    counts = sorted({min(c, n) for c in INDUCING_POINT_COUNTS}) if inducing_points is None else [min(int(inducing_points), n)]
    ranks = sorted({min(r, rank_max) for r in RANKS})
    # The pairs tried: those within the speed bound, or every rank at a count the caller fixed.
    pairs = [(m, r) for m in counts for r in ranks if inducing_points is not None or within_speed_bound(bands, m, r)]
    counts = sorted({m for m, _ in pairs})
    # Forward selection weighs each component in units of its noise (inducing_order).
    noise_units = 1.0 / np.sqrt(np.asarray(hyper.noise, np.float64)[:rank_max])

    W_folds, r0_folds = (np.asarray(x, np.float64) for x in affine.fit_folds(jnp.asarray(folds, dtype)))
    affine_held = np.einsum("fwb,nb->fnw", W_folds, V64) + r0_folds[:, None, :]
    mean_held_out = np.sum(held_out[..., None] * affine_held, axis=0)
    estimates = {pair: np.zeros_like(R64) for pair in pairs}
    for f in range(len(folds)):
        w = folds[f]
        E_f = R64 - affine_held[f]
        mean_f, P_f, C_f = _components(E_f, w, rank_max)
        # The fold's inducing points are its own training targets: a centre at a held-out target
        # has no data near it, and (E11) with a small ridge gives it a large, arbitrary weight
        # there (measured: held-out rms 1.3x the mean's where new samples showed 0.5x).
        training = np.flatnonzero(w > 0)
        fold_order = training[inducing_order(X[training], C_f[training] * noise_units, max(counts))]
        K_fold = _kernel(X, X[fold_order])
        for m in counts:
            K_nm, K_mm = K_fold[:, :m], K_fold[fold_order[:m], :m]
            a = _component_weights(K_nm, K_mm, C_f, w, ridges[:rank_max])
            for r in ranks:
                if (m, r) not in estimates:
                    continue
                estimate = affine_held[f] + mean_f + K_nm @ (P_f[:r].T @ a[:r]).T
                estimates[m, r] += held_out[f][:, None] * estimate
    tried = {key: float(np.sqrt(np.mean((value - R64) ** 2))) for key, value in estimates.items()}
    best = min(tried.values())
    m, r = min((key for key, rms in tried.items() if rms <= best * (1.0 + CHEAPER_WITHIN)),
               key=lambda key: (residual_operations(bands, *key), key[1]))
    gain, z = kernel_gain(mean_held_out, estimates[m, r], R64)
    result = CrossValidation(
        method="kernel", spectral_rms=tried[m, r], delta_e_d65=_delta_e_d65(estimates[m, r], R),
        settings=(("mean", affine.cross_validation.method), ("inducing_points", int(m)), ("rank", int(r)),
                  ("lengthscales", tuple(float(x) for x in hyper.lengthscales)),
                  ("ridges", tuple(float(x) for x in ridges[:r])),
                  ("noise", tuple(float(x) for x in np.asarray(hyper.noise)[:rank_max])),
                  ("hyperparameters_converged", bool(hyper.converged)),
                  ("tried", tuple((int(k[0]), int(k[1]), v) for k, v in sorted(tried.items()))),
                  ("mean_spectral_rms", float(np.sqrt(np.mean((mean_held_out - R64) ** 2)))),
                  ("gain", gain), ("paired_z", z), ("cost_per_pixel", N_WAVELENGTHS * bands + residual_multiply_adds(bands, m, r))),
        folds=folds_text,
    )

    def fit():
        mean, P, C = _components(E, np.ones(n), r)
        order = inducing_order(X, C_all * noise_units, m)
        K_nm, K_mm = _kernel(X, X[order]), _kernel(X[order], X[order])
        a = _component_weights(K_nm, K_mm, C, np.ones(n), ridges[:r])
        A = P.T @ a
        beyond = np.var(E - mean - C @ P, axis=0)
        variance = residual_variance(K_nm, K_mm, P, hyper.signal[:r], hyper.noise[:r], ridges[:r], beyond)
        whitening = S / hyper.lengthscales[:, None]
        as_dtype = lambda x: jnp.asarray(x, dtype)
        return (as_dtype(W), as_dtype(r0 + mean), as_dtype(mu), as_dtype(whitening), as_dtype(X[order]),
                as_dtype(A), variance.astype(dtype))

    return Candidate(result, fit)


def _at_rank(A, rank: int):
    """The best approximation of A (31, m) of rank `rank` or less in the Frobenius norm
    (Eckart-Young): its singular value decomposition cut after `rank` terms. The fit's A has rank
    r by construction (E12); this makes weights of a given rank for files and tests."""
    if min(A.shape) <= rank:
        return A
    U, singular, Vt = jnp.linalg.svd(A, full_matrices=False)
    return jnp.matmul(U[:, :rank] * singular[:rank], Vt[:rank], precision="highest")


def residual_multiply_adds(bands: int, inducing_points: int, rank: int) -> int:
    """Multiply-adds per pixel of applying a kernel residual (E8-E12) beyond the affine estimate:
    the whitening (B^2), the inducing points' dot products (B m), A at rank r (r m + 34 r); the m
    exponentials come on top (about 12 operations each in the fused kernel)."""
    return int(bands * bands + bands * inducing_points + rank * inducing_points + 34 * rank)


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
    "CHEAPER_WITHIN",
    "EXPONENTIAL_MULTIPLY_ADDS",
    "INDUCING_POINT_COUNTS",
    "RANKS",
    "RESIDUAL_RANK",
    "SELECTION_CANDIDATES",
    "SPEED_BOUND_POINTS",
    "SPEED_BOUND_RANK",
    "KernelResidual",
    "ResidualKernelEstimator",
    "ResidualVariance",
    "cross_validate_kernel",
    "inducing_order",
    "kernel_features",
    "kernel_gain",
    "residual_multiply_adds",
    "residual_operations",
    "residual_variance",
    "whitening_of",
    "within_speed_bound",
]
