"""Measurement uncertainty (spherejax.uncertainty, correct(..., noise=), spherejax.measure).

Three kinds of check:
- exact: the propagated covariances equal J diag(var) Jᵀ with J the dense Jacobian of the whole
  `correct` (every pixel's Lab with respect to every raw, dark and white count, the Stage II
  coefficients, the estimator's parameters), taken by jax.jacrev in float64: the band-wise
  shortcut of `uncertainty` is the same first-order result, not an approximation of it;
- Monte Carlo (JCGM 101): frames drawn from the noise model on the `monte_carlo` scene, the
  spread of the results against the propagated uncertainties, and the coverage of k = 2;
- the model's own formulas, and bad input.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax import monte_carlo as mc
from spherejax import simulate, uncertainty
from spherejax.polynomial import PAPER_TABLE_2

from .helpers import ON_CPU, tiny_frames

GAIN, READ, FRAMES = 1.2, 5.0, {"dark": 16, "white": 8, "sample": 4}


def _noise(**kwargs):
    return sj.NoiseModel(gain=GAIN, read_noise=READ, dark_frames=FRAMES["dark"], white_frames=FRAMES["white"],
                         sample_frames=FRAMES["sample"], **kwargs)


@pytest.fixture(scope="module")
def scene():
    return mc.noise_scene(block=5)


@pytest.fixture(scope="module")
def tiny():
    """A 6 x 7 float64 image with a 2 x 2 white patch, Table 2's Stage II and a real estimator."""
    rng, scene, raw, dark, white, patch = tiny_frames()
    calibration = sj.Calibration(
        dark=dark, white=white, patch=patch, coeffs=np.asarray(PAPER_TABLE_2, np.float64),
        wiener=scene.wiener, wiener_offset=scene.wiener_offset,
    )
    return raw, calibration


def _lab_of(raw, calibration, **replace):
    return sj.correct(raw, dataclasses.replace(calibration, **replace)).lab


def _dense_covariance(jacobians, variances):
    """Σ_inputs J J var for each pixel: jacobians of Lab (H, W, 3, *input) and the inputs'
    variances (*input) -> (H, W, 3, 3)."""
    total = 0.0
    for jacobian, variance in zip(jacobians, variances):
        flat = jacobian.reshape(*jacobian.shape[:3], -1)
        total = total + jnp.einsum("hwan,hwbn,n->hwab", flat, flat, variance.reshape(-1))
    return total


def test_pixel_noise_equals_dense_jacobian_of_the_whole_path(tiny):
    raw, calibration = tiny
    noise = _noise()
    result = sj.correct(raw, calibration, noise=noise)
    dark, white = calibration.dark, calibration.white
    jac = jax.jacrev(lambda r, d, w: _lab_of(r, calibration, dark=d, white=w), argnums=(0, 1, 2))(raw, dark, white)
    variances = (noise.raw_variance(raw, dark), noise.dark_variance(dark), noise.white_variance(white, dark))
    expected = _dense_covariance(jac, variances)
    outside = ~np.asarray(calibration.patch)  # the patch's own pixels share noise with p: left out
    np.testing.assert_allclose(np.asarray(result.lab_covariance)[outside], np.asarray(expected)[outside], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(result.lab_u), np.sqrt(np.diagonal(np.asarray(result.lab_covariance), axis1=-2, axis2=-1)))

    jac_r = jax.jacrev(lambda r, d, w: sj.correct(r, dataclasses.replace(calibration, dark=d, white=w)).reflectance, argnums=(0, 1, 2))(raw, dark, white)
    expected_r = sum(
        jnp.einsum("hwln,n->hwl", j.reshape(*j.shape[:3], -1) ** 2, v.reshape(-1)) for j, v in zip(jac_r, variances)
    )
    np.testing.assert_allclose(np.asarray(result.reflectance_u)[outside], np.sqrt(np.asarray(expected_r))[outside], rtol=1e-9, atol=1e-12)


