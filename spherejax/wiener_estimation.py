"""Wiener estimation of 31-sample reflectance from 16-band camera responses.

Zou et al. (2019) reconstruct reflectance with a 31 x 16 matrix computed from 144 colour targets
of known reflectance by Wiener estimation (Section 2 and their ref. [21]). Every estimator here is
affine in the response, so that `correct` stays one matrix product per pixel:

    r = W v + r0,      W (31, B), r0 (31,)                                         (E1)

Real responses carry an offset (a residual dark level, stray light) and noise that differs by
band, and a lab's targets never match its samples exactly; both forms below model that.

Training-based ("training"; no knowledge of the system), a ridge regression with an unpenalised
intercept (today's form when `offset=False`):
    W  = K_rv (K_vv + sigma^2 I)^-1,  K_rv = cov(r, v), K_vv = cov(v)               (E2)
    r0 = r_mean - W v_mean
sigma^2, the noise variance assumed on the responses, is the regulariser.

Model-based ("model"; Haneishi et al. 2000, Shen & Xin 2006): first estimate the system,
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

The regularisers (sigma^2; the penalty and its weight on M; the shrinkage s) and, for "auto", the
method are chosen by cross-validation: whole groups of targets are held out where the caller
names groups (material, chart); otherwise k folds whose members are spectrally alike (a k-means
clustering of the reflectances), so that every held-out fold holds colours the rest of the
targets does not span. A random k-fold split scores how well an estimator interpolates within
the training material, which is what a training-based fit is best at and what does not carry to
another material (the reason this module chooses as it does).

References:
  Haneishi, Hasegawa, Hosoi, Yokoyama, Tsumura, Miyake, "System design for accurately estimating
  the spectral reflectance of art paintings", Appl. Opt. 39(35), 6621-6632 (2000),
  doi:10.1364/AO.39.006621.
  Shen, Xin, "Spectral characterization of a color scanner based on optimized adaptive
  estimation", J. Opt. Soc. Am. A 23(7), 1566-1569 (2006), doi:10.1364/JOSAA.23.001566.

Apply with `wiener(v, estimator)` (or a plain (31, B) matrix): reflectance (..., 31).
"""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _checks
from .grid import N_WAVELENGTHS
from .number_text import json_ready

_HIGHEST = jax.lax.Precision.HIGHEST

#: Candidate noise variances of the training form, relative to the mean response variance
#: tr(K_vv) / B: from effectively unregularised to a very smooth estimate.
RELATIVE_NOISE_GRID = tuple(10.0 ** (k / 4.0) for k in range(-40, 1))

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

#: Folds of the cross-validation when no groups are given.
DEFAULT_FOLDS = 5

METHODS = ("auto", "training", "model")


# ---------------------------------------------------------------------------------------------
# The estimator


@dataclasses.dataclass(frozen=True)
class CrossValidation:
    """Cross-validated errors of one method at its chosen regularisers (hashable: it rides in
    the estimator's static part).

    method: "training" or "model". spectral_rms: rms over held-out targets and wavelengths of
    r - r_hat. delta_e_d65: mean CIEDE2000 (D65, 2°) of the held-out targets. settings: the
    chosen regularisers as (name, value) pairs. folds: how the targets were split.
    """

    method: str
    spectral_rms: float
    delta_e_d65: float
    settings: tuple[tuple[str, object], ...]
    folds: str

    def as_dict(self) -> dict:
        return {
            "method": self.method, "spectral_rms": self.spectral_rms, "delta_e_d65": self.delta_e_d65,
            "settings": dict(self.settings), "folds": self.folds,
        }


class WienerEstimator(eqx.Module):
    """An affine reflectance estimator r = W v + r0 (E1), a pytree.

    matrix: W, (31, B). offset: r0, (31,). method: "training" or "model" ("matrix" for a plain
    matrix taken by `as_estimator`) (static).
    cross_validation: the cross-validated errors of every method tried, the chosen one first
    (static; empty when the estimator was built with fixed regularisers).
    """

    matrix: jax.Array
    offset: jax.Array
    method: str = eqx.field(static=True, default="training")
    cross_validation: tuple[CrossValidation, ...] = eqx.field(static=True, default=())

    def __check_init__(self):
        if self.matrix.ndim != 2 or self.matrix.shape[0] != N_WAVELENGTHS:
            raise ValueError(f"matrix: expected shape (31, B) (31 wavelengths x B bands), got {tuple(self.matrix.shape)}")
        _checks.require_shape("offset", self.offset, (N_WAVELENGTHS,), "one value per wavelength")

    def __call__(self, v):
        return wiener(v, self)


