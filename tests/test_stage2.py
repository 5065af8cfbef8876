"""Stage II: the polynomial of Eq. 23 and its closed-form fit (Eq. 19-22)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj

from spherejax.polynomial import CONVERGED, MAX_STEPS, STATUS_NAMES, UNDETERMINED, fit_stage2_detailed

from .helpers import TABLE_2

B = 16


def training_set(n_patches=9, n_backgrounds=10, seed=0):
    """(v, p) like the paper's training data: 9 grey patches x 10 backgrounds, (90, 16) each."""
    rng = np.random.default_rng(seed)
    grey = np.linspace(0.05, 0.9, n_patches)[:, None, None]
    p = rng.uniform(0.95, 1.25, (1, n_backgrounds, B))  # darker backgrounds -> larger p
    v = grey / p * rng.uniform(0.97, 1.03, (n_patches, n_backgrounds, B))
    p = np.broadcast_to(p, v.shape)
    return v.reshape(-1, B), p.reshape(-1, B)


class TestStage2:
    def test_identity_coefficients_are_stage1(self, dtype, maybe_jit):
        v, p = training_set()
        out = maybe_jit(sj.stage2)(v.astype(dtype), p.astype(dtype), sj.identity_coeffs(B, dtype))
        assert out.dtype == dtype
        np.testing.assert_allclose(np.asarray(out), np.asarray(sj.stage1(v, p)), rtol=1e-6)

    def test_equation_23_with_table_2(self):
        v, p = training_set()
        c1, c2, c3, c4 = TABLE_2.T
        expected = (c1 * p + c2) * v + c3 * p + c4
        np.testing.assert_allclose(np.asarray(sj.stage2(v, p, TABLE_2)), expected, rtol=1e-14)

    def test_p_per_image_broadcasts_over_pixels(self):
        v = np.random.default_rng(1).uniform(0.1, 0.9, (2, 4, 5, B))
        p = np.array([1.1, 0.95])[:, None, None, None] * np.ones((2, 1, 1, B))
        out = np.asarray(sj.stage2(v, p, TABLE_2))
        np.testing.assert_allclose(out[1, 2, 3], np.asarray(sj.stage2(v[1, 2, 3], p[1, 0, 0], TABLE_2)))

    def test_gradient_with_respect_to_coefficients(self):
        v, p = training_set()
        grad = jax.grad(lambda c: jnp.sum(sj.stage2(v, p, c) ** 2))(jnp.asarray(TABLE_2))
        # d/dc of sum((Mc)^2) = 2 M^T M c per band: check band 0 by hand.
        M = np.column_stack([p[:, 0] * v[:, 0], v[:, 0], p[:, 0], np.ones(len(v))])
        np.testing.assert_allclose(np.asarray(grad)[0], 2 * M.T @ M @ TABLE_2[0], rtol=1e-12)


