"""The model-based estimator ("model"): Wiener estimation through a model of the system
(Haneishi et al. 2000), the system estimated from the targets (Shen & Xin 2006).

First estimate the system,

    v = M r + b + n,   M (B, 31) the spectral sensitivity, b (B,) an offset             (E3)

by least squares on the targets with a Tikhonov penalty on M (ridge, or second differences along
wavelength), then the noise covariance from the residuals of that fit (per band),

    K_n = diag( sum_i e_i^2 / (n - df) ),  e_i = v_i - M r_i - b,  df = tr(hat)         (E4)

and the reflectance statistics from the targets, shrunk towards a first-order Markov smoothness
prior K_p[i, j] = tau rho^|i - j| of the same total variance tau = tr(cov(r)) / 31,

    K_r = (1 - s) cov(r) + s K_p                                                       (E5)

and finally the linear minimum mean-square-error estimator of r given v,

    W  = K_r M^T (M K_r M^T + K_n)^-1                                                  (E6)
    r0 = r_mean - W (M r_mean + b)                                                     (E7)

Where the sensitivity is known (the simulator, or a measured one) it is taken instead of (E3).
The penalty and its weight on M and the shrinkage s are chosen by
`spherejax.estimation.cross_validation` (which also holds `estimate_system`, the system (E3-E4)
with its penalty chosen so).

References:
  Haneishi, Hasegawa, Hosoi, Yokoyama, Tsumura, Miyake, "System design for accurately estimating
  the spectral reflectance of art paintings", Appl. Opt. 39(35), 6621-6632 (2000),
  doi:10.1364/AO.39.006621.
  Shen, Xin, "Spectral characterization of a color scanner based on optimized adaptive
  estimation", J. Opt. Soc. Am. A 23(7), 1566-1569 (2006), doi:10.1364/JOSAA.23.001566.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .. import _checks
from ..grid import N_WAVELENGTHS
from ._targets import _check_sensitivity, _check_training, _weighted_centre
from .estimator import _HIGHEST, WienerEstimator

#: Correlation between neighbouring 10 nm samples of the Markov smoothness prior (E5); natural
#: reflectances are smooth on that scale.
MARKOV_PRIOR_CORRELATION = 0.99

#: Candidate weights of the penalty on M in (E3), relative to tr(R_c^T R_c) / tr(P).
SENSITIVITY_PENALTY_GRID = tuple(10.0 ** (k / 2.0) for k in range(-14, 1))

#: The penalties on M tried in (E3): "ridge" (towards zero: a soft rank limit) and "smooth"
#: (second differences along wavelength).
SENSITIVITY_PENALTIES = ("ridge", "smooth")

#: Candidate shrinkages s of K_r towards the smoothness prior (E5).
PRIOR_SHRINKAGE_GRID = (0.0, 0.001, 0.003, 0.01, 0.03, 0.1, 0.3)


def markov_correlation(n: int = N_WAVELENGTHS, rho: float = MARKOV_PRIOR_CORRELATION, dtype=jnp.float32):
    """First-order Markov autocorrelation K[i, j] = rho^|i - j|, shape (n, n)."""
    i = jnp.arange(n)
    return jnp.asarray(rho, dtype=dtype) ** jnp.abs(i[:, None] - i[None, :]).astype(dtype)


def _penalty_root(penalty: str, dtype):
    """L (60, 31) with P = L^T L the penalty of (E3): the identity ("ridge") or second
    differences along wavelength ("smooth"; plus a 1e-3 ridge so that P has no null space).
    Both have one shape (ridge padded with zero rows) so that one compiled program serves both."""
    eye = np.eye(N_WAVELENGTHS)
    if penalty == "ridge":
        root = np.concatenate([eye, np.zeros((N_WAVELENGTHS - 2, N_WAVELENGTHS))])
    elif penalty == "smooth":
        root = np.concatenate([eye[:-2] - 2.0 * eye[1:-1] + eye[2:], 1e-3 * eye])
    else:
        raise ValueError(f"penalty: expected one of {SENSITIVITY_PENALTIES}, got {penalty!r}")
    return jnp.asarray(root, dtype)


def _sensitivity_fit(V, R, w, penalty_weight, L):
    """(M (B, 31), b (B,), per-band noise variance K_n (B,)) of (E3-E4) from weighted targets.

    Solves min ||V_c - R_c M^T||^2 + lam ||L M^T||^2 as one stacked least-squares problem by QR
    ([R_c; sqrt(lam) L] is far better conditioned than R_c^T R_c + lam P), with
    lam = penalty_weight tr(R_c^T R_c) / tr(L^T L) so that the grid is scale-free.
    """
    v_mean, Vc = _weighted_centre(V, w)
    r_mean, Rc = _weighted_centre(R, w)
    lam = penalty_weight * jnp.sum(Rc**2) / jnp.sum(L**2)
    A = jnp.concatenate([Rc, jnp.sqrt(lam) * L])  # (n + k, 31)
    Q, upper = jnp.linalg.qr(A)  # Q (n + k, 31), upper (31, 31)
    n = Rc.shape[0]
    M_t = jax.scipy.linalg.solve_triangular(upper, jnp.matmul(Q[:n].T, Vc, precision=_HIGHEST), lower=False)
    residual = Vc - jnp.matmul(Rc, M_t, precision=_HIGHEST)
    degrees_of_freedom = jnp.sum(Q[:n] ** 2)  # tr of the hat matrix R_c (A^T A)^-1 R_c^T
    # One more for the offset b, estimated through the means.
    dof_left = jnp.maximum(jnp.sum(w) - degrees_of_freedom - 1.0, 1.0)
    noise = jnp.sum(residual**2, axis=0) / dof_left
    M = M_t.T
    return M, v_mean - jnp.matmul(M, r_mean, precision=_HIGHEST), noise


def wiener_from_system(sensitivity, offset, noise_variance, reflectance_mean, reflectance_covariance) -> WienerEstimator:
    """The model-based estimator (E6-E7) from a system and reflectance statistics.

    Args:
      sensitivity: M (B, 31), in the units of the responses the estimator will be applied to.
      offset: b (B,).
      noise_variance: K_n: (B,) per band, or a full (B, B) covariance.
      reflectance_mean: r_mean (31,). reflectance_covariance: K_r (31, 31).

    Returns:
      WienerEstimator with W = K_r M^T (M K_r M^T + K_n)^-1 and r0 = r_mean - W (M r_mean + b).
    """
    M = _checks.as_array("sensitivity", sensitivity)
    b = _checks.as_array("offset", offset)
    K_n = _checks.as_array("noise_variance", noise_variance)
    r_mean = _checks.as_array("reflectance_mean", reflectance_mean)
    K_r = _checks.as_array("reflectance_covariance", reflectance_covariance)
    if M.ndim != 2 or M.shape[1] != N_WAVELENGTHS:
        raise ValueError(f"sensitivity: expected shape (B, {N_WAVELENGTHS}) (bands, 400..700 nm step 10), got {tuple(M.shape)}")
    bands = M.shape[0]
    _checks.require_shape("offset", b, (bands,), "one offset per band of the sensitivity")
    if K_n.shape not in ((bands,), (bands, bands)):
        raise ValueError(f"noise_variance: expected shape ({bands},) or ({bands}, {bands}), got {tuple(K_n.shape)}")
    _checks.require_shape("reflectance_mean", r_mean, (N_WAVELENGTHS,), "one value per wavelength")
    _checks.require_shape("reflectance_covariance", K_r, (N_WAVELENGTHS, N_WAVELENGTHS), "31 x 31")
    dtype = _checks.float_dtype(M, b, K_n, r_mean, K_r)
    M, b, K_n, r_mean, K_r = (x.astype(dtype) for x in (M, b, K_n, r_mean, K_r))
    W, r0 = _system_wiener(M, b, K_n if K_n.ndim == 2 else jnp.diag(K_n), r_mean, K_r)
    return WienerEstimator(W, r0, method="model")


def _system_wiener(M, b, K_n, r_mean, K_r):
    """(W, r0) of (E6-E7); K_n (B, B)."""
    K_r_M_t = jnp.matmul(K_r, M.T, precision=_HIGHEST)  # (31, B)
    K_vv = jnp.matmul(M, K_r_M_t, precision=_HIGHEST) + K_n  # (B, B), M K_r M^T + K_n
    W = _symmetric_solve(K_vv, K_r_M_t.T).T
    return W, r_mean - jnp.matmul(W, jnp.matmul(M, r_mean, precision=_HIGHEST) + b, precision=_HIGHEST)


def _symmetric_solve(A, B):
    """A^-1 B for a symmetric positive (semi-)definite A (k, k), through its eigendecomposition
    so that a (numerically) singular direction gets a zero weight instead of a blow-up."""
    eigenvalues, Q = jnp.linalg.eigh(A)
    floor = jnp.max(eigenvalues) * jnp.finfo(A.dtype).eps * A.shape[0]
    inverse = jnp.where(eigenvalues > floor, 1.0 / jnp.where(eigenvalues > floor, eigenvalues, 1.0), 0.0)
    return jnp.matmul(Q * inverse, jnp.matmul(Q.T, B, precision=_HIGHEST), precision=_HIGHEST)


def _prior_covariance(Rc, w, shrinkage):
    """(E5): K_r = (1 - s) cov(r) + s tau rho^|i-j|, tau = tr(cov(r)) / 31."""
    covariance = jnp.matmul(Rc.T, Rc, precision=_HIGHEST) / jnp.sum(w)
    tau = jnp.trace(covariance) / N_WAVELENGTHS
    return (1.0 - shrinkage) * covariance + shrinkage * tau * markov_correlation(dtype=Rc.dtype)


def _model_fit(V, R, w, penalty_weight, shrinkage, L, sensitivity=None):
    """(W, r0) of (E3-E7) from weighted targets, L the penalty root (`_penalty_root`);
    `sensitivity` (B, 31) replaces (E3) if given."""
    r_mean, Rc = _weighted_centre(R, w)
    if sensitivity is None:
        M, b, noise = _sensitivity_fit(V, R, w, penalty_weight, L)
    else:
        M = sensitivity
        v_mean, Vc = _weighted_centre(V, w)
        b = v_mean - jnp.matmul(M, r_mean, precision=_HIGHEST)
        residual = Vc - jnp.matmul(Rc, M.T, precision=_HIGHEST)
        noise = jnp.sum(residual**2, axis=0) / jnp.maximum(jnp.sum(w) - 1.0, 1.0)
    # A band whose residual vanishes (exact data) still needs K_vv invertible; the floor is far
    # below any camera's noise (1e-6 of the response variance).
    floor = 1e-6 * jnp.mean(jnp.matmul(M, jnp.matmul(Rc.T, Rc, precision=_HIGHEST), precision=_HIGHEST) * M) + jnp.finfo(V.dtype).tiny
    K_n = jnp.diag(jnp.maximum(noise, floor))
    return _system_wiener(M, b, K_n, r_mean, _prior_covariance(Rc, w, shrinkage))


def model_estimator(
    responses, reflectances, *, penalty_weight=1e-4, shrinkage=0.0, penalty: str = "ridge", sensitivity=None
) -> WienerEstimator:
    """The model-based estimator (E3-E7) with given regularisers (jit- and grad-friendly).

    Args:
      responses: (n, B). reflectances: (n, 31).
      penalty_weight: weight of the penalty on M in (E3), relative (`SENSITIVITY_PENALTY_GRID`).
      shrinkage: s of (E5), in [0, 1].
      penalty: "ridge" or "smooth" (`SENSITIVITY_PENALTIES`).
      sensitivity: a known M (B, 31) to use instead of estimating it; b and K_n then come from
        the targets' residuals.
    """
    V, R = _check_training(responses, reflectances)
    if penalty not in SENSITIVITY_PENALTIES:
        raise ValueError(f"penalty: expected one of {SENSITIVITY_PENALTIES}, got {penalty!r}")
    if _checks.is_concrete(shrinkage) and not 0.0 <= float(shrinkage) <= 1.0:
        raise ValueError(f"shrinkage: expected a value in [0, 1], got {shrinkage!r}")
    if _checks.is_concrete(penalty_weight) and not float(penalty_weight) > 0.0:
        raise ValueError(f"penalty_weight: expected a value > 0, got {penalty_weight!r}")
    M = None if sensitivity is None else _check_sensitivity(sensitivity, V)
    w = jnp.ones(V.shape[0], V.dtype)
    L = _penalty_root(penalty, V.dtype)
    W, r0 = _model_fit(V, R, w, jnp.asarray(penalty_weight, V.dtype), jnp.asarray(shrinkage, V.dtype), L, M)
    return WienerEstimator(W, r0, method="model")


__all__ = [
    "MARKOV_PRIOR_CORRELATION",
    "PRIOR_SHRINKAGE_GRID",
    "SENSITIVITY_PENALTIES",
    "SENSITIVITY_PENALTY_GRID",
    "markov_correlation",
    "model_estimator",
    "wiener_from_system",
]