def as_estimator(estimator) -> WienerEstimator:
    """A WienerEstimator, or a plain (31, B) matrix taken as one with a zero offset."""
    if isinstance(estimator, WienerEstimator):
        return estimator
    W = _checks.as_array("W", estimator)
    if W.ndim != 2 or W.shape[0] != N_WAVELENGTHS:
        raise ValueError(f"W: expected shape (31, B) (31 wavelengths x the bands), got {tuple(W.shape)}")
    return WienerEstimator(W, jnp.zeros(N_WAVELENGTHS, W.dtype), method="matrix")


def wiener(v, W):
    """Reconstruct reflectance from responses: r = W v + r0 per pixel (E1).

    Args:
      v: corrected responses, shape (..., B).
      W: a `WienerEstimator` (from `fit_wiener`), or a plain matrix (31, B) (r0 = 0).

    Returns:
      reflectance, shape (..., 31), 400..700 nm step 10.
    """
    v = _checks.band_array("v", v)
    estimator = as_estimator(W)
    W = estimator.matrix
    _checks.require_shape("W", W, (N_WAVELENGTHS, v.shape[-1]), "31 wavelengths x the bands of v")
    dtype = _checks.float_dtype(v, W)
    return jnp.matmul(v.astype(dtype), W.astype(dtype).T, precision=_HIGHEST) + estimator.offset.astype(dtype)


# ---------------------------------------------------------------------------------------------
# Argument checks


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


def _check_sensitivity(sensitivity, V):
    """A known sensitivity M as an array (B, 31) in V's dtype, for responses V (n, B)."""
    M = _checks.as_array("sensitivity", sensitivity)
    _checks.require_shape("sensitivity", M, (V.shape[1], N_WAVELENGTHS), "bands of responses x 31 wavelengths")
    return M.astype(V.dtype)


def _check_noise_variance(noise_variance):
    if _checks.is_concrete(noise_variance) and not float(noise_variance) >= 0:
        raise ValueError(f"noise_variance: expected a value >= 0, got {noise_variance!r}")


def _check_determined(V, R, what: str) -> None:
    """Refuse targets that cannot determine an estimator (concrete data only): non-finite
    values, or responses or reflectances that do not vary."""
    if not (_checks.is_concrete(V) and _checks.is_concrete(R)):
        return
    V_np, R_np = np.asarray(V), np.asarray(R)
    for name, x in (("responses", V_np), ("reflectances", R_np)):
        bad = ~np.isfinite(x)
        if bad.any():
            row = int(np.argwhere(bad)[0][0])
            raise ValueError(f"{name}: target {row} has a non-finite value; expected finite {what} data")
    if not np.any(np.ptp(V_np, axis=0) > 0):
        raise ValueError(
            f"responses: all {V_np.shape[0]} targets give the same response; expected targets of "
            f"different colours to fit {what}"
        )
    if not np.any(np.ptp(R_np, axis=0) > 0):
        raise ValueError(
            f"reflectances: all {R_np.shape[0]} targets have the same reflectance; expected targets "
            f"of different colours to fit {what}"
        )


# ---------------------------------------------------------------------------------------------
# Weighted moments: every fit takes per-target weights w (n,) in {0, 1}, so that the folds of a
# cross-validation are the same computation with other weights (vmapped, one compilation).


def _weighted_centre(X, w):
    """(mean (d,), centred rows scaled by sqrt(w) (n, d)) of X (n, d) under weights w (n,)."""
    mean = jnp.sum(w[:, None] * X, axis=0) / jnp.sum(w)
    return mean, (X - mean) * jnp.sqrt(w)[:, None]


def _symmetric_solve(A, B):
    """A^-1 B for a symmetric positive (semi-)definite A (k, k), through its eigendecomposition
    so that a (numerically) singular direction gets a zero weight instead of a blow-up."""
    eigenvalues, Q = jnp.linalg.eigh(A)
    floor = jnp.max(eigenvalues) * jnp.finfo(A.dtype).eps * A.shape[0]
    inverse = jnp.where(eigenvalues > floor, 1.0 / jnp.where(eigenvalues > floor, eigenvalues, 1.0), 0.0)
    return jnp.matmul(Q * inverse, jnp.matmul(Q.T, B, precision=_HIGHEST), precision=_HIGHEST)


