"""The residual kernel estimator's hyperparameters by marginal likelihood (E13-E14).

Why. The residual of the affine estimator (E8) is a smooth function of the response that a
Gaussian process models: each of its r principal components c_j (E13) a draw with the kernel

    k(u, u') = s_j^2 exp(-sum_k (u_k - u'_k)^2 / (2 l_k^2))                       (E10, ARD)

on the whitened responses u (E9), observed with noise of variance sigma_j^2. The lengthscales l
(one per whitened direction: automatic relevance determination, Rasmussen & Williams 2006,
Section 5.1) tell which directions of the responses the residual depends on. In the directions in
which a material's targets differ mostly by the camera's noise (a 16-band response of one material
varies in a handful of directions), a single lengthscale for all made the kernel's distances
mostly noise; the marginal likelihood sends the lengthscale of such a direction to large values,
which takes it out of the distance. s_j^2 and sigma_j^2 (per component) set how far each
component's fit follows its targets: its ridge (E11) is sigma_j^2 / s_j^2.

The log marginal likelihood of the targets' components C (n, r), for targets of weights w (0 or
1: a cross-validation fold's; a held-out target enters as an independent unit variable with no
data, which adds nothing to the sum), is (Rasmussen & Williams 2006, Eq. 5.8)

    log p = sum_j [ -1/2 c_j^T (s_j^2 K + sigma_j^2 I)^-1 c_j - 1/2 log|s_j^2 K + sigma_j^2 I|
                    - n/2 log 2 pi ]                                                (E14)

maximised here over log l, log s, log sigma with optimistix's BFGS, from l_k = sqrt(d) (about the
targets' spread in whitened units, d = B), s_j^2 = var(c_j), sigma_j^2 = var(c_j) / 10. The
noise is floored at `NOISE_FLOOR` x var(c_j) and the lengthscales kept within
`LENGTHSCALE_BOUNDS`, so that the covariance stays positive definite in float64 and a direction
the targets do not resolve cannot become a unit of distance below the noise.

The fit is the exact one (every target in K); from `MAX_LIKELIHOOD_TARGETS` targets on, it uses
that many of them, drawn at random with a fixed seed (a Cholesky factor of n x n per component
and step: 160 targets take 1-3 s a fit on 2 cores once compiled, 4000 would take hours).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

#: Lengthscales are kept within these bounds (whitened response units: 1 = one standard
#: deviation of the targets along that direction). Below 0.05 a direction's distance is all
#: noise even for region means. Above 4 the kernel of a direction is nearly flat over the
#: family (two targets lie about sqrt(2 B) = 5.7 apart), and samples of another material that
#: differ from the targets mostly in such a direction get the residual as if they were targets:
#: measured on the Kubelka-Munk families (train one, apply to the other three, 12 pairs), the
#: default's rms over the affine estimator's was at most 1.031 with the bound at 4, 1.08-1.10
#: at 8 and 1e3, for 0.51-0.68 against 0.45-0.64 within the family.
LENGTHSCALE_BOUNDS = (0.05, 4.0)

#: Each component's noise variance is at least this fraction of its variance over the targets.
NOISE_FLOOR = 1e-6

#: Each component's signal variance lies within these multiples of its variance over the
#: targets (and its noise between `NOISE_FLOOR` and the upper one): bounds through a smooth map,
#: so that neither can underflow to 0 or overflow (a component of residuals that are all round-off
#: drove an unbounded signal to 0, and its ridge to infinity).
_SIGNAL_BOUNDS = (1e-6, 1e3)

#: The exact marginal likelihood uses at most this many targets (`fit_hyperparameters`): its
#: cost grows as n^3 (a Cholesky factor per component and step), and a few hundred targets of
#: one material pin 16 lengthscales and 2 r variances down (the held-out figures of
#: `kernel_residual.INDUCING_POINT_COUNTS` used 160 of 200).
MAX_LIKELIHOOD_TARGETS = 160

#: Targets are padded (with weight 0) to a multiple of this, so that nearby sizes share a
#: compiled program (compiling one takes several seconds).
_TARGETS_QUANTUM = 32

#: BFGS's steps and tolerance on the scaled objective.
MAX_STEPS = 100
TOLERANCE = 1e-6


@dataclasses.dataclass(frozen=True)
class Hyperparameters:
    """lengthscales (..., d) in whitened response units; signal (..., r) and noise (..., r): s_j^2
    and sigma_j^2 of each residual component, in its units squared; converged (...,) bool."""

    lengthscales: np.ndarray
    signal: np.ndarray
    noise: np.ndarray
    converged: np.ndarray

    @property
    def ridge(self) -> np.ndarray:
        """sigma_j^2 / s_j^2 (..., r): each component's ridge in (E11)."""
        return self.noise / self.signal


def _bounded(raw, low, high):
    """Maps R onto (low, high) in log space: a smooth bound for the unconstrained optimiser."""
    log_low, log_high = np.log(low), np.log(high)
    return jnp.exp(log_low + (log_high - log_low) * jax.nn.sigmoid(raw))


def _unbounded(value, low, high):
    log_low, log_high = np.log(low), np.log(high)
    fraction = (jnp.log(value) - log_low) / (log_high - log_low)
    fraction = jnp.clip(fraction, 1e-6, 1 - 1e-6)
    return jnp.log(fraction) - jnp.log1p(-fraction)


def squared_distances(X, Y):
    """|x_i - y_j|^2 (n, m) for rows X (n, d), Y (m, d), never below 0."""
    cross = jnp.matmul(X, Y.T, precision=jax.lax.Precision.HIGHEST)
    return jnp.maximum(jnp.sum(X * X, axis=1)[:, None] + jnp.sum(Y * Y, axis=1)[None, :] - 2.0 * cross, 0.0)


