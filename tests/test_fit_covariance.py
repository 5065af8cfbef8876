"""Parameter covariances of the two fitted stages, the inputs of first-order (GUM) propagation:
the Stage II coefficients (`Stage2Fit.covariance`) and the reflectance estimator
(`estimator_covariance`). Each is checked against a textbook float64 computation and against
Monte Carlo refits of data with known noise."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax.polynomial import CONVERGED, NONFINITE, ROBUST_TUNING, UNDETERMINED, fit_stage2_detailed
from spherejax.wiener_estimation import training_estimator

from .helpers import TABLE_2

B = 16
NOISE = 0.002  # response noise of the Stage II targets


def stage2_training_set(bands=B, seed=0):
    """(v, p) (90, bands) like the paper's: 9 grey patches (v 0.05-1) x 10 backgrounds (p 0.9-1.1)."""
    rng = np.random.default_rng(seed)
    grey = np.linspace(0.05, 1.0, 9)[:, None, None]
    p = rng.uniform(0.9, 1.1, (1, 10, bands))
    v = grey / p * rng.uniform(0.97, 1.03, (9, 10, bands))
    return v.reshape(-1, bands), np.broadcast_to(p, v.shape).reshape(-1, bands)


def design(v, p):
    """M (n, 4) = (p v, v, p, 1) of Eq. 20 for one band."""
    return np.column_stack([p * v, v, p, np.ones_like(v)])


def textbook_l2_covariance(v, p, target):
    """sigma^2 (MᵀM)^-1 with sigma^2 = RSS / (n - 4), float64, one band (n,) each."""
    M = design(v, p)
    coeffs = np.linalg.lstsq(M, target, rcond=None)[0]
    residual = target - M @ coeffs
    return residual @ residual / (len(v) - 4) * np.linalg.inv(M.T @ M)


def psi_and_derivative(loss, u):
    """psi(u) and psi'(u) of each robust loss, derived by hand (the module differentiates psi)."""
    c = ROBUST_TUNING[loss]
    if loss == "huber":
        return np.clip(u, -c, c), (np.abs(u) < c).astype(float)
    if loss == "cauchy":
        q = (u / c) ** 2
        return u / (1 + q), (1 - q) / (1 + q) ** 2
    q = (u / c) ** 2
    inside = np.abs(u) < c
    return np.where(inside, u * (1 - q) ** 2, 0.0), np.where(inside, (1 - q) * (1 - 5 * q), 0.0)


def close(actual, expected, rtol):
    """Entrywise within rtol of the largest entry (covariances have entries near zero)."""
    np.testing.assert_allclose(actual, expected, rtol=rtol, atol=rtol * np.max(np.abs(expected)))