# ---------------------------------------------------------------------------------------------
# Training-based form (E2)


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
        form W = R^T V (V^T V + n sigma^2 I)^-1 of the first release.
    """
    V, R = _check_training(responses, reflectances)
    _check_noise_variance(noise_variance)
    W, r0 = _training_fit(V, R, jnp.ones(V.shape[0], V.dtype), jnp.asarray(noise_variance, V.dtype), offset)
    return WienerEstimator(W, r0, method="training")


# ---------------------------------------------------------------------------------------------
# Model-based form (E3-E7)


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


# ---------------------------------------------------------------------------------------------
# Cross-validation


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


def fold_weights(reflectances, groups=None, folds: int = DEFAULT_FOLDS) -> np.ndarray:
    """Training weights (F, n) of the F folds of `fold_labels`: 0 where a target is held out."""
    labels, _ = fold_labels(reflectances, groups, folds)
    return _weights_of(labels)


def _weights_of(labels: np.ndarray) -> np.ndarray:
    """(F, n) training weights, one row per distinct fold label: 0 where the target is held out."""
    return (labels[None, :] != np.unique(labels)[:, None]).astype(np.float64)


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
    from .colorimetry import delta_e_2000, reflectance_to_lab

    return jnp.mean(delta_e_2000(reflectance_to_lab(estimates, "D65"), reflectance_to_lab(R, "D65")))


def _delta_e_d65(estimates, R) -> float:
    # The shortest decimal of the precision it was computed in (a report's JSON states it so).
    return json_ready(np.asarray(_mean_delta_e_d65(jnp.asarray(estimates, R.dtype), R)))


def _cross_validate_training(V, R, weights, folds_text, offset=True):
    """(CrossValidation, chosen sigma^2) of the training form."""
    V_np = np.asarray(V, np.float64)
    power = np.mean((V_np - V_np.mean(axis=0)) ** 2) if offset else np.mean(V_np**2)
    candidates = (power * np.asarray(RELATIVE_NOISE_GRID)).astype(V.dtype)
    estimates = np.asarray(_training_cv(V, R, jnp.asarray(weights, V.dtype), jnp.asarray(candidates), offset), np.float64)
    k, rms = _best(estimates, R)
    result = CrossValidation(
        method="training", spectral_rms=rms, delta_e_d65=_delta_e_d65(estimates[k], R),
        settings=(("noise_variance", json_ready(candidates[k])), ("offset", bool(offset))), folds=folds_text,
    )
    return result, jnp.asarray(candidates[k])


def _cross_validate_model(V, R, weights, folds_text, sensitivity=None):
    """(CrossValidation, penalty, penalty weight, shrinkage) of the model form; with a known
    `sensitivity` (B, 31) only the shrinkage is chosen."""
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
    return result, penalty, penalty_weight, shrinkage


# ---------------------------------------------------------------------------------------------
# The entry point

# Jitted once for the final fit of each method: run op by op, each LAPACK call and reduction
# would compile on its own (seconds in all, against milliseconds of work).
_training_fit_jit = jax.jit(_training_fit, static_argnames=("offset",))
_model_fit_jit = jax.jit(_model_fit)



def fit_wiener(
    responses,
    reflectances,
    noise_variance=None,
    *,
    method: str = "auto",
    groups=None,
    folds: int = DEFAULT_FOLDS,
    sensitivity=None,
    offset: bool = True,
) -> WienerEstimator:
    """An affine reflectance estimator r = W v + r0 from targets of known reflectance.

    Args:
      responses: corrected camera responses of the targets, shape (n, B) (144 targets in the
        paper; Stage II responses in the full method).
      reflectances: their measured reflectances, shape (n, 31), 400..700 nm step 10.
      noise_variance: sigma^2 of the training form (>= 0, response units squared); given, it
        fixes the method to "training" with no cross-validation (the first release's call).
      method: "auto" (default: the method and regularisers with the lowest cross-validated
        spectral rms), "training" (E2) or "model" (E3-E7).
      groups: optional label per target (n,), e.g. material or chart: cross-validation then holds
        out one group at a time. None: `folds` clusters of spectrally alike targets.
      folds: the number of folds without groups.
      sensitivity: a known sensitivity M (B, 31) for the model form (with "auto" the model form
        uses it; only b and K_n are then estimated).
      offset: False fits the training form without r0 (the first release's form).

    Returns:
      WienerEstimator: .matrix (31, B), .offset (31,), .method, .cross_validation (each method
      tried, the chosen one first, with its held-out spectral rms and mean ΔE00 under D65).

    The fits run on the responses divided by the power of two nearest their rms (exact, so
    flat-fielded responses give the same bits), which keeps responses in any units, 1e-30 to
    1e30, inside float32's range; W and the reported sigma^2 are in the caller's units.

    Raises:
      ValueError: on shapes, non-finite data, or targets that do not vary (nothing to fit).
    """
    V, R = _check_training(responses, reflectances)
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if noise_variance is not None:
        if method == "model":
            raise ValueError("noise_variance: applies to the training form; got it with method='model'")
        _check_noise_variance(noise_variance)
        W, r0 = _training_fit(V, R, jnp.ones(V.shape[0], V.dtype), jnp.asarray(noise_variance, V.dtype), offset)
        return WienerEstimator(W, r0, method="training")
    if not (_checks.is_concrete(V) and _checks.is_concrete(R)):
        raise ValueError(
            "fit_wiener: choosing regularisers by cross-validation needs concrete data, not traced "
            "values; call it outside jit/grad, or use training_estimator / model_estimator with "
            "fixed regularisers inside"
        )
    _check_determined(V, R, "a Wiener estimator")
    # Fit in units where the responses' rms is about 1: responses of 1e30 (or 1e-30) would
    # overflow (underflow) the squares of the fits in float32. A power of two, so that scaling is
    # exact and responses near 1 (flat-fielded ones) give the same bits as unscaled.
    scale = _unit_scale(V)
    V = V / scale
    M = None if sensitivity is None else _check_sensitivity(sensitivity, V) / scale
    labels, folds_text = fold_labels(R, groups, folds)
    weights = _weights_of(labels)
    ones = jnp.ones(V.shape[0], V.dtype)

    candidates = {}
    if method in ("auto", "training"):
        cv, sigma2 = _cross_validate_training(V, R, weights, folds_text, offset=offset)
        candidates["training"] = (cv, functools.partial(_training_fit_jit, V, R, ones, sigma2, offset))
    if method in ("auto", "model"):
        cv, penalty, penalty_weight, shrinkage = _cross_validate_model(V, R, weights, folds_text, M)
        candidates["model"] = (cv, functools.partial(
            _model_fit_jit, V, R, ones, jnp.asarray(penalty_weight, V.dtype), jnp.asarray(shrinkage, V.dtype),
            _penalty_root(penalty, V.dtype), M,
        ))
    ranked = sorted(candidates.values(), key=lambda item: item[0].spectral_rms)
    W, r0 = ranked[0][1]()
    reports = tuple(_in_response_units(item[0], scale) for item in ranked)
    return WienerEstimator(W / scale, r0, method=ranked[0][0].method, cross_validation=reports)


def _unit_scale(V) -> float:
    """The power of two nearest the rms of V (1 if V is all zero)."""
    rms = float(np.sqrt(np.mean(np.square(np.asarray(V, np.float64)))))
    return 1.0 if not rms > 0 else float(2.0 ** np.round(np.log2(rms)))


def _in_response_units(report: CrossValidation, scale: float) -> CrossValidation:
    """A report of a fit on responses / scale, with sigma^2 back in the caller's units."""
    settings = tuple((k, v * scale**2 if k == "noise_variance" else v) for k, v in report.settings)
    return dataclasses.replace(report, settings=settings)


# ---------------------------------------------------------------------------------------------
# Sampling covariance of an estimator: how much r = W x + r0 would move with other training noise


class EstimatorCovariance(eqx.Module):
    """Sampling covariance of an affine estimator r = W x + r0 (E1) from its finite training set.

    Writing the estimator as the multivariate linear regression R ≈ X̃ [W r0]ᵀ on X̃ = [V, 1]
    (n, B + 1), the coefficients have the Kronecker covariance Cov(vec [W r0]ᵀ) = residual ⊗ gram
    (vec stacking columns, i.e. one wavelength's B + 1 coefficients after another), so that for a
    response x (B,), with x̃ = (x, 1),

        Cov(r | x) ≈ (x̃ᵀ gram x̃) residual                                              (C1)

    gram: (B + 1, B + 1), (X̃ᵀX̃)⁻¹ (last row and column: the offset's), in 1 / response² in the
      band block, 1 / response against the offset and dimensionless in the corner, so that
      x̃ᵀ gram x̃ is dimensionless. residual: (31, 31), the residual covariance Σ of the
      estimator's reflectances on its training targets (reflectance² units). From
      `estimator_covariance`; the input of first-order (GUM, JCGM 100:2008) propagation of the
      estimator's uncertainty.
    """

    gram: jax.Array
    residual: jax.Array

    def prediction_scale(self, x):
        """x̃ᵀ gram x̃ (dimensionless) for responses x (..., B), x̃ = (x, 1): shape (...).

        The variance of the estimate at x in units of the residual variance: 1/n at the mean
        training response, growing with the distance from it (the leverage of x).
        """
        x = _checks.band_array("x", x)
        bands = self.gram.shape[-1] - 1
        _checks.require_last_axis("x", x, bands, f"one response per band of the estimator, B = {bands}")
        dtype = _checks.float_dtype(x, self.gram)
        x, gram = x.astype(dtype), self.gram.astype(dtype)
        # x̃ᵀ G x̃ = xᵀ G_xx x + 2 xᵀ g + G_11 without concatenating a 1 to every pixel.
        quadratic = jnp.sum(jnp.matmul(x, gram[:bands, :bands], precision=_HIGHEST) * x, axis=-1)
        return quadratic + 2.0 * jnp.matmul(x, gram[:bands, bands], precision=_HIGHEST) + gram[bands, bands]

    def prediction_covariance(self, x):
        """Cov(r | x) of (C1) for responses x (..., B): shape (..., 31, 31), reflectance² units."""
        scale = self.prediction_scale(x)
        return scale[..., None, None] * self.residual.astype(scale.dtype)


def _estimator_covariance(V, R, W, r0):
    """(gram, residual) of `estimator_covariance` on checked arrays of one dtype."""
    n, bands = V.shape
    # gram = (X̃ᵀX̃)⁻¹ through the centred responses V_c = V - 1 v_meanᵀ: with X̃ = [V_c, 1] T,
    # T = [[I, 0], [v_meanᵀ, 1]], and V_c ⟂ 1,
    #     (X̃ᵀX̃)⁻¹ = [[G, -G m], [-mᵀ G, 1/n + mᵀ G m]],  G = (V_cᵀV_c)⁻¹, m = v_mean.
    # G from the SVD of V_c with unit-norm columns (G = D Q diag(1/s²) Qᵀ D, D the inverse column
    # norms): never forming V_cᵀV_c keeps its squared condition number out, and the scaling
    # keeps bands of very different magnitude (or units) from deciding the rank cut-off.
    # Directions with a (numerically) zero singular value get zero weight, as in a pseudo-inverse.
    mean = jnp.mean(V, axis=0)
    Vc = V - mean
    norms = jnp.sqrt(jnp.sum(Vc**2, axis=0))
    inverse_norms = jnp.where(norms > 0, 1.0 / jnp.where(norms > 0, norms, 1.0), 0.0)
    _, s, Q_t = jnp.linalg.svd(Vc * inverse_norms, full_matrices=False)
    cutoff = jnp.max(s) * jnp.finfo(V.dtype).eps * max(V.shape)
    inverse_square = jnp.where(s > cutoff, 1.0 / jnp.where(s > cutoff, s, 1.0) ** 2, 0.0)
    root = Q_t.T * jnp.sqrt(inverse_square) * inverse_norms[:, None]  # G = root rootᵀ
    G = jnp.matmul(root, root.T, precision=_HIGHEST)
    G_m = jnp.matmul(G, mean, precision=_HIGHEST)
    corner = 1.0 / n + jnp.dot(mean, G_m, precision=_HIGHEST)
    gram = jnp.concatenate([
        jnp.concatenate([G, -G_m[:, None]], axis=1),
        jnp.concatenate([-G_m, corner[None]])[None, :],
    ])
    E = R - (jnp.matmul(V, W.T, precision=_HIGHEST) + r0)
    residual = jnp.matmul(E.T, E, precision=_HIGHEST) / (n - (bands + 1))
    return gram, residual


def estimator_covariance(responses, reflectances, *, estimator) -> EstimatorCovariance:
    """The sampling covariance (C1) of an affine reflectance estimator from its training targets.

    Args:
      responses: the training responses V, (n, B), that the estimator was fitted on.
      reflectances: their reflectances R, (n, 31), 400..700 nm step 10.
      estimator: keyword-only; a `WienerEstimator` or a plain (31, B) matrix (r0 = 0).

    Returns:
      `EstimatorCovariance` with gram = (X̃ᵀX̃)⁻¹, X̃ = [V, 1] (n, B + 1), and
      residual = EᵀE / (n - (B + 1)), E = R - (V Wᵀ + r0) the estimator's own residuals on the
      targets: Cov(r | x) ≈ (x̃ᵀ gram x̃) residual, the covariance of the coefficients of a
      multivariate ordinary least-squares regression, Cov(vec [W r0]ᵀ) = residual ⊗ gram
      (e.g. Mardia, Kent, Bibby, Multivariate Analysis, Academic Press 1979, ch. 6). gram is
      computed from the SVD of the centred responses with columns scaled to unit norm, not by
      inverting X̃ᵀX̃, so that badly scaled responses (bands in very different units) keep
      their digits. It is a pseudo-inverse: a direction in which the training responses do
      not vary at all (exactly collinear bands) gets zero variance, an underestimate for a
      response off that span.

    Any affine estimator is treated here like the ordinary least-squares one on [V, 1] for its
    sampling variability. For the training form with a small sigma^2 that is what it is; for
    ridge (larger sigma^2) and model-based estimators it is an estimate, conservative for such
    shrinkage estimators (their coefficients vary less than least squares' across training
    sets), while their residuals, and so `residual`, are larger. Neither part includes the
    estimator's bias on materials unlike the targets: that is a model error, to be assessed on
    held-out materials (`fit_wiener`'s cross-validation), not a sampling variance. jit- and
    grad-friendly; the value checks (non-finite data) run on concrete data only.

    Raises:
      ValueError: on shapes (responses not (n, B), reflectances not (n, 31), an estimator for
        other than B bands), n <= B + 1 (no degree of freedom left for the residual covariance),
        or non-finite values.
    """
    V = _checks.as_array("responses", responses)
    R = _checks.as_array("reflectances", reflectances)
    if V.ndim != 2:
        raise ValueError(f"responses: expected shape (n, B) (targets, bands), got {tuple(V.shape)}")
    _checks.require_shape(
        "reflectances", R, (V.shape[0], N_WAVELENGTHS), "one 400..700 nm spectrum per target, same n as responses"
    )
    n, bands = V.shape
    if n <= bands + 1:
        raise ValueError(
            f"responses: shape {tuple(V.shape)} leaves no degree of freedom for the residual "
            f"covariance; expected more than B + 1 = {bands + 1} targets"
        )
    # A plain matrix is checked under the name "estimator" before `as_estimator` gives it r0 = 0.
    matrix = estimator.matrix if isinstance(estimator, WienerEstimator) else _checks.as_array("estimator", estimator)
    _checks.require_shape("estimator", matrix, (N_WAVELENGTHS, bands), "W: 31 wavelengths x the bands of responses")
    fit = as_estimator(estimator if isinstance(estimator, WienerEstimator) else matrix)
    arrays = {"responses": V, "reflectances": R, "estimator.matrix": fit.matrix, "estimator.offset": fit.offset}
    for name, x in arrays.items():
        if _checks.is_concrete(x) and not bool(np.all(np.isfinite(np.asarray(x)))):
            raise ValueError(f"{name}: has non-finite values (shape {tuple(x.shape)}); expected finite values")
    dtype = _checks.float_dtype(V, R, fit.matrix, fit.offset)
    gram, residual = _estimator_covariance_jit(
        V.astype(dtype), R.astype(dtype), fit.matrix.astype(dtype), fit.offset.astype(dtype)
    )
    return EstimatorCovariance(gram, residual)


_estimator_covariance_jit = jax.jit(_estimator_covariance)


# ---------------------------------------------------------------------------------------------
# The first release's functions, kept: the offset-free training form's leave-one-out choice.


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
    Markov prior `markov_correlation()` when `reflectances` is None (the first release's form).

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


__all__ = [
    "RELATIVE_NOISE_GRID",
    "SENSITIVITY_PENALTY_GRID",
    "SENSITIVITY_PENALTIES",
    "PRIOR_SHRINKAGE_GRID",
    "METHODS",
    "CrossValidation",
    "EstimatorCovariance",
    "WienerEstimator",
    "as_estimator",
    "estimate_system",
    "estimator_covariance",
    "fit_wiener",
    "fold_labels",
    "fold_weights",
    "markov_correlation",
    "model_estimator",
    "select_wiener_noise_variance",
    "training_estimator",
    "wiener",
    "wiener_from_sensitivity",
    "wiener_from_system",
    "wiener_loo_errors",
]