def test_patch_ratio_uncertainty_equals_dense_jacobian(tiny):
    raw, calibration = tiny
    noise = _noise()
    dark, white = calibration.dark, calibration.white
    jac = jax.jacrev(lambda r, d, w: sj.patch_ratio(r, dataclasses.replace(calibration, dark=d, white=w)), argnums=(0, 1, 2))(raw, dark, white)
    variances = (noise.raw_variance(raw, dark), noise.dark_variance(dark), noise.white_variance(white, dark))
    expected = sum(jnp.einsum("bn,n->b", j.reshape(j.shape[0], -1) ** 2, v.reshape(-1)) for j, v in zip(jac, variances))
    np.testing.assert_allclose(np.asarray(sj.patch_ratio_u(raw, calibration, noise)), np.sqrt(np.asarray(expected)), rtol=1e-9)


@pytest.mark.slow
def test_systematic_terms_equal_dense_jacobians(tiny):
    """Stage II coefficients (N6), the estimator (N7) and the white standard (N5), each alone."""
    raw, calibration = tiny
    bands = calibration.bands
    rng = np.random.default_rng(5)
    a = rng.normal(size=(bands, 4, 4)) * 1e-3
    coeffs_cov = a @ np.swapaxes(a, 1, 2)
    g = rng.normal(size=(bands + 1, bands + 1)) * 1e-2
    gram = g @ g.T
    s = rng.normal(size=(31, 31)) * 1e-3
    residual = s @ s.T
    white_u = rng.uniform(0.001, 0.004, bands)
    silent = dict(gain=1e12, read_noise=0.0)  # pixel noise off (the gain's shot term ~ 0)
    outside = ~np.asarray(calibration.patch)

    model = sj.NoiseModel(**silent, coeffs_covariance=coeffs_cov)
    got = np.asarray(sj.correct(raw, calibration, noise=model).lab_covariance)
    jac = jax.jacrev(lambda c: _lab_of(raw, calibration, coeffs=c))(calibration.coeffs)  # (H, W, 3, B, 4)
    expected = jnp.einsum("hwabk,bkl,hwcbl->hwac", jac, coeffs_cov, jac)
    np.testing.assert_allclose(got[outside], np.asarray(expected)[outside], rtol=1e-7, atol=1e-14)

    model = sj.NoiseModel(**silent, estimator_covariance=sj.EstimatorCovariance(gram=gram, residual=residual))
    got = np.asarray(sj.correct(raw, calibration, noise=model).lab_covariance)
    theta = jnp.concatenate([calibration.wiener, calibration.wiener_offset[:, None]], axis=1)  # (31, B + 1)
    jac = jax.jacrev(lambda t: _lab_of(raw, calibration, wiener=t[:, :bands], wiener_offset=t[:, bands]))(theta)
    expected = jnp.einsum("hwali,lm,ij,hwcmj->hwac", jac, residual, gram, jac)
    np.testing.assert_allclose(got[outside], np.asarray(expected)[outside], rtol=1e-7, atol=1e-14)

    model = sj.NoiseModel(**silent, white_reflectance_u=white_u)
    got = np.asarray(sj.correct(raw, calibration, noise=model).lab_covariance)
    patch = np.asarray(calibration.patch)[..., None]

    def scaled(delta):  # a white standard (1 + δ) times as reflective scales every flat field
        dark = calibration.dark
        return sj.correct(jnp.where(patch, raw, dark + (raw - dark) * (1.0 + delta)), calibration).lab

    jac = jax.jacrev(scaled)(jnp.zeros(bands))
    expected = jnp.einsum("hwab,b,hwcb->hwac", jac, white_u**2, jac)
    np.testing.assert_allclose(got[outside], np.asarray(expected)[outside], rtol=1e-7, atol=1e-14)


