"""Wiener estimation: the training-based and model-based affine estimators, their equations line
by line, recovery of a known system, cross-validation, generalisation to held-out material
families on the simulated camera, dtypes and gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax import estimation, simulated_targets, spectra, wiener_estimation
from spherejax.estimation import _offset_free

from .helpers import gaussian_sensitivity


@pytest.fixture(scope="module")
def sets():
    return spectra.reflectance_sets()


@pytest.fixture(scope="module")
def held_out(sets):
    """Materials the estimators never see in training: TM-30 CES and the RAW to ACES patches."""
    return np.concatenate([sets["CES (TM-30)"], sets["RAW to ACES training"]])


@pytest.fixture(scope="module")
def families():
    """Material family -> (responses, reflectances) through the simulated camera (offset, shot
    and read noise), and the true system behind them."""
    return simulated_targets.family_responses(seed=0), simulated_targets.target_system()


def respond(reflectances, sensitivity, noise, seed, offset=0.0):
    rng = np.random.default_rng(seed)
    v = reflectances @ sensitivity.T + offset
    return v + rng.normal(0.0, noise, v.shape)


def rms(a, b):
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


def with_ones(V):
    return np.concatenate([V, np.ones((len(V), 1))], axis=1)


class TestTrainingBased:
    def test_offset_free_noise_free_limit_is_least_squares(self, sets):
        """offset=False is the offset-free estimator."""
        R = sets["ColorChecker: PMC"]
        V = respond(R, gaussian_sensitivity(), 0.001, seed=0)
        estimator = sj.fit_wiener(V, R, noise_variance=0.0, offset=False)
        expected = np.linalg.lstsq(V, R, rcond=None)[0].T
        np.testing.assert_allclose(np.asarray(estimator.matrix), expected, rtol=1e-7, atol=1e-9)
        np.testing.assert_array_equal(np.asarray(estimator.offset), 0.0)

    def test_noise_free_limit_with_offset_is_least_squares_on_v_and_one(self, sets):
        R = sets["ColorChecker: PMC"]
        V = respond(R, gaussian_sensitivity(), 0.001, seed=0, offset=0.02)
        estimator = sj.fit_wiener(V, R, noise_variance=0.0)
        expected = np.linalg.lstsq(with_ones(V), R, rcond=None)[0].T  # (31, 17)
        np.testing.assert_allclose(np.asarray(estimator.matrix), expected[:, :16], rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(np.asarray(estimator.offset), expected[:, 16], rtol=1e-6, atol=1e-8)

    def test_offset_free_equals_the_wiener_formula(self, sets):
        R = sets["ColorChecker: PMC"]
        V = respond(R, gaussian_sensitivity(), 0.001, seed=0)
        n = len(R)
        sigma2 = 1e-4
        expected = (R.T @ V / n) @ np.linalg.inv(V.T @ V / n + sigma2 * np.eye(16))
        W = sj.fit_wiener(V, R, noise_variance=sigma2, offset=False).matrix
        np.testing.assert_allclose(np.asarray(W), expected, rtol=1e-8)

    def test_with_offset_equals_the_centred_wiener_formula(self, sets):
        """(E2): W = K_rv (K_vv + sigma^2 I)^-1 with covariances, r0 = r_mean - W v_mean."""
        R = sets["ColorChecker: PMC"]
        V = respond(R, gaussian_sensitivity(), 0.001, seed=0, offset=0.01)
        sigma2 = 1e-4
        Vc, Rc = V - V.mean(0), R - R.mean(0)
        W = (Rc.T @ Vc / len(R)) @ np.linalg.inv(Vc.T @ Vc / len(R) + sigma2 * np.eye(16))
        estimator = sj.training_estimator(V, R, sigma2)
        np.testing.assert_allclose(np.asarray(estimator.matrix), W, rtol=1e-8)
        np.testing.assert_allclose(np.asarray(estimator.offset), R.mean(0) - W @ V.mean(0), rtol=1e-8, atol=1e-12)

    def test_leave_one_out_shortcut_equals_refitting(self, sets):
        R = sets["ColorChecker: ColorChecker N Ohta"]
        V = respond(R, gaussian_sensitivity(), 0.005, seed=1)
        candidates = np.array([1e-7, 1e-5, 1e-3])
        shortcut = np.asarray(wiener_estimation.wiener_loo_errors(V, R, candidates))
        for sigma2, fast in zip(candidates, shortcut):
            residuals = []
            for i in range(len(R)):
                keep = np.arange(len(R)) != i
                W = sj.fit_wiener(V[keep], R[keep], noise_variance=sigma2 * len(R) / (len(R) - 1), offset=False).matrix
                residuals.append(R[i] - np.asarray(W) @ V[i])
            assert fast == pytest.approx(np.sqrt(np.mean(np.square(residuals))), rel=1e-8)

    def test_an_offset_on_the_responses_changes_nothing(self, sets, held_out):
        """A residual dark level shifts every response by the same b; the affine estimators
        absorb it exactly, the offset-free form does not."""
        train = np.concatenate([v for k, v in sets.items() if k.startswith(("ColorChecker", "TCS", "VS"))])
        M = gaussian_sensitivity()
        V, V_test = respond(train, M, 0.002, seed=2), respond(held_out, M, 0.002, seed=3)
        b = np.linspace(0.03, 0.005, 16)
        for fit in (
            lambda V_: sj.training_estimator(V_, train, 1e-6),
            lambda V_: sj.model_estimator(V_, train, penalty_weight=1e-4, shrinkage=0.01),
        ):
            np.testing.assert_allclose(
                np.asarray(sj.wiener(V_test + b, fit(V + b))), np.asarray(sj.wiener(V_test, fit(V))), atol=1e-9
            )
        old = lambda V_: sj.fit_wiener(V_, train, noise_variance=1e-6, offset=False)  # noqa: E731
        assert rms(sj.wiener(V_test + b, old(V + b)), held_out) > 1.2 * rms(sj.wiener(V_test, old(V)), held_out)

    @pytest.mark.parametrize("training_set", ["ColorChecker: ColorChecker N Ohta", "ColorChecker: PMC"])
    def test_leave_one_out_picks_a_regulariser_that_generalises(self, sets, held_out, training_set):
        """The offset-free choice: with few targets (24-30), broad filters (FWHM 30 nm)
        and 2 % noise the unregularised fit chases the noise. Over five noise draws the
        leave-one-out choice must be within 5 % of the best grid value for held-out data it
        never saw, and on average at least 10 % better than no regularisation."""
        train = sets[training_set]
        M = gaussian_sensitivity(fwhm_nm=30.0)
        fit = jax.jit(lambda V, R, s2: sj.fit_wiener(V, R, s2, offset=False).matrix)
        gains = []
        for seed in range(5):
            V_train = respond(train, M, 0.02, seed=seed)
            V_test = respond(held_out, M, 0.02, seed=100 + seed)
            chosen, candidates, _ = _offset_free.select_wiener_noise_variance(V_train, train)
            held_out_error = [rms(sj.wiener(V_test, fit(V_train, train, c)), held_out) for c in np.asarray(candidates)]
            error_chosen = rms(sj.wiener(V_test, fit(V_train, train, chosen)), held_out)
            assert error_chosen <= 1.05 * min(held_out_error)
            gains.append(error_chosen / held_out_error[0])  # candidates[0]: effectively none
        assert np.mean(gains) <= 0.9, gains

    def test_jit_and_float32(self, sets, dtype, maybe_jit):
        R = sets["ColorChecker: PMC"]
        V = respond(R, gaussian_sensitivity(), 0.002, seed=6, offset=0.01)
        fit = maybe_jit(sj.training_estimator)
        estimator = fit(V.astype(dtype), R.astype(dtype), 1e-5)
        assert estimator.matrix.shape == (31, 16) and estimator.matrix.dtype == dtype
        assert estimator.offset.shape == (31,) and estimator.offset.dtype == dtype
        reference = sj.training_estimator(V, R, 1e-5)
        tolerance = {np.float32: 2e-4, np.float64: 1e-10}[dtype]
        np.testing.assert_allclose(
            np.asarray(sj.wiener(V, estimator)), np.asarray(sj.wiener(V, reference)), atol=tolerance
        )


class TestModelBased:
    def test_recovers_a_known_sensitivity_and_offset_from_exact_responses(self, sets):
        """(E3) with a vanishing penalty on the 450 shipped spectra (full rank) returns M and b."""
        R = spectra.all_reflectances()
        for M in (gaussian_sensitivity(), simulated_targets.target_system().sensitivity):
            b = np.linspace(0.01, 0.002, 16)
            M_hat, b_hat, noise = sj.estimate_system(R @ M.T + b, R, penalty_weight=1e-12, penalty="ridge")
            np.testing.assert_allclose(np.asarray(M_hat), M, atol=1e-7 * np.abs(M).max())
            np.testing.assert_allclose(np.asarray(b_hat), b, atol=1e-10)
            assert np.all(np.asarray(noise) < 1e-18)

    def test_the_estimator_equations_line_by_line(self, sets):
        """(E6-E7) against numpy, with a full noise covariance and an offset."""
        rng = np.random.default_rng(0)
        R = sets["RAW to ACES training"]
        M, b = gaussian_sensitivity(), rng.uniform(0.0, 0.02, 16)
        K_n = np.diag(rng.uniform(1e-6, 1e-5, 16)) + 1e-7
        r_mean, K_r = R.mean(0), np.cov(R.T, bias=True)
        W = K_r @ M.T @ np.linalg.inv(M @ K_r @ M.T + K_n)
        estimator = sj.wiener_from_system(M, b, K_n, r_mean, K_r)
        np.testing.assert_allclose(np.asarray(estimator.matrix), W, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(np.asarray(estimator.offset), r_mean - W @ (M @ r_mean + b), rtol=1e-7, atol=1e-10)
        diagonal = sj.wiener_from_system(M, b, np.diag(K_n), r_mean, K_r)
        np.testing.assert_allclose(
            np.asarray(diagonal.matrix),
            K_r @ M.T @ np.linalg.inv(M @ K_r @ M.T + np.diag(np.diag(K_n))), rtol=1e-7, atol=1e-9,
        )

    def test_fit_with_known_sensitivity_follows_the_equations(self, sets):
        """model_estimator(sensitivity=M): b = v_mean - M r_mean, K_n the per-band residual
        variance, K_r (E5) with the Markov prior."""
        R = sets["RAW to ACES training"]
        M = gaussian_sensitivity()
        V = respond(R, M, 0.003, seed=4, offset=0.01)
        s = 0.1
        estimator = sj.model_estimator(V, R, sensitivity=M, shrinkage=s)
        n = len(R)
        r_mean, v_mean = R.mean(0), V.mean(0)
        b = v_mean - M @ r_mean
        residual = (V - v_mean) - (R - r_mean) @ M.T
        K_n = np.diag(np.sum(residual**2, axis=0) / (n - 1))
        covariance = np.cov(R.T, bias=True)
        i = np.arange(31)
        K_r = (1 - s) * covariance + s * np.trace(covariance) / 31 * 0.99 ** np.abs(i[:, None] - i[None])
        W = K_r @ M.T @ np.linalg.inv(M @ K_r @ M.T + K_n)
        np.testing.assert_allclose(np.asarray(estimator.matrix), W, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(np.asarray(estimator.offset), r_mean - W @ (M @ r_mean + b), atol=1e-9)

    def test_noise_free_with_training_correlation_matches_training_based(self, sets):
        """The offset-free wiener_from_sensitivity: uncentred, no offset."""
        train = np.concatenate([v for k, v in sets.items() if k.startswith("ColorChecker")])
        M = gaussian_sensitivity()
        W_model = np.asarray(_offset_free.wiener_from_sensitivity(M, train, noise_variance=0.0))
        W_train = np.asarray(sj.fit_wiener(train @ M.T, train, noise_variance=0.0, offset=False).matrix)
        np.testing.assert_allclose(W_model, W_train, rtol=1e-6, atol=1e-8)

    def test_markov_prior_without_examples(self, held_out):
        M = gaussian_sensitivity()
        W = _offset_free.wiener_from_sensitivity(M, None, noise_variance=0.002**2)
        estimate = np.asarray(sj.wiener(respond(held_out, M, 0.002, seed=8), W))
        assert rms(estimate, held_out) < 0.01

    def test_estimated_noise_is_the_cameras(self, families):
        """K_n from the residuals of (E3) on 190 targets is the simulated camera's noise plus
        what the 31-sample model cannot represent: within a factor 3 of the truth per band."""
        (V, R), truth = families[0]["RAW to ACES"], families[1]
        _, b_hat, noise = sj.estimate_system(V, R)
        true_noise = truth.noise_variance(R)
        ratio = np.asarray(noise) / true_noise
        assert np.all(ratio > 0.7) and np.all(ratio < 3.0), ratio
        np.testing.assert_allclose(np.asarray(b_hat), truth.offset, atol=0.004)


class TestCrossValidation:
    def test_groups_are_held_out_in_turn(self):
        labels, text = wiener_estimation.fold_labels(np.ones((6, 31)), groups=["a", "b", "a", "c", "b", "c"])
        np.testing.assert_array_equal(labels, [0, 1, 0, 2, 1, 2])
        assert "3 groups" in text

    def test_folds_gather_alike_spectra(self, sets):
        """Without groups the folds are spectral clusters: a fold holds alike targets, so a
        held-out fold is a colour region the rest does not cover."""
        R = sets["RAW to ACES training"]
        labels, _ = wiener_estimation.fold_labels(R, folds=5)
        assert sorted(np.unique(labels)) == [0, 1, 2, 3, 4]
        shape = R / R.mean(axis=1, keepdims=True)
        within = np.mean([np.var(shape[labels == k], axis=0).sum() for k in range(5)])
        assert within < 0.5 * np.var(shape, axis=0).sum()

    def test_reported_errors_are_those_of_refitting_each_fold(self, sets):
        R = np.concatenate([sets["CES (TM-30)"], sets["TCS: CIE 2024"]])
        V = respond(R, gaussian_sensitivity(), 0.003, seed=9, offset=0.01)
        groups = ["CES"] * 99 + ["TCS"] * 15
        estimator = sj.fit_wiener(V, R, method="training", groups=groups)
        (report,) = estimator.cross_validation
        sigma2 = dict(report.settings)["noise_variance"]
        estimates = np.empty_like(R)
        for group in ("CES", "TCS"):
            held = np.asarray(groups) == group
            estimates[held] = np.asarray(sj.wiener(V[held], sj.training_estimator(V[~held], R[~held], sigma2)))
        assert report.spectral_rms == pytest.approx(rms(estimates, R), rel=1e-6)
        de = np.asarray(sj.delta_e_2000(sj.reflectance_to_lab(estimates), sj.reflectance_to_lab(R)))
        assert report.delta_e_d65 == pytest.approx(float(np.mean(de)), rel=1e-6)
        assert report.folds == "leave one group out (2 groups)"

    def test_auto_reports_every_method_and_applies_the_best(self, families):
        """Every method is reported with its held-out errors, the chosen one first: the affine
        methods on the k-means folds, the best of them the estimator's affine part, and the kernel
        estimator on it (99 targets: more than KERNEL_MIN_TARGETS), taken exactly when its gain
        and paired z pass KERNEL_MIN_GAIN and KERNEL_MIN_Z; the local method last, on the
        kernel's folds, reported only; every report with its cost per pixel."""
        V, R = families[0]["TM-30 CES"]
        assert len(V) >= estimation.KERNEL_MIN_TARGETS
        estimator = sj.fit_wiener(V, R)
        reports = {c.method: c for c in estimator.cross_validation}
        assert set(reports) == {"training", "model", "kernel", "local"} and len(estimator.cross_validation) == 4
        assert estimator.cross_validation[-1].method == "local"  # reported, never taken
        assert reports["local"].folds == reports["kernel"].folds
        assert all(dict(c.settings)["cost_per_pixel"] >= 31 * V.shape[1] for c in estimator.cross_validation)
        assert estimator.method == estimator.cross_validation[0].method
        for c in estimator.cross_validation:
            assert 0 < c.spectral_rms < 0.05 and 0 < c.delta_e_d65 < 5
        affine_best = min(("training", "model"), key=lambda m: reports[m].spectral_rms)
        kernel = dict(reports["kernel"].settings)
        assert kernel["mean"] == affine_best
        assert reports["kernel"].folds == "5 folds of targets drawn at random (seed 0)"
        taken = kernel["gain"] >= estimation.KERNEL_MIN_GAIN and kernel["paired_z"] >= estimation.KERNEL_MIN_Z
        assert (estimator.method == "kernel") == taken
        mean = estimator.affine if taken else estimator
        assert mean.method == affine_best
        again = {"training": sj.fit_wiener(V, R, method="training"), "model": sj.fit_wiener(V, R, method="model")}
        np.testing.assert_array_equal(np.asarray(mean.matrix), np.asarray(again[affine_best].matrix))


