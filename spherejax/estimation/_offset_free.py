"""The offset-free estimators, outside the default family (`fit_estimator`): no r0, so they
serve as the baseline the affine estimators are measured against.

  wiener_loo_errors             the leave-one-out spectral rms of the offset-free training form
                                W = R^T V (V^T V + n sigma^2 I)^-1 (E2 with r0 = 0) for each
                                candidate sigma^2, exact, without refitting
  select_wiener_noise_variance  the sigma^2 of least leave-one-out error among candidates
  wiener_from_sensitivity       the model-based matrix W = K_r M^T (M K_r M^T + sigma^2 I)^-1 of
                                a known system with no offset, K_r the uncentred R^T R / n or the
                                Markov prior (E6 without b or centring)

`fit_wiener(V, R, select_wiener_noise_variance(V, R)[0], offset=False)` is the offset-free
training estimator at its leave-one-out sigma^2: the baseline rows of benchmarks/bench_wiener.py
and of tests/test_wiener.py. Not among `spherejax.estimation`'s names; `spherejax.wiener_estimation`
re-exports them under these names.
"""

from __future__ import annotations

import jax.numpy as jnp

from .. import _checks
from ..grid import N_WAVELENGTHS
from ._targets import _check_noise_variance, _check_training
from .estimator import _HIGHEST
from .haneishi2000 import markov_correlation
from .regression import RELATIVE_NOISE_GRID


def wiener_loo_errors(responses, reflectances, noise_variances):
    """Leave-one-out rms spectral error of the offset-free training estimator for each sigma^2.

    Args:
      responses: shape (n, B). reflectances: shape (n, 31).
      noise_variances: shape (L,), sigma^2 in response units squared.

    Returns:
      shape (L,): rms over targets and wavelengths of r_i - W_{-i} v_i, where W_{-i} is trained
      without target i. Uses H = V (V^T V + n sigma^2 I)^-1 V^T and e_loo = (R - H R) / (1 - h_ii),
      exact for this estimator, so no refit is needed.
    """
    V, R = _check_training(responses, reflectances)
    lambdas = V.shape[0] * jnp.asarray(noise_variances, dtype=V.dtype)
    U, s, _ = jnp.linalg.svd(V, full_matrices=False)  # U (n, k), s (k,)
    shrink = s**2 / (s**2 + lambdas[:, None])  # (L, k)
    U_t_R = jnp.matmul(U.T, R, precision=_HIGHEST)  # (k, 31)
    fitted = jnp.einsum("nk,lk,kw->lnw", U, shrink, U_t_R, precision=_HIGHEST)
    leverage = jnp.einsum("nk,lk->ln", U**2, shrink)
    loo_residual = (R[None] - fitted) / (1.0 - leverage)[..., None]
    return jnp.sqrt(jnp.mean(loo_residual**2, axis=(1, 2)))


def select_wiener_noise_variance(responses, reflectances, noise_variances=None):
    """sigma^2 minimising the leave-one-out spectral error of the offset-free training form.

    Args:
      responses: shape (n, B). reflectances: shape (n, 31).
      noise_variances: candidates, shape (L,); default `RELATIVE_NOISE_GRID` times trace(K_vv)/B.

    Returns:
      (best sigma^2 (scalar), candidates (L,), leave-one-out rms errors (L,)).
    """
    V, R = _check_training(responses, reflectances)
    if noise_variances is None:
        power = jnp.mean(V**2)  # trace(K_vv) / B
        noise_variances = power * jnp.asarray(RELATIVE_NOISE_GRID, dtype=V.dtype)
    noise_variances = jnp.asarray(noise_variances, dtype=V.dtype)
    if noise_variances.ndim != 1 or noise_variances.shape[0] == 0:
        raise ValueError(
            f"noise_variances: expected a non-empty 1-D array of candidates, got shape "
            f"{tuple(noise_variances.shape)}"
        )
    errors = wiener_loo_errors(V, R, noise_variances)
    errors_finite = jnp.where(jnp.isfinite(errors), errors, jnp.inf)
    return noise_variances[jnp.argmin(errors_finite)], noise_variances, errors


def wiener_from_sensitivity(sensitivity, reflectances=None, noise_variance=0.0):
    """Model-based Wiener matrix W = K_r M^T (M K_r M^T + sigma^2 I)^-1 for a known system with
    no offset and K_r the (uncentred) autocorrelation R^T R / n of example spectra, or the
    Markov prior `markov_correlation()` when `reflectances` is None.

    Returns:
      W, shape (31, B).
    """
    M = _checks.as_array("sensitivity", sensitivity)
    if M.ndim != 2 or M.shape[1] != N_WAVELENGTHS:
        raise ValueError(
            f"sensitivity: expected shape (B, {N_WAVELENGTHS}) (bands, 400..700 nm step 10), "
            f"got {tuple(M.shape)}"
        )
    _check_noise_variance(noise_variance)
    if reflectances is None:
        dtype = _checks.float_dtype(M)
        K_r = markov_correlation(dtype=dtype)
    else:
        R = _checks.as_array("reflectances", reflectances)
        if R.ndim != 2 or R.shape[1] != N_WAVELENGTHS:
            raise ValueError(
                f"reflectances: expected shape (n, {N_WAVELENGTHS}), got {tuple(R.shape)}"
            )
        dtype = _checks.float_dtype(M, R)
        R = R.astype(dtype)
        K_r = jnp.matmul(R.T, R, precision=_HIGHEST) / R.shape[0]
    M = M.astype(dtype)
    K_r_M_t = jnp.matmul(K_r, M.T, precision=_HIGHEST)  # (31, B)
    A = jnp.matmul(M, K_r_M_t, precision=_HIGHEST) + jnp.asarray(noise_variance, dtype) * jnp.eye(
        M.shape[0], dtype=dtype
    )
    return jnp.linalg.solve(A, K_r_M_t.T).T