class TestFitStage2:
    def test_recovers_table_2_from_exact_data(self, maybe_jit):
        """Zou et al. Table 2 coefficients come back to 1e-6 from noise-free data (float64)."""
        v, p = training_set()
        target = np.asarray(sj.stage2(v, p, TABLE_2))
        fitted = np.asarray(maybe_jit(sj.fit_stage2)(v, p, target))
        assert fitted.shape == (B, 4)
        np.testing.assert_allclose(fitted, TABLE_2, rtol=0, atol=1e-6)

    def test_float32(self):
        v, p = training_set()
        target = np.asarray(sj.stage2(v, p, TABLE_2))
        fitted = sj.fit_stage2(v.astype(np.float32), p.astype(np.float32), target.astype(np.float32))
        assert fitted.dtype == np.float32
        # The p⊙v and v columns are nearly collinear (p ~ 1), so float32 loses about three digits.
        np.testing.assert_allclose(np.asarray(fitted), TABLE_2, atol=2e-3)
        prediction = np.asarray(sj.stage2(v, p, np.asarray(fitted, np.float64)))
        np.testing.assert_allclose(prediction, target, atol=2e-5)

    def test_matches_per_band_numpy_least_squares_on_noisy_data(self):
        v, p = training_set(seed=3)
        rng = np.random.default_rng(3)
        target = np.asarray(sj.stage2(v, p, TABLE_2)) + rng.normal(0, 0.003, v.shape)
        fitted = np.asarray(sj.fit_stage2(v, p, target))
        for band in range(B):
            M = np.column_stack([p[:, band] * v[:, band], v[:, band], p[:, band], np.ones(len(v))])
            expected = np.linalg.lstsq(M, target[:, band], rcond=None)[0]
            np.testing.assert_allclose(fitted[band], expected, rtol=1e-9, atol=1e-12)

    def test_non_finite_samples_are_dropped(self):
        v, p = training_set()
        target = np.asarray(sj.stage2(v, p, TABLE_2))
        v_bad, target_bad = v.copy(), target.copy()
        v_bad[3, 2] = np.nan
        target_bad[10, 2] = np.inf
        fitted = np.asarray(sj.fit_stage2(v_bad, p, target_bad))
        np.testing.assert_allclose(fitted, TABLE_2, atol=1e-6)

    def test_band_without_enough_samples_is_nan_others_fine(self):
        v, p = training_set()
        target = np.asarray(sj.stage2(v, p, TABLE_2))
        v = v.copy()
        v[3:, 7] = np.nan  # 3 usable samples left in band 7
        with pytest.raises(ValueError, match=r"band\(s\) \[7\] cannot be fitted: band 7 has only 3 finite samples"):
            sj.fit_stage2(v, p, target)
        fit = fit_stage2_detailed(v, p, target)
        assert np.asarray(fit.status)[7] == UNDETERMINED and np.isnan(np.asarray(fit.coeffs)[7]).all()
        np.testing.assert_allclose(np.delete(np.asarray(fit.coeffs), 7, axis=0), np.delete(TABLE_2, 7, axis=0), atol=1e-6)

    @pytest.mark.parametrize("loss", ["l2", "huber", "cauchy", "tukey"])
    def test_one_background_is_refused_not_nan(self, loss):
        """A constant p (one background) makes the columns (pv, v) and (p, 1) collinear: the
        closed form would return NaN coefficients silently."""
        v, p = training_set()
        p = p.copy()
        p[:, 4] = 1.1
        target = np.asarray(sj.stage2(v, p, TABLE_2))
        with pytest.raises(ValueError, match=r"band\(s\) \[4\] cannot be fitted: band 4 has p is 1.1 in every sample \(one background only\?\)"):
            sj.fit_stage2(v, p, target, loss=loss)
        fit = fit_stage2_detailed(v, p, target, loss)
        assert fit.problems() == {4: STATUS_NAMES[UNDETERMINED]}
        assert np.isfinite(np.delete(np.asarray(fit.coeffs), 4, axis=0)).all()

    def test_identical_samples_are_refused_not_nan(self):
        v = np.full((90, B), 0.4)
        p = np.tile(np.linspace(1.0, 1.2, 90)[:, None], (1, B))
        with pytest.raises(ValueError, match=r"band\(s\) \[0, 1, .*15\] cannot be fitted: band 0 has v is 0.4 in every sample"):
            sj.fit_stage2(v, p, p * v)

    def test_traced_fit_flags_instead_of_raising(self):
        v, p = training_set()
        p = p.copy()
        p[:, 4] = 1.1
        target = np.asarray(sj.stage2(v, p, TABLE_2))
        coeffs = jax.jit(sj.fit_stage2)(v, p, target)
        assert np.isnan(np.asarray(coeffs)[4]).all()


ROBUST = ["huber", "cauchy", "tukey"]


def with_gross_outliers(target, fraction=0.1, seed=0):
    """`fraction` of the samples get errors of 0.1-0.3 in every band (a patch over a crease,
    a mislabelled capture): 50-150 times the 0.002 noise."""
    rng = np.random.default_rng(seed)
    dirty = target.copy()
    rows = rng.choice(len(target), int(round(fraction * len(target))), replace=False)
    dirty[rows] += rng.choice([-1.0, 1.0], (len(rows), B)) * rng.uniform(0.1, 0.3, (len(rows), B))
    return dirty