def held_out_family_table(families):
    """family -> (rms of auto, of the offset-free form, of the oracle), each trained on
    the other three families and applied to this one."""
    data, truth = families
    table = {}
    for family in data:
        V = np.concatenate([data[f][0] for f in data if f != family])
        R = np.concatenate([data[f][1] for f in data if f != family])
        V_test, R_test = data[family]
        auto = sj.fit_wiener(V, R)
        first_release = sj.fit_wiener(V, R, _offset_free.select_wiener_noise_variance(V, R)[0], offset=False)
        oracle = sj.wiener_from_system(
            truth.sensitivity, truth.offset, truth.noise_variance(R), R.mean(0), np.cov(R.T, bias=True)
        )
        table[family] = tuple(rms(sj.wiener(V_test, e), R_test) for e in (auto, first_release, oracle))
    return table


class TestAcrossMaterials:
    @pytest.mark.slow
    def test_held_out_families(self, families):
        """Each material family held out in turn (ColorChecker, TCS/CQS, TM-30 CES, RAW to ACES):
        the default estimator does at least as well as the offset-free training form and
        within 10 % of the oracle built from the simulator's true sensitivity and noise."""
        for family, (auto, first_release, oracle) in held_out_family_table(families).items():
            assert auto <= first_release, (family, auto, first_release)
            assert auto <= 1.10 * oracle, (family, auto, oracle)

    @pytest.mark.slow
    def test_train_on_one_family_apply_to_each(self, families):
        """The acceptance protocol's shape: fit on one family with the defaults, apply to every
        family; the default is never worse than the offset-free form, and within 10 % of the
        oracle on at least 14 of the 16 pairs."""
        data, truth = families
        within = 0
        for train in data:
            V, R = data[train]
            auto = sj.fit_wiener(V, R)
            first_release = sj.fit_wiener(V, R, _offset_free.select_wiener_noise_variance(V, R)[0], offset=False)
            oracle = sj.wiener_from_system(truth.sensitivity, truth.offset, truth.noise_variance(R), R.mean(0), np.cov(R.T, bias=True))
            for test in data:
                V_test, R_test = data[test]
                errors = [rms(sj.wiener(V_test, e), R_test) for e in (auto, first_release, oracle)]
                assert errors[0] <= errors[1], (train, test, errors)
                within += errors[0] <= 1.10 * errors[2]
        assert within >= 14

    def test_float32_follows_float64(self, families):
        V, R = families[0]["RAW to ACES"]
        V_test, R_test = families[0]["TM-30 CES"]
        e64 = sj.fit_wiener(V, R)
        e32 = sj.fit_wiener(V.astype(np.float32), R.astype(np.float32))
        assert e32.matrix.dtype == np.float32 and e32.method == e64.method
        assert rms(np.asarray(sj.wiener(V_test.astype(np.float32), e32), np.float64), R_test) == pytest.approx(
            rms(sj.wiener(V_test, e64), R_test), rel=0.02
        )


