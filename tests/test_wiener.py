"""Wiener estimation: the training-based form with cross-validated regularisation, the
model-based form, and generalisation to spectra outside the training set."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax import spectra, wiener_estimation

from .helpers import gaussian_sensitivity


@pytest.fixture(scope="module")
def sets():
    return spectra.reflectance_sets()


@pytest.fixture(scope="module")
def held_out(sets):
    """Materials the estimators never see in training: TM-30 CES and the RAW to ACES patches."""
    return np.concatenate([sets["CES (TM-30)"], sets["RAW to ACES training"]])


def respond(reflectances, sensitivity, noise, seed):
    rng = np.random.default_rng(seed)
    v = reflectances @ sensitivity.T
    return v + rng.normal(0.0, noise, v.shape)


def rms(a, b):
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


class TestTrainingBased:
    def test_noise_free_limit_is_least_squares(self, sets):
        R = sets["ColorChecker: PMC"]
        V = respond(R, gaussian_sensitivity(), 0.001, seed=0)
        W = np.asarray(sj.fit_wiener(V, R, noise_variance=0.0))
        expected = np.linalg.lstsq(V, R, rcond=None)[0].T
        np.testing.assert_allclose(W, expected, rtol=1e-7, atol=1e-9)

    def test_equals_the_wiener_formula(self, sets):
        R = sets["ColorChecker: PMC"]
        V = respond(R, gaussian_sensitivity(), 0.001, seed=0)
        n = len(R)
        sigma2 = 1e-4
        expected = (R.T @ V / n) @ np.linalg.inv(V.T @ V / n + sigma2 * np.eye(16))
        np.testing.assert_allclose(np.asarray(sj.fit_wiener(V, R, noise_variance=sigma2)), expected, rtol=1e-8)

    def test_leave_one_out_shortcut_equals_refitting(self, sets):
        R = sets["ColorChecker: ColorChecker N Ohta"]
        V = respond(R, gaussian_sensitivity(), 0.005, seed=1)
        candidates = np.array([1e-7, 1e-5, 1e-3])
        shortcut = np.asarray(wiener_estimation.wiener_loo_errors(V, R, candidates))
        for sigma2, fast in zip(candidates, shortcut):
            residuals = []
            for i in range(len(R)):
                keep = np.arange(len(R)) != i
                W = np.asarray(sj.fit_wiener(V[keep], R[keep], noise_variance=sigma2 * len(R) / (len(R) - 1)))
                residuals.append(R[i] - W @ V[i])
            assert fast == pytest.approx(np.sqrt(np.mean(np.square(residuals))), rel=1e-8)

    def test_generalises_to_held_out_materials(self, sets, held_out):
        """Train on ColorCheckers, TCS and CQS samples (161 targets, the paper uses 144); measure
        TM-30 CES and RAW to ACES patches (289) that training never saw."""
        train = np.concatenate([v for k, v in sets.items() if k.startswith(("ColorChecker", "TCS", "VS"))])
        M = gaussian_sensitivity()
        W = sj.fit_wiener(respond(train, M, 0.002, seed=2), train)
        estimate = np.asarray(sj.wiener(respond(held_out, M, 0.002, seed=3), W))
        assert rms(estimate, held_out) < 0.006
        de = np.asarray(sj.delta_e_2000(sj.reflectance_to_lab(estimate), sj.reflectance_to_lab(held_out)))
        assert np.mean(de) < 0.4 and np.percentile(de, 95) < 1.0

    @pytest.mark.parametrize("training_set", ["ColorChecker: ColorChecker N Ohta", "ColorChecker: PMC"])
    def test_cross_validation_picks_a_regulariser_that_generalises(self, sets, held_out, training_set):
        """With few targets (24-30), broad filters (FWHM 30 nm) and 2 % noise the unregularised
        fit chases the noise. Over five noise draws the leave-one-out choice must be within 5 %
        of the best grid value for held-out data it never saw, and on average at least 10 %
        better than no regularisation."""
        train = sets[training_set]
        M = gaussian_sensitivity(fwhm_nm=30.0)
        fit = jax.jit(sj.fit_wiener)
        gains = []
        for seed in range(5):
            V_train = respond(train, M, 0.02, seed=seed)
            V_test = respond(held_out, M, 0.02, seed=100 + seed)
            _, candidates, _ = sj.select_wiener_noise_variance(V_train, train)
            held_out_error = [
                rms(sj.wiener(V_test, fit(V_train, train, c)), held_out) for c in np.asarray(candidates)
            ]
            error_chosen = rms(sj.wiener(V_test, sj.fit_wiener(V_train, train)), held_out)
            assert error_chosen <= 1.05 * min(held_out_error)
            gains.append(error_chosen / held_out_error[0])  # candidates[0]: effectively none
        assert np.mean(gains) <= 0.9, gains

    def test_jit_and_float32(self, sets, dtype, maybe_jit):
        R = sets["ColorChecker: PMC"]
        V = respond(R, gaussian_sensitivity(), 0.002, seed=6)
        fit = maybe_jit(sj.fit_wiener)
        W_fixed = fit(V.astype(dtype), R.astype(dtype), 1e-5)
        assert W_fixed.shape == (31, 16) and W_fixed.dtype == dtype
        tolerance = {np.float32: 1e-3, np.float64: 1e-10}[dtype]
        np.testing.assert_allclose(np.asarray(W_fixed), np.asarray(sj.fit_wiener(V, R, 1e-5)), atol=tolerance)
        # With the cross-validated choice float32 may settle on a neighbouring grid value (the
        # leave-one-out curve is flat near its minimum): compare what matters, the estimates.
        W_cv = fit(V.astype(dtype), R.astype(dtype))
        error = rms(sj.wiener(V, np.asarray(W_cv, np.float64)), R)
        assert error == pytest.approx(rms(sj.wiener(V, sj.fit_wiener(V, R)), R), rel=0.05)


class TestModelBased:
    def test_noise_free_with_training_correlation_matches_training_based(self, sets):
        train = np.concatenate([v for k, v in sets.items() if k.startswith("ColorChecker")])
        M = gaussian_sensitivity()
        W_model = np.asarray(sj.wiener_from_sensitivity(M, train, noise_variance=0.0))
        W_train = np.asarray(sj.fit_wiener(train @ M.T, train, noise_variance=0.0))
        np.testing.assert_allclose(W_model, W_train, rtol=1e-6, atol=1e-8)

    def test_generalises_to_held_out_materials(self, sets, held_out):
        train = np.concatenate([v for k, v in sets.items() if k.startswith(("ColorChecker", "TCS", "VS"))])
        M = gaussian_sensitivity()
        W = sj.wiener_from_sensitivity(M, train, noise_variance=0.002**2)
        estimate = np.asarray(sj.wiener(respond(held_out, M, 0.002, seed=7), W))
        assert rms(estimate, held_out) < 0.006

    def test_markov_prior_without_examples(self, held_out):
        M = gaussian_sensitivity()
        W = sj.wiener_from_sensitivity(M, None, noise_variance=0.002**2)
        estimate = np.asarray(sj.wiener(respond(held_out, M, 0.002, seed=8), W))
        assert rms(estimate, held_out) < 0.01


class TestApply:
    def test_n_dimensional(self, dtype):
        W = np.random.default_rng(0).normal(size=(31, 16)).astype(dtype)
        v = np.random.default_rng(1).uniform(size=(2, 3, 4, 16)).astype(dtype)
        out = sj.wiener(v, W)
        assert out.shape == (2, 3, 4, 31) and out.dtype == dtype
        np.testing.assert_allclose(np.asarray(out), v @ W.T, rtol=1e-5)

    def test_gradient(self):
        W = jnp.asarray(np.random.default_rng(0).normal(size=(31, 16)))
        v = jnp.ones((5, 16))
        grad = jax.grad(lambda w: jnp.sum(sj.wiener(v, w)))(W)
        np.testing.assert_allclose(np.asarray(grad), 5.0)


class TestBadInput:
    def test_reflectance_count_mismatch(self):
        with pytest.raises(ValueError, match=r"reflectances: expected shape \(10, 31\).*got \(9, 31\)"):
            sj.fit_wiener(np.ones((10, 16)), np.ones((9, 31)))

    def test_reflectance_wavelengths(self):
        with pytest.raises(ValueError, match=r"reflectances: expected shape \(10, 31\).*got \(10, 16\)"):
            sj.fit_wiener(np.ones((10, 16)), np.ones((10, 16)))

    def test_responses_rank(self):
        with pytest.raises(ValueError, match=r"responses: expected shape \(n, B\).*got \(16,\)"):
            sj.fit_wiener(np.ones(16), np.ones((16, 31)))

    def test_one_target(self):
        with pytest.raises(ValueError, match="responses: 1 target"):
            sj.fit_wiener(np.ones((1, 16)), np.ones((1, 31)))

    def test_negative_noise(self):
        with pytest.raises(ValueError, match=r"noise_variance: expected a value >= 0, got -1"):
            sj.fit_wiener(np.eye(16), np.ones((16, 31)), noise_variance=-1.0)

    def test_sensitivity_shape(self):
        with pytest.raises(ValueError, match=r"sensitivity: expected shape \(B, 31\).*got \(31, 16\)"):
            sj.wiener_from_sensitivity(np.ones((31, 16)))

    def test_wiener_matrix_shape(self):
        with pytest.raises(ValueError, match=r"W: expected shape \(31, 16\).*got \(16, 31\)"):
            sj.wiener(np.ones((4, 16)), np.ones((16, 31)))

    def test_empty_candidate_grid(self):
        with pytest.raises(ValueError, match="noise_variances: expected a non-empty 1-D array"):
            sj.select_wiener_noise_variance(np.eye(16), np.ones((16, 31)), np.array([]))
