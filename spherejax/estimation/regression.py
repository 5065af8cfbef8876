"""The training-based estimator ("training"): a ridge regression of reflectance on response.

No knowledge of the system: the affine estimator (E1) is fitted to targets of known reflectance,
as Zou et al. (2019, Section 2) compute their 31 x 16 matrix from 144 colour targets. This form is
a ridge regression with an unpenalised intercept (the offset-free form when `offset=False`):

    W  = K_rv (K_vv + sigma^2 I)^-1,  K_rv = cov(r, v), K_vv = cov(v)               (E2)
    r0 = r_mean - W v_mean

sigma^2, the noise variance assumed on the responses, is the regulariser
(`spherejax.estimation.cross_validation` chooses it from `RELATIVE_NOISE_GRID`).

Named by the method, not a reference: the code cites no paper for this form beyond Zou et al.'s
use of a target-trained Wiener matrix.
"""

from __future__ import annotations

import jax.numpy as jnp

from ._targets import _check_noise_variance, _check_training, _weighted_centre
from .estimator import _HIGHEST, WienerEstimator

#: Candidate noise variances of the training form, relative to the mean response variance
#: tr(K_vv) / B: from effectively unregularised to a very smooth estimate.
RELATIVE_NOISE_GRID = tuple(10.0 ** (k / 4.0) for k in range(-40, 1))


def _training_fit(V, R, w, noise_variance, offset: bool):
    """(W (31, B), r0 (31,)) of (E2) from the targets with weight 1.

    Computed from the SVD of the centred responses, W^T = Q diag(s / (s^2 + n sigma^2)) U^T R_c:
    forming V^T V would square V's condition number, which costs float32 about three digits.
    """
    n = jnp.sum(w)
    if offset:
        v_mean, Vc = _weighted_centre(V, w)
        r_mean, Rc = _weighted_centre(R, w)
    else:
        v_mean = jnp.zeros(V.shape[1], V.dtype)
        r_mean = jnp.zeros(R.shape[1], R.dtype)
        Vc, Rc = V * jnp.sqrt(w)[:, None], R * jnp.sqrt(w)[:, None]
    U, s, Q_t = jnp.linalg.svd(Vc, full_matrices=False)
    # s^2 + lam = 0 only for a zero singular value with no regularisation: that direction carries
    # no information and gets a zero weight, as in a pseudo-inverse.
    denominator = s**2 + n * noise_variance
    gain = jnp.where(denominator > 0, s / jnp.where(denominator > 0, denominator, 1.0), 0.0)
    W = jnp.matmul(Q_t.T * gain, jnp.matmul(U.T, Rc, precision=_HIGHEST), precision=_HIGHEST).T
    return W, r_mean - jnp.matmul(W, v_mean, precision=_HIGHEST)


def training_estimator(responses, reflectances, noise_variance, *, offset: bool = True) -> WienerEstimator:
    """The training-based estimator (E2) with a given sigma^2 (jit- and grad-friendly).

    Args:
      responses: (n, B). reflectances: (n, 31).
      noise_variance: sigma^2 >= 0, in response units squared.
      offset: fit r0 too (an unpenalised intercept, i.e. on [v, 1]); False is the offset-free
        form W = R^T V (V^T V + n sigma^2 I)^-1 (r0 = 0).
    """
    V, R = _check_training(responses, reflectances)
    _check_noise_variance(noise_variance)
    W, r0 = _training_fit(V, R, jnp.ones(V.shape[0], V.dtype), jnp.asarray(noise_variance, V.dtype), offset)
    return WienerEstimator(W, r0, method="training")


__all__ = ["RELATIVE_NOISE_GRID", "training_estimator"]