@pytest.fixture(scope="module")
def data():
    """Training-like data from Table 2 with 0.002 noise, and its closed-form ("clean") fit."""
    v, p = training_set(seed=0)
    clean = np.asarray(sj.stage2(v, p, TABLE_2)) + np.random.default_rng(1).normal(0, 0.002, v.shape)
    return v, p, clean, np.asarray(sj.fit_stage2(v, p, clean))


class TestRobustFits:
    @pytest.mark.parametrize("loss", ROBUST)
    def test_ten_percent_gross_outliers(self, data, loss):
        """Robust fits land at least 5 times closer to the clean-data fit than the closed form."""
        v, p, clean, clean_fit = data
        dirty = with_gross_outliers(clean)
        l2_error = np.linalg.norm(np.asarray(sj.fit_stage2(v, p, dirty)) - clean_fit)
        fit = fit_stage2_detailed(v, p, dirty, loss)
        robust_error = np.linalg.norm(np.asarray(fit.coeffs) - clean_fit)
        assert robust_error * 5 < l2_error, (robust_error, l2_error)
        assert np.all(np.asarray(fit.status) == CONVERGED)
        assert np.all(np.asarray(fit.steps) > 1)

    @pytest.mark.parametrize("loss", ROBUST)
    def test_clean_data_agrees_with_the_closed_form(self, loss):
        """On clean data every loss gives the closed form: exactly on model data, and within
        1e-4 in prediction with the noise of a 35 x 35 px average (1e-4)."""
        v, p = training_set(seed=2)
        exact = np.asarray(sj.stage2(v, p, TABLE_2))
        np.testing.assert_allclose(np.asarray(sj.fit_stage2(v, p, exact, loss)), TABLE_2, atol=1e-4)
        noisy = exact + np.random.default_rng(3).normal(0, 1e-4, v.shape)
        robust, l2 = (np.asarray(sj.fit_stage2(v, p, noisy, name)) for name in (loss, "l2"))
        np.testing.assert_allclose(np.asarray(sj.stage2(v, p, robust)), np.asarray(sj.stage2(v, p, l2)), atol=1e-4)

    @pytest.mark.parametrize("loss", ROBUST)
    def test_float32_and_jit(self, data, loss, maybe_jit):
        v, p, clean, clean_fit = data
        dirty = with_gross_outliers(clean).astype(np.float32)
        fit = maybe_jit(fit_stage2_detailed, static_argnames=("loss",))(v.astype(np.float32), p.astype(np.float32), dirty, loss=loss)
        assert fit.coeffs.dtype == np.float32
        prediction = np.asarray(sj.stage2(v, p, np.asarray(fit.coeffs, np.float64)))
        np.testing.assert_allclose(prediction, np.asarray(sj.stage2(v, p, clean_fit)), atol=3e-3)

    def test_fixed_scale(self, data):
        v, p, clean, clean_fit = data
        fit = fit_stage2_detailed(v, p, with_gross_outliers(clean), "huber", scale=0.002)
        np.testing.assert_allclose(np.asarray(fit.scale), 0.002)
        assert np.linalg.norm(np.asarray(fit.coeffs) - clean_fit) < 0.2
        estimated = fit_stage2_detailed(v, p, with_gross_outliers(clean), "huber")
        # MAD of the residuals: close to the 0.002 noise, not inflated by the outliers.
        assert np.all((np.asarray(estimated.scale) > 0.001) & (np.asarray(estimated.scale) < 0.004))

    def test_per_band_status_and_dropped_counts(self, data):
        v, p, clean, _ = data
        v = v.copy()
        v[:88, 3] = np.nan  # band 3: 2 usable samples left
        v[5, 9] = np.inf  # band 9: one dropped
        fit = fit_stage2_detailed(v, p, with_gross_outliers(clean), "cauchy")
        status = np.asarray(fit.status)
        assert status[3] == UNDETERMINED and np.isnan(np.asarray(fit.coeffs)[3]).all()
        assert np.all(np.delete(status, 3) == CONVERGED)
        dropped = np.asarray(fit.dropped)
        assert dropped[3] == 88 and dropped[9] == 1 and dropped[0] == 0
        assert fit.problems() == {3: STATUS_NAMES[UNDETERMINED]}

    def test_max_steps_is_reported_not_raised(self, data):
        v, p, clean, _ = data
        fit = fit_stage2_detailed(v, p, with_gross_outliers(clean), "tukey", max_steps=2)
        assert np.all(np.asarray(fit.status) == MAX_STEPS)
        assert np.isfinite(np.asarray(fit.coeffs)).all()

    def test_l2_detailed(self, data):
        v, p, clean, clean_fit = data
        fit = fit_stage2_detailed(v, p, clean)
        np.testing.assert_array_equal(np.asarray(fit.coeffs), clean_fit)
        assert np.all(np.asarray(fit.status) == CONVERGED) and np.all(np.asarray(fit.steps) == 0)