class TestStage2Covariance:
    def test_l2_is_textbook_one_band(self, dtype):
        v, p = stage2_training_set(bands=1)
        target = np.asarray(sj.stage2(v, p, TABLE_2[:1])) + np.random.default_rng(1).normal(0, NOISE, v.shape)
        v, p, target = (x.astype(dtype) for x in (v, p, target))
        fit = fit_stage2_detailed(v, p, target)
        assert fit.covariance.shape == (1, 4, 4) and fit.covariance.dtype == dtype
        expected = textbook_l2_covariance(*(x[:, 0].astype(np.float64) for x in (v, p, target)))
        close(np.asarray(fit.covariance[0], np.float64), expected, 1e-9 if dtype == np.float64 else 2e-2)

    def test_l2_is_textbook_all_bands_with_dropped_samples(self, dtype):
        v, p = stage2_training_set()
        target = np.asarray(sj.stage2(v, p, TABLE_2)) + np.random.default_rng(2).normal(0, NOISE, v.shape)
        v = v.copy()
        v[[4, 50], 3] = np.nan  # band 3 fits on 88 samples: n - 4 = 84 degrees of freedom
        v, p, target = (x.astype(dtype) for x in (v, p, target))
        covariance = np.asarray(fit_stage2_detailed(v, p, target).covariance, np.float64)
        for band in range(B):
            keep = np.isfinite(v[:, band])
            expected = textbook_l2_covariance(*(x[keep, band].astype(np.float64) for x in (v, p, target)))
            close(covariance[band], expected, 1e-9 if dtype == np.float64 else 2e-2)

    @pytest.mark.parametrize("loss", ["huber", "cauchy", "tukey"])
    def test_robust_is_hubers_formula(self, loss):
        """Huber (1981) Sec. 7.6 written out in numpy with psi' derived by hand, on data with
        outliers so that psi' varies (K > 1)."""
        v, p = stage2_training_set(bands=2, seed=3)
        rng = np.random.default_rng(4)
        target = np.asarray(sj.stage2(v, p, TABLE_2[:2])) + rng.normal(0, NOISE, v.shape)
        target[rng.choice(90, 9, replace=False)] += 0.05
        fit = fit_stage2_detailed(v, p, target, loss)
        assert np.all(np.asarray(fit.status) == CONVERGED)
        for band in range(2):
            M = design(v[:, band], p[:, band])
            s = float(fit.scale[band])
            u = (target[:, band] - M @ np.asarray(fit.coeffs[band])) / s
            psi, dpsi = psi_and_derivative(loss, u)
            n = len(u)
            k = 1 + 4 / n * dpsi.var() / dpsi.mean() ** 2
            expected = k**2 * np.sum(psi**2) / (n - 4) / dpsi.mean() ** 2 * s**2 * np.linalg.inv(M.T @ M)
            assert k > 1.005  # psi' does vary: K's correction is exercised
            close(np.asarray(fit.covariance[band]), expected, 1e-8)

    @pytest.mark.parametrize("loss", ["huber", "cauchy", "tukey"])
    def test_robust_with_a_wide_scale_is_least_squares(self, loss):
        """With s far above the residuals psi(u) ~ u, psi' ~ 1, K ~ 1: the l2 covariance."""
        v, p = stage2_training_set(bands=2, seed=5)  # the shapes above: one compilation per loss
        target = np.asarray(sj.stage2(v, p, TABLE_2[:2])) + np.random.default_rng(6).normal(0, NOISE, v.shape)
        robust = fit_stage2_detailed(v, p, target, loss, scale=1000 * NOISE)
        close(np.asarray(robust.covariance), np.asarray(fit_stage2_detailed(v, p, target).covariance), 1e-4)

    @pytest.mark.parametrize("loss", ["l2", "huber"])
    def test_monte_carlo_recovery(self, loss):
        """Refit 1000 noisy copies of one band (Gaussian noise, Table 2 band 1): the spread of the
        fitted c1..c4 is the reported covariance. Each copy is one "band" of a single vmapped fit.
        For Huber this is the asymptotic sandwich at 95 % efficiency, not exact at n = 90."""
        refits = 1000
        v, p = stage2_training_set(bands=1)
        clean = np.asarray(sj.stage2(v, p, TABLE_2[:1]))
        V, P = np.tile(v, (1, refits)), np.tile(p, (1, refits))
        target = clean + np.random.default_rng(7).normal(0, NOISE, (90, refits))
        fit = fit_stage2_detailed(V, P, target, loss)
        assert np.all(np.asarray(fit.status) == CONVERGED)
        empirical = np.cov(np.asarray(fit.coeffs).T)
        reported = np.asarray(fit.covariance).mean(axis=0)
        ratio = np.sqrt(np.diag(empirical) / np.diag(reported))
        assert np.all((ratio > 0.9) & (ratio < 1.1)), ratio
        correlation = lambda S: S / np.sqrt(np.outer(np.diag(S), np.diag(S)))  # noqa: E731
        # p ~ 1 makes p v and v nearly collinear: c1 and c2 trade off almost exactly.
        assert correlation(reported)[0, 1] < -0.99
        assert abs(correlation(empirical)[0, 1] - correlation(reported)[0, 1]) < 0.005
        np.testing.assert_allclose(correlation(empirical), correlation(reported), atol=0.05)

    def test_undetermined_nonfinite_and_no_degree_of_freedom_are_nan(self):
        v, p = stage2_training_set(bands=4)
        target = np.asarray(sj.stage2(v, p, TABLE_2[:4])) + np.random.default_rng(8).normal(0, NOISE, v.shape)
        v = v.copy()
        v[3:, 0] = np.nan  # 3 usable samples: UNDETERMINED
        target[:, 1] = 1e308  # overflows the solve: NONFINITE
        target[::2, 1] = -1e308
        # Band 3: 4 usable samples (4 patches on 4 backgrounds) determine c1..c4 exactly and
        # leave no degree of freedom to estimate the noise.
        v[np.setdiff1d(np.arange(90), [0, 21, 42, 63]), 3] = np.nan
        fit = fit_stage2_detailed(v, p, target)
        status, covariance = np.asarray(fit.status), np.asarray(fit.covariance)
        assert status.tolist() == [UNDETERMINED, NONFINITE, CONVERGED, CONVERGED]
        assert np.isnan(covariance[:2]).all()
        assert np.isfinite(covariance[2]).all()
        assert np.isfinite(np.asarray(fit.coeffs)[3]).all() and np.isnan(covariance[3]).all()

    @pytest.mark.parametrize("loss", ["l2", "tukey"])
    def test_jit_symmetric_positive_definite(self, loss):
        v, p = stage2_training_set(bands=2, seed=9)
        target = np.asarray(sj.stage2(v, p, TABLE_2[:2])) + np.random.default_rng(9).normal(0, NOISE, v.shape)
        eager = np.asarray(fit_stage2_detailed(v, p, target, loss).covariance)
        traced = np.asarray(jax.jit(fit_stage2_detailed, static_argnames=("loss",))(v, p, target, loss=loss).covariance)
        close(traced, eager, 1e-10)
        np.testing.assert_allclose(eager, np.swapaxes(eager, 1, 2), rtol=1e-10, atol=0)
        assert np.all(np.linalg.eigvalsh(eager) > 0)


