"""Wiener estimation of 31-sample reflectance from 16-band camera responses.

Zou et al. (2019) reconstruct reflectance with a 31 x 16 matrix computed from 144 colour targets
of known reflectance by Wiener estimation (Section 2 and their ref. [21]). Two forms:

Training-based (no knowledge of the system):
    W = K_rv (K_vv + sigma^2 I)^-1,  K_rv = R^T V / n,  K_vv = V^T V / n
with V (n, B) the corrected responses of the targets and R (n, 31) their reflectances. sigma^2 is
the variance of the noise assumed on the responses; it is the estimator's regulariser: 0 gives the
least-squares fit of the training set, which chases measurement noise and extrapolates badly to
materials outside it. `fit_wiener` chooses sigma^2 from the data by leave-one-out cross-validation
(exact and cheap for this linear estimator: the ridge identity e_loo = e / (1 - h_ii) on an SVD of
V), so that the matrix is tuned for targets it has not seen.

Model-based (the system's spectral sensitivity M (B, 31) is known, v = M r + n):
    W = K_r M^T (M K_r M^T + sigma^2 I)^-1
with K_r the reflectance autocorrelation, estimated from example spectra or taken from a
first-order Markov smoothness prior.

Apply with `wiener(v, W)`: reflectance = v @ W^T, shape (..., 31).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from . import _checks
from .grid import N_WAVELENGTHS

_HIGHEST = jax.lax.Precision.HIGHEST

#: Candidate noise variances for cross-validation, relative to the mean response power
#: trace(K_vv) / B: from effectively unregularised to a very smooth estimate.
RELATIVE_NOISE_GRID = tuple(10.0 ** (k / 4.0) for k in range(-40, 1))

#: Correlation between neighbouring 10 nm samples in the default Markov prior of
#: `wiener_from_sensitivity`; natural reflectances are smooth on that scale.
MARKOV_PRIOR_CORRELATION = 0.99


def _check_training(responses, reflectances):
    responses = _checks.as_array("responses", responses)
    reflectances = _checks.as_array("reflectances", reflectances)
    if responses.ndim != 2:
        raise ValueError(
            f"responses: expected shape (n, B) (targets, bands), got {tuple(responses.shape)}"
        )
    _checks.require_shape(
        "reflectances",
        reflectances,
        (responses.shape[0], N_WAVELENGTHS),
        "one 400..700 nm spectrum per target, same n as responses",
    )
    if responses.shape[0] < 2:
        raise ValueError(
            f"responses: {responses.shape[0]} target(s) cannot train a Wiener matrix; expected "
            "at least 2 (the paper uses 144)"
        )
    dtype = _checks.float_dtype(responses, reflectances)
    return responses.astype(dtype), reflectances.astype(dtype)


def wiener_loo_errors(responses, reflectances, noise_variances):
    """Leave-one-out rms spectral error of the training-based estimator for each sigma^2.

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


def _training_wiener(V, R, noise_variance):
    """W = R^T V (V^T V + n sigma^2 I)^-1, computed from the SVD V = U S Q^T as
    W^T = Q diag(s / (s^2 + n sigma^2)) U^T R.

    Forming V^T V squares the condition number of V: in float32 that costs about three
    significant digits of W for typical 10 nm filter sets; the SVD form does not.
    """
    lam = V.shape[0] * noise_variance
    U, s, Q_t = jnp.linalg.svd(V, full_matrices=False)
    # s^2 + lam = 0 only for a zero singular value with no regularisation: that direction carries
    # no information and gets a zero weight, as in a pseudo-inverse.
    denominator = s**2 + lam
    gain = jnp.where(denominator > 0, s / jnp.where(denominator > 0, denominator, 1.0), 0.0)
    U_t_R = jnp.matmul(U.T, R, precision=_HIGHEST)  # (k, 31)
    return jnp.matmul(Q_t.T * gain, U_t_R, precision=_HIGHEST).T


def select_wiener_noise_variance(responses, reflectances, noise_variances=None):
    """sigma^2 minimising the leave-one-out spectral error (see `wiener_loo_errors`).

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


def fit_wiener(responses, reflectances, noise_variance=None):
    """Training-based Wiener matrix from targets of known reflectance.

    Args:
      responses: corrected camera responses of the targets, shape (n, B) (144 targets in the
        paper; Stage II responses in the full method).
      reflectances: their measured reflectances, shape (n, 31), 400..700 nm step 10.
      noise_variance: sigma^2 (>= 0, response units squared). None (default) chooses it by
        leave-one-out cross-validation over `RELATIVE_NOISE_GRID`.

    Returns:
      W, shape (31, B): reflectance = v @ W.T (see `wiener`).
    """
    V, R = _check_training(responses, reflectances)
    if noise_variance is None:
        noise_variance, _, _ = select_wiener_noise_variance(V, R)
    else:
        if _checks.is_concrete(noise_variance) and not float(noise_variance) >= 0:
            raise ValueError(f"noise_variance: expected a value >= 0, got {noise_variance!r}")
        noise_variance = jnp.asarray(noise_variance, dtype=V.dtype)
    return _training_wiener(V, R, noise_variance)


def markov_correlation(n: int = N_WAVELENGTHS, rho: float = MARKOV_PRIOR_CORRELATION, dtype=jnp.float32):
    """First-order Markov autocorrelation K[i, j] = rho^|i - j|, shape (n, n)."""
    i = jnp.arange(n)
    return jnp.asarray(rho, dtype=dtype) ** jnp.abs(i[:, None] - i[None, :]).astype(dtype)


def wiener_from_sensitivity(sensitivity, reflectances=None, noise_variance=0.0):
    """Model-based Wiener matrix W = K_r M^T (M K_r M^T + sigma^2 I)^-1 for a known system.

    Args:
      sensitivity: M, shape (B, 31): the response of band b to reflectance r is (M @ r)[b], in the
        units of the responses W will be applied to (for flat-fielded responses, each row divided
        by its response to the white standard). Sampled 400..700 nm step 10.
      reflectances: example spectra, shape (n, 31), whose autocorrelation R^T R / n is K_r; None
        uses the first-order Markov prior `markov_correlation()` instead.
      noise_variance: sigma^2 >= 0 on the responses.

    Returns:
      W, shape (31, B).
    """
    M = _checks.as_array("sensitivity", sensitivity)
    if M.ndim != 2 or M.shape[1] != N_WAVELENGTHS:
        raise ValueError(
            f"sensitivity: expected shape (B, {N_WAVELENGTHS}) (bands, 400..700 nm step 10), "
            f"got {tuple(M.shape)}"
        )
    if _checks.is_concrete(noise_variance) and not float(noise_variance) >= 0:
        raise ValueError(f"noise_variance: expected a value >= 0, got {noise_variance!r}")
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


def wiener(v, W):
    """Reconstruct reflectance from responses: r = W v per pixel.

    Args:
      v: corrected responses, shape (..., B).
      W: Wiener matrix, shape (31, B).

    Returns:
      reflectance, shape (..., 31), 400..700 nm step 10.
    """
    v = _checks.band_array("v", v)
    W = _checks.as_array("W", W)
    _checks.require_shape("W", W, (N_WAVELENGTHS, v.shape[-1]), "31 wavelengths x the bands of v")
    dtype = _checks.float_dtype(v, W)
    return jnp.matmul(v.astype(dtype), W.astype(dtype).T, precision=_HIGHEST)


__all__ = [
    "RELATIVE_NOISE_GRID",
    "fit_wiener",
    "select_wiener_noise_variance",
    "wiener_loo_errors",
    "wiener_from_sensitivity",
    "markov_correlation",
    "wiener",
]