def _parameters(raw, variance):
    d = raw.shape[0] - 2 * variance.shape[0]
    r = variance.shape[0]
    lengthscales = _bounded(raw[:d], *LENGTHSCALE_BOUNDS)
    signal = variance * _bounded(raw[d:d + r], *_SIGNAL_BOUNDS)
    noise = variance * _bounded(raw[d + r:], NOISE_FLOOR, _SIGNAL_BOUNDS[1])
    return lengthscales, signal, noise


def negative_log_likelihood(raw, args):
    """-(E14) / n for unconstrained parameters raw (d + 2 r,) (`_parameters`), args = (U (n, d),
    C (n, r), w (n,) 0/1, var (r,)): per target, so that the tolerance means the same at any n."""
    U, C, w, variance = args
    lengthscales, signal, noise = _parameters(raw, variance)
    X = U / lengthscales
    K = jnp.exp(-0.5 * squared_distances(X, X)) * (w[:, None] * w[None, :])
    eye = jnp.eye(U.shape[0], dtype=U.dtype)

    def one(c, s2, n2):
        covariance = s2 * K + jnp.diag(w * n2 + (1.0 - w))
        factor = jnp.linalg.cholesky(covariance + 1e-10 * s2 * eye)
        alpha = jax.scipy.linalg.cho_solve((factor, True), c * w)
        return 0.5 * jnp.dot(c * w, alpha) + jnp.sum(jnp.log(jnp.diagonal(factor)))

    # One component after another (lax.map), not vmap: a batch of r Choleskys of n x n is a LAPACK
    # call large enough for jaxlib < 0.12 to share out to XLA's thread pool, which can hang the
    # program with another such call in flight (small_solve); one matrix at a time never does.
    total = jnp.sum(jax.lax.map(lambda args: one(*args), (C.T, signal, noise)))
    return total / jnp.maximum(jnp.sum(w), 1.0)


def _start(U, C, w):
    d, r = U.shape[1], C.shape[1]
    count = jnp.maximum(jnp.sum(w), 1.0)
    mean = jnp.sum(C * w[:, None], axis=0) / count
    variance = jnp.sum(w[:, None] * (C - mean) ** 2, axis=0) / count
    variance = jnp.maximum(variance, jnp.finfo(C.dtype).tiny ** 0.5)
    raw = jnp.concatenate([
        jnp.full((d,), _unbounded(jnp.sqrt(jnp.asarray(d, U.dtype)), *LENGTHSCALE_BOUNDS)),
        jnp.full((r,), _unbounded(jnp.asarray(1.0, U.dtype), *_SIGNAL_BOUNDS)),
        jnp.full((r,), _unbounded(jnp.asarray(0.1, U.dtype), NOISE_FLOOR, _SIGNAL_BOUNDS[1])),
    ])
    return raw, variance


@jax.jit
def _fit(U, C, w):
    raw, variance = _start(U, C, w)
    solution = optx.minimise(
        negative_log_likelihood, optx.BFGS(rtol=TOLERANCE, atol=TOLERANCE), raw, args=(U, C, w, variance),
        max_steps=MAX_STEPS, throw=False,
    )
    lengthscales, signal, noise = _parameters(solution.value, variance)
    return lengthscales, signal, noise, solution.result == optx.RESULTS.successful


def fit_hyperparameters(U, C, weights=None, *, seed: int = 0) -> Hyperparameters:
    """The lengthscales (d,), signal and noise variances (r,) maximising (E14) for whitened
    responses U (n, d) and residual components C (n, r), float64; with `weights` (F, n) of 0/1
    (cross-validation folds), one fit per fold, each on its own targets only (F, d), (F, r).

    From `MAX_LIKELIHOOD_TARGETS` targets on, the fit uses that many, drawn at random (`seed`).
    The targets are padded to a multiple of `_TARGETS_QUANTUM` with held-out rows (weight 0,
    which add nothing to E14), so that sets of nearby sizes share one compiled program.
    """
    U, C = np.asarray(U, np.float64), np.asarray(C, np.float64)
    n = U.shape[0]
    folds = np.ones((1, n)) if weights is None else np.asarray(weights, np.float64)
    if n > MAX_LIKELIHOOD_TARGETS:
        keep = np.sort(np.random.default_rng(seed).choice(n, MAX_LIKELIHOOD_TARGETS, replace=False))
        U, C, folds = U[keep], C[keep], folds[:, keep]
    padding = -len(U) % _TARGETS_QUANTUM
    U, C = np.pad(U, ((0, padding), (0, 0))), np.pad(C, ((0, padding), (0, 0)))
    folds = np.pad(folds, ((0, 0), (0, padding)))
    with jax.enable_x64(True):
        fitted = [_fit(jnp.asarray(U), jnp.asarray(C), jnp.asarray(w)) for w in folds]
        lengthscales, signal, noise, converged = (np.stack([np.asarray(f[i]) for f in fitted]) for i in range(4))
    if weights is None:
        lengthscales, signal, noise, converged = lengthscales[0], signal[0], noise[0], converged[0]
    return Hyperparameters(lengthscales, signal, noise, converged)


__all__ = [
    "LENGTHSCALE_BOUNDS",
    "MAX_LIKELIHOOD_TARGETS",
    "NOISE_FLOOR",
    "Hyperparameters",
    "fit_hyperparameters",
    "negative_log_likelihood",
    "squared_distances",
]
