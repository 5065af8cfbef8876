"""The sampling covariance of an affine reflectance estimator r = W x + r0 (E1) from its finite
training set: how much the estimate would move with other training noise, the input of
first-order (GUM, JCGM 100:2008) propagation of the estimator's uncertainty.

Reference: the covariance of the coefficients of a multivariate ordinary least-squares
regression, e.g. Mardia, Kent, Bibby, Multivariate Analysis, Academic Press 1979, ch. 6.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _checks
from ..grid import N_WAVELENGTHS
from .estimator import _HIGHEST, WienerEstimator, as_estimator


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


__all__ = ["EstimatorCovariance", "estimator_covariance"]