def test_without_noise_nothing_changes(tiny, scene):
    raw, calibration = tiny
    plain = sj.correct(raw, calibration)
    assert plain.reflectance_u is None and plain.lab_u is None and plain.lab_covariance is None and plain.p_u is None
    with_noise = sj.correct(raw, calibration, noise=_noise())
    # Bit for bit on the CPU. On an H100 (jax 0.11.2) XLA fuses the program with the
    # uncertainties differently: float64 values 2.3e-12 apart relative (1.7e-13 absolute);
    # the float32 case below was not reached there, its bound is the GPU kernel's rounding
    # against the jax.numpy path (reflectance 4.8e-7, Lab 1.2e-4, gpu_kernel's docstring).
    rtol64, atol32 = (0.0, 0.0) if ON_CPU else (1e-10, 2e-4)
    np.testing.assert_allclose(np.asarray(plain.reflectance), np.asarray(with_noise.reflectance), rtol=rtol64, atol=0)
    np.testing.assert_allclose(np.asarray(plain.lab), np.asarray(with_noise.lab), rtol=rtol64, atol=0)
    # float32 uint16 through the default (fused) path too
    raw16, calibration32 = scene.draw(np.random.default_rng(0))
    a, b = sj.correct(raw16, calibration32), sj.correct(raw16, calibration32, noise=scene.noise_model())
    np.testing.assert_allclose(np.asarray(a.lab), np.asarray(b.lab), rtol=0, atol=atol32)
    assert b.lab_u.dtype == np.float32 and b.lab_u.shape == a.lab.shape and b.reflectance_u.shape == a.reflectance.shape
    with pytest.raises(ValueError, match="delta_e_u: this result has no uncertainties"):
        a.delta_e_u(np.zeros(3))


def test_frame_variances_follow_the_model():
    noise = sj.NoiseModel(gain=2.0, read_noise=4.0, dark_frames=10, white_frames=5, sample_frames=2)
    raw, dark, white = jnp.array([300.0, 90.0]), jnp.array([100.0, 100.0]), jnp.array([1100.0, 1100.0])
    np.testing.assert_allclose(noise.raw_variance(raw, dark), [(200 / 2 + 16) / 2, 16 / 2])  # signal clipped at 0
    np.testing.assert_allclose(noise.dark_variance(dark), [1.6, 1.6])
    np.testing.assert_allclose(noise.white_variance(white, dark), [(1000 / 2 + 16) / 5] * 2)


def test_strips_give_the_whole_image_uncertainties(scene):
    raw, calibration = scene.draw(np.random.default_rng(1))
    noise = scene.noise_model()
    whole = sj.correct(raw, calibration, noise=noise)
    p, p_u = sj.patch_ratio(raw, calibration), sj.patch_ratio_u(raw, calibration, noise)
    np.testing.assert_array_equal(np.asarray(p_u), np.asarray(whole.p_u))
    strip = sj.correct(raw[7:19], calibration.rows(7, 19), p=p, p_u=p_u, noise=noise)
    np.testing.assert_allclose(np.asarray(strip.lab_u), np.asarray(whole.lab_u)[7:19], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(strip.reflectance_u), np.asarray(whole.reflectance_u)[7:19], rtol=1e-6)
    with pytest.raises(ValueError, match="p_u: expected u\\(p\\)"):
        sj.correct(raw[7:19], calibration.rows(7, 19), p=p, noise=noise)


def test_bad_pixels_are_nan_and_batches_work(scene):
    raw, calibration = scene.draw(np.random.default_rng(2))
    raw = raw.copy()
    raw[12, 13, 4] = scene.saturation
    result = sj.correct(raw, calibration, noise=scene.noise_model())
    assert result.quality[12, 13] != 0
    assert np.all(np.isnan(np.asarray(result.lab_u)[12, 13])) and np.all(np.isnan(np.asarray(result.reflectance_u)[12, 13]))
    good = np.asarray(result.valid)
    assert np.all(np.isfinite(np.asarray(result.lab_u)[good])) and np.all(np.asarray(result.lab_u)[good] > 0)
    batch = sj.correct(np.stack([raw, raw]), calibration, noise=scene.noise_model())
    np.testing.assert_allclose(np.asarray(batch.lab_u[1]), np.asarray(result.lab_u), rtol=1e-6)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(gain=0.0, read_noise=1.0), "gain"),
        (dict(gain=-1.0, read_noise=1.0), "gain"),
        (dict(gain=1.0, read_noise=-1.0), "read_noise"),
        (dict(gain=float("nan"), read_noise=1.0), "gain"),
        (dict(gain=1.0, read_noise=1.0, dark_frames=0), "dark_frames"),
        (dict(gain=1.0, read_noise=1.0, white_frames=[1, 2]), "white_frames"),
        (dict(gain=1.0, read_noise=1.0, white_reflectance_u=-0.1), "white_reflectance_u"),
        (dict(gain=1.0, read_noise=1.0, coeffs_covariance=np.zeros((16, 4))), "coeffs_covariance"),
        (dict(gain=np.ones((2, 2)), read_noise=1.0), "gain"),
        (dict(gain=1.0, read_noise=1.0, estimator_covariance=np.zeros((17, 17))), "estimator_covariance"),
    ],
)
def test_bad_noise_models_raise_one_line(kwargs, match):
    with pytest.raises(ValueError, match=match) as error:
        sj.NoiseModel(**kwargs)
    assert "\n" not in str(error.value)