class TestBadInput:
    def test_all_nan_band(self):
        v, p = training_set()
        v = v.copy()
        v[:, 6] = np.nan
        with pytest.raises(ValueError, match=r"v, p, target: band\(s\) \[6\] have no finite sample"):
            sj.fit_stage2(v, p, v, loss="huber")

    @pytest.mark.parametrize("scale", [0.0, -0.01, [0.01] * 15 + [0.0]])
    def test_non_positive_scale(self, scale):
        v, p = training_set()
        with pytest.raises(ValueError, match="scale: expected a residual scale > 0"):
            sj.fit_stage2(v, p, v, loss="huber", scale=scale)

    def test_scale_shape(self):
        v, p = training_set()
        with pytest.raises(ValueError, match=r"scale: expected a number or shape \(16,\)"):
            sj.fit_stage2(v, p, v, loss="cauchy", scale=np.ones(4))

    def test_max_steps(self):
        v, p = training_set()
        with pytest.raises(ValueError, match="max_steps: expected a positive integer, got 0"):
            sj.fit_stage2(v, p, v, loss="tukey", max_steps=0)

    def test_unknown_loss(self):
        v, p = training_set()
        with pytest.raises(ValueError, match=r"loss: unknown loss 'l3'; expected one of \['l2', 'huber', 'cauchy', 'tukey'\]"):
            sj.fit_stage2(v, p, v, loss="l3")

    def test_target_shape(self):
        v, p = training_set()
        with pytest.raises(ValueError, match=r"target: expected shape \(90, 16\).*got \(90, 15\)"):
            sj.fit_stage2(v, p, v[:, :15])

    def test_p_shape(self):
        v, p = training_set()
        with pytest.raises(ValueError, match=r"p: expected shape \(90, 16\).*got \(89, 16\)"):
            sj.fit_stage2(v, p[:89], v)

    def test_v_rank(self):
        with pytest.raises(ValueError, match=r"v: expected shape \(n, B\).*got \(90,\)"):
            sj.fit_stage2(np.ones(90), np.ones(90), np.ones(90))

    def test_too_few_samples(self):
        v, p = training_set()
        with pytest.raises(ValueError, match="v: 3 samples cannot determine the 4 coefficients"):
            sj.fit_stage2(v[:3], p[:3], v[:3])

    def test_coeffs_shape(self):
        v, p = training_set()
        with pytest.raises(ValueError, match=r"coeffs: expected shape \(16, 4\).*got \(4, 16\)"):
            sj.stage2(v, p, TABLE_2.T)

    def test_p_band_count(self):
        v, p = training_set()
        with pytest.raises(ValueError, match=r"p: expected shape \(\.\.\., 16\).*got \(90, 8\)"):
            sj.stage2(v, p[:, :8], TABLE_2)