# ---------------------------------------------------------------------------------------------
# The reflectance estimator

SIGMA_R = 0.01  # reflectance noise of the synthetic targets, independent across wavelengths


def linear_targets(n=144, seed=0):
    """Responses X (n, 16) with correlated bands, a true affine map (W (31, 16), r0 (31,)) and
    the noise-free reflectances X Wᵀ + r0."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(0.05, 0.9, (n, B))
    X = 0.7 * X + 0.3 * X.mean(axis=1, keepdims=True)
    W = rng.normal(0.0, 0.5, (31, B))
    r0 = rng.uniform(0.0, 0.1, 31)
    return X, W, r0, X @ W.T + r0


def textbook_estimator_covariance(X, R, W, r0):
    """(gram, residual) in float64 by the normal equations."""
    X1 = np.column_stack([X, np.ones(len(X))])
    E = R - (X @ W.T + r0)
    return np.linalg.inv(X1.T @ X1), E.T @ E / (len(X) - X1.shape[1])


class TestEstimatorCovariance:
    def test_is_textbook(self, dtype):
        X, _, _, clean = linear_targets()
        R = clean + np.random.default_rng(1).normal(0, SIGMA_R, clean.shape)
        X, R = X.astype(dtype), R.astype(dtype)
        estimator = training_estimator(X, R, 1e-12)
        result = sj.estimator_covariance(X, R, estimator=estimator)
        assert result.gram.shape == (B + 1, B + 1) and result.residual.shape == (31, 31)
        assert result.gram.dtype == dtype and result.residual.dtype == dtype
        gram, residual = textbook_estimator_covariance(
            *(np.asarray(x, np.float64) for x in (X, R, estimator.matrix, estimator.offset))
        )
        rtol = 1e-9 if dtype == np.float64 else 1e-4
        close(np.asarray(result.gram, np.float64), gram, rtol)
        close(np.asarray(result.residual, np.float64), residual, rtol)

    def test_plain_matrix_has_no_offset(self):
        X, W, _, clean = linear_targets()
        result = sj.estimator_covariance(X, clean, estimator=W)
        _, residual = textbook_estimator_covariance(X, clean, W, np.zeros(31))
        close(np.asarray(result.residual), residual, 1e-10)

    def test_symmetric_positive_semidefinite(self, dtype):
        X, _, _, clean = linear_targets(seed=2)
        R = (clean + np.random.default_rng(2).normal(0, SIGMA_R, clean.shape)).astype(dtype)
        result = sj.estimator_covariance(X.astype(dtype), R, estimator=training_estimator(X.astype(dtype), R, 1e-12))
        x = np.random.default_rng(3).uniform(0.05, 0.9, (5, B)).astype(dtype)
        for matrix in (np.asarray(result.gram), np.asarray(result.residual), *np.asarray(result.prediction_covariance(x))):
            matrix = matrix.astype(np.float64)
            np.testing.assert_allclose(matrix, matrix.T, rtol=0, atol=1e-6 * np.max(np.abs(matrix)))
            assert np.linalg.eigvalsh(matrix).min() > -1e-5 * np.max(np.abs(matrix))

    def test_badly_scaled_responses_keep_their_digits(self, dtype):
        """Bands in units 1e-3 and 1e3 apart: gram scales exactly as (D^-1, 1) gram (D^-1, 1)."""
        X, _, _, clean = linear_targets(seed=4)
        R = clean + np.random.default_rng(4).normal(0, SIGMA_R, clean.shape)
        units = np.where(np.arange(B) % 2 == 0, 1e-3, 1e3)
        W = training_estimator(X, R, 1e-12)
        reference = np.asarray(sj.estimator_covariance(X, R, estimator=W).gram)
        scaled = sj.estimator_covariance(
            (X * units).astype(dtype), R.astype(dtype), estimator=sj.WienerEstimator(W.matrix / units, W.offset)
        )
        d = np.append(1.0 / units, 1.0)
        expected = d[:, None] * reference * d[None, :]
        relative = np.asarray(scaled.gram, np.float64) / expected
        np.testing.assert_allclose(relative, 1.0, rtol=1e-8 if dtype == np.float64 else 1e-2)

    def test_monte_carlo_recovery(self):
        """Refit the near-OLS training estimator on 1000 noisy copies of the reflectances: the
        spread of its estimates at test responses is the prediction covariance, and the
        residual covariance is sigma^2 I."""
        refits = 1000
        X, _, _, clean = linear_targets()
        noisy = clean + np.random.default_rng(5).normal(0, SIGMA_R, (refits, *clean.shape))

        def refit(R):
            estimator = training_estimator(X, R, 1e-12)
            return estimator.matrix, estimator.offset, sj.estimator_covariance(X, R, estimator=estimator).residual

        W, r0, residual = jax.jit(jax.vmap(refit))(jnp.asarray(noisy))
        rng = np.random.default_rng(6)
        x = np.stack([X.mean(axis=0), X[0], rng.uniform(0.05, 0.9, B), np.full(B, 0.95)])
        estimates = np.einsum("kwb,xb->kxw", np.asarray(W), x) + np.asarray(r0)[:, None]
        empirical_std = estimates.std(axis=0, ddof=1)

        one = sj.estimator_covariance(X, noisy[0], estimator=training_estimator(X, noisy[0], 1e-12))
        mean_residual = np.asarray(residual).mean(axis=0)
        predicted = sj.EstimatorCovariance(one.gram, jnp.asarray(mean_residual)).prediction_covariance(x)
        ratio = empirical_std / np.sqrt(np.diagonal(np.asarray(predicted), axis1=-2, axis2=-1))
        assert np.all((ratio > 0.85) & (ratio < 1.15)), (ratio.min(), ratio.max())
        # At the mean training response the leverage is exactly 1/n.
        np.testing.assert_allclose(float(one.prediction_scale(X.mean(axis=0))), 1 / len(X), rtol=1e-10)

        np.testing.assert_allclose(np.diag(mean_residual), SIGMA_R**2, rtol=0.03)
        off_diagonal = mean_residual - np.diag(np.diag(mean_residual))
        assert np.max(np.abs(off_diagonal)) < 0.03 * SIGMA_R**2
        single = np.asarray(one.residual)
        np.testing.assert_allclose(np.mean(np.diag(single)), SIGMA_R**2, rtol=0.1)

    def test_prediction_scale_jit_grad_and_batch(self):
        X, W, r0, clean = linear_targets()
        result = sj.estimator_covariance(X, clean, estimator=sj.WienerEstimator(W, r0))
        gram = np.asarray(result.gram)
        x = np.random.default_rng(7).uniform(0.05, 0.9, (2, 3, B))
        x1 = np.concatenate([x, np.ones((2, 3, 1))], axis=-1)
        expected = np.einsum("...i,ij,...j->...", x1, gram, x1)
        scale = jax.jit(lambda covariance, y: covariance.prediction_scale(y))(result, x)
        assert scale.shape == (2, 3) and result.prediction_covariance(x).shape == (2, 3, 31, 31)
        np.testing.assert_allclose(np.asarray(scale), expected, rtol=1e-10)
        grad = jax.grad(lambda y: result.prediction_scale(y))(jnp.asarray(x[0, 0]))
        np.testing.assert_allclose(np.asarray(grad), 2 * (gram @ x1[0, 0])[:B], rtol=1e-9)
        # float32 responses on a float64 covariance compute in float64 (no implicit promotion).
        assert result.prediction_scale(x.astype(np.float32)).dtype == np.float64

    def test_bad_input_names_the_argument(self):
        X, W, r0, clean = linear_targets(n=40)
        estimator = sj.WienerEstimator(W, r0)
        with pytest.raises(ValueError, match=r"responses: shape \(17, 16\) leaves no degree of freedom.*B \+ 1 = 17"):
            sj.estimator_covariance(X[:17], clean[:17], estimator=estimator)
        with pytest.raises(ValueError, match=r"reflectances: expected shape \(40, 31\)"):
            sj.estimator_covariance(X, clean[:39], estimator=estimator)
        with pytest.raises(ValueError, match=r"responses: expected shape \(n, B\)"):
            sj.estimator_covariance(X[0], clean, estimator=estimator)
        with pytest.raises(ValueError, match=r"estimator: expected shape \(31, 15\)"):
            sj.estimator_covariance(X[:, :15], clean, estimator=estimator)
        with pytest.raises(ValueError, match=r"estimator: expected shape \(31, 16\)"):
            sj.estimator_covariance(X, clean, estimator=W[:30])
        bad = X.copy()
        bad[3, 2] = np.nan
        with pytest.raises(ValueError, match=r"responses: has non-finite values"):
            sj.estimator_covariance(bad, clean, estimator=estimator)
        with pytest.raises(ValueError, match=r"estimator.offset: has non-finite values"):
            sj.estimator_covariance(X, clean, estimator=sj.WienerEstimator(W, r0 * np.inf))
        result = sj.estimator_covariance(X, clean, estimator=estimator)
        with pytest.raises(ValueError, match=r"x: expected shape \(\.\.\., 16\)"):
            result.prediction_covariance(X[:, :15])