def test_noise_model_must_fit_the_bands(tiny):
    raw, calibration = tiny
    with pytest.raises(ValueError, match="gain has 3 values, expected one or 16"):
        sj.correct(raw, calibration, noise=sj.NoiseModel(gain=[1.0, 2.0, 3.0], read_noise=1.0))
    with pytest.raises(ValueError, match="coeffs_covariance has shape"):
        sj.correct(raw, calibration, noise=sj.NoiseModel(gain=1.0, read_noise=1.0, coeffs_covariance=np.zeros((3, 4, 4))))
    with pytest.raises(ValueError, match="noise: expected a spherejax.NoiseModel"):
        sj.correct(raw, calibration, noise={"gain": 1.0})


def test_json_round_trip_and_refusals():
    model = sj.NoiseModel(
        gain=np.linspace(1, 2, 16), read_noise=3.5, dark_frames=16, white_frames=8, sample_frames=4,
        white_reflectance_u=0.002, coeffs_covariance=np.eye(4)[None].repeat(16, 0) * 1e-4,
        estimator_covariance=sj.EstimatorCovariance(gram=np.eye(17) * 0.1, residual=np.eye(31) * 1e-5),
    )
    back = sj.NoiseModel.from_json(model.to_json())
    for a, b in zip(jax.tree_util.tree_leaves(model), jax.tree_util.tree_leaves(back)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        assert np.asarray(a).dtype == np.asarray(b).dtype
    with pytest.raises(ValueError, match="unknown key 'gian'"):
        sj.NoiseModel.from_json({"gian": 1.0, "read_noise_counts": 1.0})
    with pytest.raises(ValueError, match="missing 'gain_e_per_count'"):
        sj.NoiseModel.from_json({"read_noise_counts": 1.0})
    with pytest.raises(ValueError, match="gain_e_per_count expected finite numbers"):
        sj.NoiseModel.from_json({"gain_e_per_count": float("inf"), "read_noise_counts": 1.0})
    with pytest.raises(ValueError, match="gain"):
        sj.NoiseModel.from_json({"gain_e_per_count": -1.0, "read_noise_counts": 1.0})
    with pytest.raises(ValueError, match="read_noise_counts is 'loud', expected numbers"):
        sj.NoiseModel.from_json({"gain_e_per_count": 1.0, "read_noise_counts": "loud"})


def test_gradients_of_the_uncertainty_are_finite_and_right(scene):
    """The uncertainty is itself differentiable (planning studies: which gain, how many frames)."""
    raw, calibration = scene.draw(np.random.default_rng(4))

    def mean_u(frames):
        noise = dataclasses.replace(scene.noise_model(), sample_frames=frames)
        return jnp.nanmean(sj.correct(raw, calibration, noise=noise).lab_u[..., 0])

    g = jax.grad(mean_u)(jnp.float32(4.0))
    # u ∝ sqrt(pixel part / frames + common part): d/dframes is negative, and near -u/(2 frames)
    assert np.isfinite(g) and g < 0
    step = 0.05
    numeric = (mean_u(jnp.float32(4.0 + step)) - mean_u(jnp.float32(4.0 - step))) / (2 * step)
    np.testing.assert_allclose(g, numeric, rtol=2e-2)


# ---------------------------------------------------------------------------- Monte Carlo


@pytest.fixture(scope="module")
def monte_carlo_run(scene):
    return mc.run(scene, scene.noise_model(), trials=300, seed=11)


def test_monte_carlo_per_pixel_spread_matches_propagation(scene, monte_carlo_run):
    run = monte_carlo_run
    good = np.all(np.isfinite(run.lab), axis=(0, -1)) & (scene.kind != mc.KIND_PATCH)
    empirical = np.std(run.lab, axis=0, ddof=1)
    propagated = np.median(run.lab_u, axis=0)
    for kind, name in mc.KIND_NAMES.items():
        pixels = good & (scene.kind == kind)
        ratio = np.median(propagated[pixels] / empirical[pixels], axis=0)
        assert np.all(np.abs(ratio - 1) < 0.06), (name, ratio)
    ratio_r = np.median(np.median(run.reflectance_u, axis=0)[good] / np.std(run.reflectance, axis=0, ddof=1)[good])
    assert abs(ratio_r - 1) < 0.05
    # the correlation of L*, a*, b* too: empirical covariance against the propagated one
    pixel = tuple(np.argwhere(good & (scene.kind == mc.KIND_CHART))[7])
    empirical_cov = np.cov(run.lab[:, pixel[0], pixel[1]].T)
    np.testing.assert_allclose(np.median(run.lab_covariance[:, pixel[0], pixel[1]], axis=0), empirical_cov,
                               atol=0.25 * np.sqrt(np.outer(np.diag(empirical_cov), np.diag(empirical_cov))).max())


def test_monte_carlo_coverage_of_k2_is_95_percent(scene, monte_carlo_run):
    run = monte_carlo_run
    good = np.all(np.isfinite(run.lab), axis=(0, -1)) & (scene.kind != mc.KIND_PATCH)
    inside = np.abs(run.lab - run.true_lab)[:, good] <= 2 * run.lab_u[:, good]
    coverage = inside.mean(axis=(0, 1))
    assert np.all(np.abs(coverage - 0.9545) < 0.015), coverage


def test_delta_e_uncertainty_matches_monte_carlo_away_from_zero(scene, monte_carlo_run):
    run = monte_carlo_run
    pixel = tuple(np.argwhere(scene.kind == mc.KIND_CHART)[40])
    lab, cov = run.lab[:, pixel[0], pixel[1]], run.lab_covariance[:, pixel[0], pixel[1]]
    reference = run.true_lab[pixel] + np.array([1.5, -2.0, 1.0])  # ΔE00 of a few units
    de = np.asarray(sj.delta_e_2000(jnp.asarray(lab), jnp.asarray(reference)))
    u = np.asarray(uncertainty.delta_e_uncertainty(jnp.asarray(lab), jnp.asarray(cov), jnp.asarray(reference)))
    assert abs(np.median(u) / np.std(de, ddof=1) - 1) < 0.12
    # near 0 first order breaks down: against the true colour itself, u -> 0 while ΔE00 does not
    de0 = np.asarray(sj.delta_e_2000(jnp.asarray(lab), jnp.asarray(run.true_lab[pixel])))
    u0 = np.asarray(uncertainty.delta_e_uncertainty(jnp.asarray(lab), jnp.asarray(cov), jnp.asarray(run.true_lab[pixel])))
    assert np.mean(de0) > 3 * np.std(de0) * 0.5 and np.all(np.isfinite(u0))


@pytest.mark.slow
def test_delta_e_u_of_a_result_matches_the_kernel(scene):
    raw, calibration = scene.draw(np.random.default_rng(6))
    result = sj.correct(raw, calibration, noise=scene.noise_model())
    reference = np.array([50.0, 10.0, -10.0])
    u = np.asarray(result.delta_e_u(reference))
    expected = uncertainty.delta_e_uncertainty(result.lab, result.lab_covariance, jnp.asarray(reference, jnp.float32))
    np.testing.assert_allclose(u, np.asarray(expected), rtol=1e-4)  # float32, jit against eager
    with_reference_cov = np.asarray(result.delta_e_u(reference, np.eye(3, dtype=np.float32) * 0.01))
    good = np.asarray(result.valid)
    assert np.all(with_reference_cov[good] > u[good])
    with pytest.raises(ValueError, match="reference_covariance: expected shape"):
        result.delta_e_u(reference, np.eye(2))


# ---------------------------------------------------------------------------- regions


def _rect(shape, r0, r1, c0, c1):
    mask = np.zeros(shape, bool)
    mask[r0:r1, c0:c1] = True
    return mask


def test_measure_equals_the_mean_of_correct(scene):
    raw, calibration = scene.draw(np.random.default_rng(7))
    mask = _rect(scene.patch.shape, 5, 10, 10, 15)
    m = sj.measure(raw, calibration, mask, scene.noise_model())
    pixels = np.asarray(sj.correct(raw, calibration).reflectance)[mask]
    np.testing.assert_allclose(m.reflectance, pixels.mean(axis=0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(m.reflectance_spread, pixels.std(axis=0), rtol=1e-3, atol=1e-6)
    np.testing.assert_allclose(m.lab, np.asarray(sj.reflectance_to_lab(jnp.asarray(m.reflectance))), rtol=1e-6, atol=1e-6)
    assert m.pixels == 25 and m.excluded == 0
    np.testing.assert_allclose(m.lab_covariance, sum(m.lab_budget.values()), rtol=1e-9)
    under_a = m.under("A")
    np.testing.assert_allclose(under_a.lab, np.asarray(sj.reflectance_to_lab(jnp.asarray(m.reflectance), "A")), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(sj.measure(raw, calibration, mask, scene.noise_model(), illuminant="A").lab_covariance, under_a.lab_covariance, rtol=1e-6)


def test_measure_pixel_noise_averages_down_and_common_terms_do_not(scene):
    raw, calibration = scene.draw(np.random.default_rng(8))
    noise = scene.noise_model()
    small = sj.measure(raw, calibration, _rect(scene.patch.shape, 5, 7, 5, 7), noise)  # 4 px of one patch
    large = sj.measure(raw, calibration, _rect(scene.patch.shape, 5, 9, 5, 9), noise)  # 16 px of it
    for source in uncertainty.PIXEL_SOURCES:
        ratio = np.sqrt(np.diag(large.reflectance_budget[source]) / np.diag(small.reflectance_budget[source]))
        np.testing.assert_allclose(np.median(ratio), 0.5, rtol=0.15)  # 1 / sqrt(4)
    for source in ("white-patch ratio",):
        ratio = np.sqrt(np.diag(large.reflectance_budget[source]) / np.diag(small.reflectance_budget[source]))
        np.testing.assert_allclose(np.median(ratio), 1.0, rtol=0.05)


def test_measure_matches_monte_carlo_of_region_means(scene, monte_carlo_run):
    run = monte_carlo_run
    noise = scene.noise_model()
    for rect in [(5, 10, 5, 10), (20, 25, 5, 10), (10, 15, 25, 30)]:  # chart, dark, near full scale
        mask = _rect(scene.patch.shape, *rect)
        measurements = [sj.measure(raw, scene.calibration(dark, white), mask, noise)
                        for raw, dark, white in zip(run.raws[:150], run.darks[:150], run.whites[:150])]
        labs = np.array([m.lab for m in measurements])
        propagated = np.sqrt(np.median([np.diag(m.lab_covariance) for m in measurements], axis=0))
        ratio = propagated / labs.std(axis=0, ddof=1)
        assert np.all(np.abs(ratio - 1) < 0.2), (rect, ratio)  # 150 trials: sd of a std ~6 %
        d, u = measurements[0].delta_e(measurements[0].lab + np.array([2.0, 0.0, 0.0]))
        assert d > 1 and u > 0


def test_measure_excludes_flagged_pixels_and_refuses_bad_regions(scene):
    raw, calibration = scene.draw(np.random.default_rng(9))
    raw = raw.copy()
    raw[6, 6, 3] = scene.saturation
    mask = _rect(scene.patch.shape, 5, 10, 5, 10)
    m = sj.measure(raw, calibration, mask)
    assert m.pixels == 24 and m.excluded == 1
    assert m.lab_covariance is None and m.reflectance_u is None and np.isnan(m.delta_e(np.zeros(3))[1])
    with pytest.raises(ValueError, match="mask: selects no pixel"):
        sj.measure(raw, calibration, np.zeros(scene.patch.shape, bool))
    with pytest.raises(ValueError, match="mask: expected shape"):
        sj.measure(raw, calibration, mask[:-1])
    with pytest.raises(ValueError, match="mask: expected a boolean array"):
        sj.measure(raw, calibration, mask.astype(np.uint8))
    raw[5:7, 5:7, 0] = scene.saturation
    with pytest.raises(ValueError, match="all 4 pixels of the region are flagged"):
        sj.measure(raw, calibration, _rect(scene.patch.shape, 5, 7, 5, 7))
    with pytest.raises(ValueError, match="reference_lab: expected three finite numbers"):
        m.delta_e([1.0, 2.0])


@pytest.mark.slow
def test_coverage_on_the_physical_simulator():
    """Monte Carlo on the sphere simulator's own image (a test sample on a patterned background,
    glare, vignetting, lamp change): the noise-free capture is the mean, frames are drawn around
    it, and the k = 2 intervals cover the noise-free path's Lab about 95 % of the time."""
    design = simulate.ExperimentDesign(training_backgrounds=2, training_patches=2, test_backgrounds=1, test_patches=3, targets=4)
    experiment = simulate.simulate_experiment(seed=2, instrument=simulate.InstrumentModel(noise=False), design=design)
    test_frame = next(frame for frame in experiment.frames if frame.set == "test")
    estimator = mc.noise_scene(block=1)  # the estimator and Stage II of the chart scene
    scene = mc.simulated_scene(experiment, test_frame.id, coeffs=estimator.coeffs, wiener=estimator.wiener,
                               wiener_offset=estimator.wiener_offset)
    # The corner holding the white patch (rows 8:32, columns 244:268), one test patch (78:113,
    # 174:209) and the patterned background around it: a quarter of the frame, for speed.
    window = (slice(0, 120), slice(160, 272))
    scene = dataclasses.replace(scene, **{name: getattr(scene, name)[window] for name in ("white_counts", "sample_counts", "patch", "kind")})
    assert scene.patch.sum() == 24 * 24
    run = mc.run(scene, scene.noise_model(), trials=100, seed=3)
    good = np.all(np.isfinite(run.lab), axis=(0, -1)) & (scene.kind != mc.KIND_PATCH)
    assert good.sum() > 0.9 * good.size - scene.patch.sum()
    coverage = (np.abs(run.lab - run.true_lab)[:, good] <= 2 * run.lab_u[:, good]).mean(axis=(0, 1))
    assert np.all(np.abs(coverage - 0.9545) < 0.015), coverage
    ratio = np.median(np.median(run.lab_u, axis=0)[good] / np.std(run.lab, axis=0, ddof=1)[good], axis=0)
    assert np.all(np.abs(ratio - 1) < 0.05), ratio


def test_p_u_and_patch_ratio_u_refuse_what_they_cannot_use(scene):
    raw, calibration = scene.draw(np.random.default_rng(10))
    noise = scene.noise_model()
    p, p_u = sj.patch_ratio(raw, calibration), sj.patch_ratio_u(raw, calibration, noise)
    with pytest.raises(ValueError, match="p_u: expected None without p"):
        sj.correct(raw, calibration, p_u=p_u, noise=noise)
    with pytest.raises(ValueError, match="p_u: expected None without noise"):
        sj.correct(raw, calibration, p=p, p_u=p_u)
    with pytest.raises(ValueError, match="p_u: expected shape"):
        sj.correct(raw, calibration, p=p, p_u=p_u[:3], noise=noise)
    with pytest.raises(ValueError, match="noise: expected a spherejax.NoiseModel, got None"):
        sj.patch_ratio_u(raw, calibration, None)
    with pytest.raises(ValueError, match="calibration: has no patch"):
        sj.patch_ratio_u(raw[:10], calibration.rows(0, 10), noise)