class TestGradients:
    @pytest.mark.parametrize(
        "fit",
        [
            lambda V, R: sj.training_estimator(V, R, 1e-5),
            lambda V, R: sj.model_estimator(V, R, penalty_weight=1e-4, shrinkage=0.03),
            lambda V, R: sj.model_estimator(V, R, penalty_weight=1e-3, shrinkage=0.0, penalty="smooth"),
        ],
        ids=["training", "model-ridge", "model-smooth"],
    )
    def test_finite_and_equal_to_finite_differences(self, sets, fit):
        """d(held-out error)/d(training responses): what a differentiable calibration study uses."""
        R = sets["ColorChecker: PMC"]
        V = respond(R, gaussian_sensitivity(), 0.003, seed=11, offset=0.01)
        R_test = sets["TCS: CIE 2024"]
        V_test = respond(R_test, gaussian_sensitivity(), 0.003, seed=12, offset=0.01)

        def loss(V_train):
            return jnp.mean((sj.wiener(V_test, fit(V_train, R)) - R_test) ** 2)

        gradient = np.asarray(jax.grad(loss)(jnp.asarray(V)))
        assert np.all(np.isfinite(gradient))
        direction = np.random.default_rng(0).normal(size=V.shape)
        h = 1e-6
        numeric = (float(loss(V + h * direction)) - float(loss(V - h * direction))) / (2 * h)
        assert float(np.sum(gradient * direction)) == pytest.approx(numeric, rel=1e-4)

    def test_gradient_through_apply(self):
        estimator = sj.WienerEstimator(jnp.asarray(np.random.default_rng(0).normal(size=(31, 16))), jnp.ones(31))
        v = jnp.ones((5, 16))
        grad = jax.grad(lambda e: jnp.sum(sj.wiener(v, e)))(estimator)
        np.testing.assert_allclose(np.asarray(grad.matrix), 5.0)
        np.testing.assert_allclose(np.asarray(grad.offset), 5.0)


class TestApply:
    def test_n_dimensional(self, dtype):
        W = np.random.default_rng(0).normal(size=(31, 16)).astype(dtype)
        v = np.random.default_rng(1).uniform(size=(2, 3, 4, 16)).astype(dtype)
        out = sj.wiener(v, W)
        assert out.shape == (2, 3, 4, 31) and out.dtype == dtype
        np.testing.assert_allclose(np.asarray(out), v @ W.T, rtol=1e-5, atol=1e-5)

    def test_estimator_adds_its_offset(self, dtype):
        W = np.random.default_rng(0).normal(size=(31, 16)).astype(dtype)
        r0 = np.random.default_rng(1).normal(size=31).astype(dtype)
        v = np.random.default_rng(2).uniform(size=(3, 4, 16)).astype(dtype)
        out = sj.wiener(v, sj.WienerEstimator(jnp.asarray(W), jnp.asarray(r0)))
        np.testing.assert_allclose(np.asarray(out), v @ W.T + r0, rtol=1e-5, atol=1e-5)

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

    def test_identical_responses_cannot_determine_an_estimator(self, sets):
        R = sets["ColorChecker: PMC"]
        with pytest.raises(ValueError, match="responses: all 30 targets give the same response"):
            sj.fit_wiener(np.full((30, 16), 0.5), R)

    def test_identical_reflectances_cannot_determine_an_estimator(self):
        V = np.random.default_rng(0).uniform(size=(30, 16))
        with pytest.raises(ValueError, match="reflectances: all 30 targets have the same reflectance"):
            sj.fit_wiener(V, np.full((30, 31), 0.4))

    def test_non_finite_target(self, sets):
        R = sets["ColorChecker: PMC"]
        V = respond(R, gaussian_sensitivity(), 0.0, seed=0)
        V[7, 3] = np.nan
        with pytest.raises(ValueError, match="responses: target 7 has a non-finite value"):
            sj.fit_wiener(V, R)

    def test_unknown_method(self):
        with pytest.raises(ValueError, match=r"method: expected one of \('auto', 'training', 'model', 'kernel'\), got 'wiener'"):
            sj.fit_wiener(np.eye(16), np.ones((16, 31)), method="wiener")

    def test_noise_variance_with_model(self):
        with pytest.raises(ValueError, match="noise_variance: applies to the training form"):
            sj.fit_wiener(np.eye(16), np.ones((16, 31)), 1e-4, method="model")

    def test_one_group(self, sets):
        R = sets["ColorChecker: PMC"]
        V = respond(R, gaussian_sensitivity(), 0.001, seed=0)
        with pytest.raises(ValueError, match=r"groups: all 30 targets are in one group \('paper'\)"):
            sj.fit_wiener(V, R, groups=["paper"] * 30)

    def test_groups_shape(self, sets):
        R = sets["ColorChecker: PMC"]
        V = respond(R, gaussian_sensitivity(), 0.001, seed=0)
        with pytest.raises(ValueError, match=r"groups: expected one label per target, shape \(30,\), got \(29,\)"):
            sj.fit_wiener(V, R, groups=["a", "b"] * 14 + ["a"])

    def test_traced_auto_fit_is_refused(self, sets):
        R = sets["ColorChecker: PMC"]
        V = respond(R, gaussian_sensitivity(), 0.001, seed=0)
        with pytest.raises(ValueError, match="needs concrete data"):
            jax.jit(lambda V: sj.fit_wiener(V, R).matrix)(V)

    def test_sensitivity_shape(self):
        with pytest.raises(ValueError, match=r"sensitivity: expected shape \(B, 31\).*got \(31, 16\)"):
            _offset_free.wiener_from_sensitivity(np.ones((31, 16)))
        with pytest.raises(ValueError, match=r"sensitivity: expected shape \(16, 31\).*got \(16, 30\)"):
            sj.model_estimator(np.eye(16), np.ones((16, 31)), sensitivity=np.ones((16, 30)))

    def test_model_regularisers(self):
        with pytest.raises(ValueError, match=r"shrinkage: expected a value in \[0, 1\], got 1.5"):
            sj.model_estimator(np.eye(16), np.ones((16, 31)), shrinkage=1.5)
        with pytest.raises(ValueError, match=r"penalty: expected one of \('ridge', 'smooth'\), got 'lasso'"):
            sj.model_estimator(np.eye(16), np.ones((16, 31)), penalty="lasso")

    def test_wiener_matrix_shape(self):
        with pytest.raises(ValueError, match=r"W: expected shape \(31, B\).*got \(16, 31\)"):
            sj.wiener(np.ones((4, 16)), np.ones((16, 31)))
        with pytest.raises(ValueError, match=r"W: expected shape \(31, 16\).*got \(31, 8\)"):
            sj.wiener(np.ones((4, 16)), np.ones((31, 8)))

    def test_empty_candidate_grid(self):
        with pytest.raises(ValueError, match="noise_variances: expected a non-empty 1-D array"):
            _offset_free.select_wiener_noise_variance(np.eye(16), np.ones((16, 31)), np.array([]))
