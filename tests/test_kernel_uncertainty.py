"""The kernel estimator's own uncertainty (E15, `estimation.ResidualVariance`) carried into
`correct(..., noise=)` and `measure` (N8 of `spherejax.uncertainty`).

The variance is built here from a Gaussian-process fit written out in numpy (`gp_variance`): X
from the generalised eigenproblem K_mn K_nm x = gamma K_mm x with X^T K_mm X = I (scipy's
`eigh(a, b)` normalises its eigenvectors so), C_ji = sigma_j^2 / (lambda_j + gamma_i). Checked:
- Monte Carlo: functions drawn from the model's own prior, observed with its noise at the
  targets, estimated by its posterior mean: the mean squared error at a response is the
  predictive variance (exactly, for the deterministic training conditional's generative model;
  with every target an inducing point that is the exact Gaussian process), at the component level
  and through `correct(..., noise=)`'s reflectance uncertainty;
- exact: what `correct` adds equals the variance at each pixel's Stage II response, and its Lab
  covariance equals J (sum_j var_j P_j P_j^T) J^T with J the Jacobian of colorimetry's Lab;
- held out: on the shade-card and Kubelka-Munk families (seed 0 to train, seed 1 to test), errors
  standardised by sqrt(latent variance + noise) spread about as a unit normal; the variance grows
  away from the targets;
- a residual without a variance (older calibrations) changes nothing, bit for bit.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import spherejax as sj
from spherejax import colorimetry, uncertainty
from spherejax import monte_carlo as mc
from spherejax.estimation.estimator import KernelResidual, ResidualVariance
from spherejax.polynomial import PAPER_TABLE_2
from spherejax.target_families import target_family

from .helpers import tiny_frames

#: Pixel noise off: the gain's shot term and the read noise ~ 0, so a pixel's propagated variance
#: is the estimator's own.
SILENT = {"gain": 1e12, "read_noise": 0.0}


def rbf(X, Y):
    """exp(-|x_i - y_j|^2 / 2) (n, m) for rows already divided by the lengthscale."""
    squared = np.sum(X * X, axis=1)[:, None] + np.sum(Y * Y, axis=1)[None, :] - 2.0 * X @ Y.T
    return np.exp(-0.5 * np.maximum(squared, 0.0))


def gp_variance(K_nm, K_mm, components, signal, noise, beyond) -> ResidualVariance:
    """E15 of the subset-of-regressors fit on features K_nm (n, m), K_mm (m, m): components P
    (r, 31), signal s^2 (r,), noise sigma^2 (r,), beyond (31,) the targets' scatter per wavelength."""
    m = K_mm.shape[0]
    gamma, X = scipy.linalg.eigh(K_nm.T @ K_nm, K_mm + 1e-10 * m * np.eye(m))  # X^T K_mm X = I
    ridges = noise / signal
    weights = noise[:, None] / (ridges[:, None] + np.maximum(gamma, 0.0)[None, :])
    return ResidualVariance(*(jnp.asarray(x, jnp.float64) for x in (components, signal, X, weights, beyond)))


def posterior_weights(K_nm, K_mm, C, ridges):
    """a (r, m) of (E11): (K_mn K_nm + lambda_j K_mm)^-1 K_mn c_j, one component a row."""
    m = K_mm.shape[0]
    return np.stack([np.linalg.solve(K_nm.T @ K_nm + ridge * (K_mm + 1e-10 * m * np.eye(m)), K_nm.T @ C[:, j])
                     for j, ridge in enumerate(ridges)])


def dtc_errors(rng, Z_train, Z_inducing, Z_test, signal, noise, draws):
    """Monte Carlo of the deterministic training conditional's own model (Quinonero-Candela &
    Rasmussen 2005, Sec. 5): inducing values u ~ N(0, s^2 K_mm), the function's projection
    f_Q(x) = k_x^T K_mm^-1 u seen at the targets with noise sigma^2, the truth at a test point
    f_Q plus an independent part of variance s^2 (1 - Q_xx). Returns the errors of the
    posterior mean (E11) at Z_test, (draws, p), for one component."""
    m = len(Z_inducing)
    K_mm = rbf(Z_inducing, Z_inducing) + 1e-10 * m * np.eye(m)
    K_nm, K_pm = rbf(Z_train, Z_inducing), rbf(Z_test, Z_inducing)
    factor = np.linalg.cholesky(signal * K_mm)
    u = rng.standard_normal((draws, m)) @ factor.T
    projection_train, projection_test = np.linalg.solve(K_mm, K_nm.T).T, np.linalg.solve(K_mm, K_pm.T).T
    y = u @ projection_train.T + np.sqrt(noise) * rng.standard_normal((draws, len(Z_train)))
    q_test = np.sum(projection_test * K_pm, axis=1)
    truth = u @ projection_test.T + np.sqrt(signal * np.maximum(1.0 - q_test, 0.0)) * rng.standard_normal((draws, len(Z_test)))
    a = np.linalg.solve(K_nm.T @ K_nm + noise / signal * K_mm, K_nm.T @ y.T)  # (m, draws)
    return truth - (K_pm @ a).T


@pytest.mark.parametrize("m", [12, 40])
def test_component_variance_is_the_mean_squared_error_of_the_posterior_mean(m):
    """E15 against Monte Carlo of its model, with fewer inducing points than targets (12 of 40)
    and with every target one (the exact Gaussian process); test points at the targets, between
    them and far away (where it must return the prior s^2)."""
    rng = np.random.default_rng(0)
    Z_train = rng.normal(size=(40, 3)) * 1.5
    Z_test = np.concatenate([Z_train[:5] + 0.05, rng.normal(size=(10, 3)) * 1.5, Z_train[:3] + 30.0])
    signal, noise = np.array([4e-4, 1e-4]), np.array([1e-5, 4e-6])
    Z_inducing = Z_train[:m]
    variance = gp_variance(rbf(Z_train, Z_inducing), rbf(Z_inducing, Z_inducing), np.eye(2, 31), signal, noise, np.zeros(31))
    predicted = np.asarray(variance.component_variance(jnp.asarray(rbf(Z_test, Z_inducing))))  # (p, 2)
    draws = 20000
    for j in range(2):
        errors = dtc_errors(rng, Z_train, Z_inducing, Z_test, signal[j], noise[j], draws)
        ratio = np.mean(errors**2, axis=0) / predicted[:, j]
        # sampling: the mean of 20000 squared normals has a relative sd of sqrt(2 / 20000) = 1 %
        assert np.all(np.abs(ratio - 1.0) < 0.05), (j, ratio)
    np.testing.assert_allclose(predicted[-3:], np.broadcast_to(signal, (3, 2)), rtol=1e-9)  # far: the prior
    assert np.all(predicted <= signal * (1 + 1e-9)) and np.all(predicted[:5] < 0.2 * signal)


# --------------------------------------------------------------------------- through correct


@pytest.fixture(scope="module")
def kernel_scene():
    """A 6 x 7 float64 image (Table 2's Stage II, the Monte Carlo scene's estimator) whose
    calibration carries a kernel residual with its variance, fitted on 20 of its own pixels'
    Stage II responses (nudged), every target an inducing point: (raw, calibration, v_tilde,
    training responses (n, B), the residual's model (l, S, mu, P, signal, noise))."""
    rng, scene, raw, dark, white, patch = tiny_frames()
    bands = raw.shape[-1]
    affine = sj.Calibration(dark=dark, white=white, patch=patch, coeffs=np.asarray(PAPER_TABLE_2, np.float64),
                            wiener=scene.wiener, wiener_offset=scene.wiener_offset)
    v_tilde = np.asarray(sj.correct(raw, affine, intermediates=True).v_stage2)
    pixels = v_tilde[~patch]
    mu = pixels.mean(axis=0)
    eigenvalues, Q = np.linalg.eigh(np.cov((pixels - mu).T, bias=True))
    S = (Q / np.sqrt(np.maximum(eigenvalues, 1e-8 * eigenvalues.max()))).T
    lengthscale = 3.0
    whitening = S / lengthscale
    training = pixels[:20] + 0.1 * (rng.normal(size=(20, bands)) @ np.linalg.inv(S).T)  # 0.1 whitened units off
    Z = (training - mu) @ whitening.T
    P = np.linalg.qr(rng.normal(size=(31, 2)))[0].T  # two orthonormal components (2, 31)
    signal, noise = np.array([4e-4, 6.4e-5]), np.array([1e-5, 4e-6])
    K = rbf(Z, Z)
    C = rng.normal(size=(20, 2)) * np.sqrt(signal)  # the targets' components: any will do for the weights
    A = P.T @ posterior_weights(K, K, C, noise / signal)
    variance = gp_variance(K, K, P, signal, noise, np.full(31, 1e-6))
    residual = KernelResidual(*(jnp.asarray(x) for x in (mu, whitening, Z, A)), variance=variance)
    calibration = dataclasses.replace(affine, wiener_residual=residual)
    return raw, calibration, v_tilde, training, (whitening, mu, P, signal, noise)


def test_correct_adds_the_residual_variance_at_each_pixels_response(kernel_scene):
    """N8 exactly: reflectance_u^2 grows by sum_j var_j(v_tilde) P_jw^2 at each pixel's Stage II
    response, and the Lab covariance by J (sum_j var_j P_j P_j^T) J^T, J = dLab/dr of colorimetry
    at the pixel's reflectance (jax.jacfwd); the values themselves do not change."""
    raw, calibration, v_tilde, _, _ = kernel_scene
    without = dataclasses.replace(calibration, wiener_residual=dataclasses.replace(calibration.wiener_residual, variance=None))
    noise = sj.NoiseModel(**SILENT)
    got, before = sj.correct(raw, calibration, noise=noise), sj.correct(raw, without, noise=noise)
    outside = ~np.asarray(calibration.patch)
    assert np.array_equal(np.asarray(got.reflectance), np.asarray(before.reflectance))
    assert np.array_equal(np.asarray(got.lab), np.asarray(before.lab))
    residual = calibration.wiener_residual
    added = np.asarray(got.reflectance_u) ** 2 - np.asarray(before.reflectance_u) ** 2
    expected = np.asarray(residual.reflectance_variance(jnp.asarray(v_tilde)))
    np.testing.assert_allclose(added[outside], expected[outside], rtol=1e-7, atol=1e-15)
    silent = np.asarray(before.reflectance_u)[outside] ** 2
    assert np.all(expected[outside].sum(axis=-1) > 1e3 * silent.sum(axis=-1))  # far above the silent pixel noise

    covariance = np.asarray(uncertainty.residual_covariance(jnp.asarray(v_tilde), residual))  # (H, W, 31, 31)
    np.testing.assert_allclose(np.diagonal(covariance, axis1=-2, axis2=-1), expected, rtol=1e-12)
    jacobian = jax.vmap(jax.jacfwd(lambda r: colorimetry.reflectance_to_lab(r, calibration.illuminant, observer=calibration.observer)))(
        jnp.asarray(got.reflectance)[outside])
    lab_added = np.asarray(got.lab_covariance)[outside] - np.asarray(before.lab_covariance)[outside]
    lab_expected = np.einsum("pax,pxy,pby->pab", jacobian, covariance[outside], jacobian)
    np.testing.assert_allclose(lab_added, lab_expected, rtol=1e-6, atol=1e-12)


def test_correct_reflectance_u_matches_monte_carlo_of_the_residual(kernel_scene):
    """The residual's share of a pixel's reflectance variance through `correct(..., noise=)`
    against sampling: functions drawn from the Gaussian process's prior at the 20 targets and
    every pixel's response jointly, the targets observed with the components' noise, the posterior
    mean (E11, every target an inducing point: the exact process) as the estimate; the mean squared
    error of the reflectance, sum_j e_j P_j, per pixel and wavelength, over 20000 draws."""
    raw, calibration, v_tilde, training, (whitening, mu, P, signal, noise) = kernel_scene
    outside = ~np.asarray(calibration.patch)
    without = dataclasses.replace(calibration, wiener_residual=dataclasses.replace(calibration.wiener_residual, variance=None))
    model = sj.NoiseModel(**SILENT)
    propagated = (np.asarray(sj.correct(raw, calibration, noise=model).reflectance_u) ** 2
                  - np.asarray(sj.correct(raw, without, noise=model).reflectance_u) ** 2)[outside]  # (p, 31)
    Z = (training - mu) @ whitening.T
    Z_pixels = (v_tilde[outside] - mu) @ whitening.T
    rng = np.random.default_rng(7)
    draws = 20000
    error = sum(np.einsum("dp,w->dpw", dtc_errors(rng, Z, Z, Z_pixels, signal[j], noise[j], draws), P[j]) for j in range(2))
    sampled = np.mean(error**2, axis=0)
    ratio = sampled / propagated
    # Measured: median 1.002, all within 0.972..1.029 (sampling: 1 % relative sd per entry).
    assert abs(np.median(ratio) - 1.0) < 0.01, np.median(ratio)
    assert np.all(np.abs(ratio - 1.0) < 0.06), (ratio.min(), ratio.max())


def test_a_residual_without_variance_changes_nothing(kernel_scene):
    """Older calibrations (variance None) go through the path they went before: a variance of
    zeros adds exact zeros, so the uncertainties are the same bit for bit, and so are the values
    with any variance."""
    raw, calibration, _, _, _ = kernel_scene
    residual = calibration.wiener_residual
    zero = ResidualVariance(residual.variance.components, jnp.zeros_like(residual.variance.prior),
                            residual.variance.projection, jnp.zeros_like(residual.variance.weights),
                            residual.variance.noise)
    model = sj.NoiseModel(gain=1.2, read_noise=5.0, dark_frames=16, white_frames=8)
    none = sj.correct(raw, dataclasses.replace(calibration, wiener_residual=dataclasses.replace(residual, variance=None)), noise=model)
    zeros = sj.correct(raw, dataclasses.replace(calibration, wiener_residual=dataclasses.replace(residual, variance=zero)), noise=model)
    for name in ("reflectance", "lab", "reflectance_u", "lab_u", "lab_covariance"):
        a, b = np.asarray(getattr(none, name)), np.asarray(getattr(zeros, name))
        assert a.tobytes() == b.tobytes(), name


def test_strips_and_float32_carry_the_residual_variance(kernel_scene):
    """Rows of a calibration (`Calibration.rows`, a strip corrected with the whole image's p and
    u(p)) carry the variance and give the whole image's uncertainties of those rows; a float32
    calibration (uint16 frames' compute dtype) gives the float64 ones to float32's precision."""
    raw, calibration, _, _, _ = kernel_scene
    model = sj.NoiseModel(gain=1.2, read_noise=5.0, dark_frames=16, white_frames=8)
    whole = sj.correct(raw, calibration, noise=model)
    p, p_u = sj.patch_ratio(raw, calibration), sj.patch_ratio_u(raw, calibration, model)
    rows = calibration.rows(2, 5)
    assert rows.wiener_residual.variance is calibration.wiener_residual.variance
    strip = sj.correct(raw[2:5], rows, p=p, p_u=p_u, noise=model)
    np.testing.assert_allclose(np.asarray(strip.reflectance_u), np.asarray(whole.reflectance_u)[2:5], rtol=1e-12)  # measured 1.9e-16
    np.testing.assert_allclose(np.asarray(strip.lab_u), np.asarray(whole.lab_u)[2:5], rtol=1e-12)
    single = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32) if jnp.issubdtype(x.dtype, jnp.floating) else x,
                                    calibration)
    got = sj.correct(raw.astype(np.float32), single, noise=model)
    outside = ~np.asarray(calibration.patch)
    # measured: 1.0e-6 relative at most (float32's unit round-off is 6e-8)
    np.testing.assert_allclose(np.asarray(got.reflectance_u)[outside], np.asarray(whole.reflectance_u)[outside], rtol=2e-5)


def _region_mask(calibration):
    mask = np.zeros(calibration.image_shape, bool)
    mask[3:6, 2:6] = True
    return mask


def test_measure_adds_the_residual_variance_at_the_regions_mean_response(kernel_scene):
    """`measure`'s budget gains "kernel residual": sum_j var_j(v_bar) P_j P_j^T at the region's
    mean Stage II response (the residual is one function for every pixel: its error does not
    average down), in the reflectance covariance and, through Lab's Jacobian, in Lab's and its U;
    every other source's share is unchanged."""
    raw, calibration, v_tilde, _, (whitening, mu, P, signal, _) = kernel_scene
    mask = _region_mask(calibration)
    model = sj.NoiseModel(gain=1.2, read_noise=5.0, dark_frames=16, white_frames=8)
    without = dataclasses.replace(calibration, wiener_residual=dataclasses.replace(calibration.wiener_residual, variance=None))
    got, before = sj.measure(raw, calibration, mask, model), sj.measure(raw, without, mask, model)
    assert list(got.reflectance_budget) == [*before.reflectance_budget, uncertainty.RESIDUAL_SOURCE]
    for name, covariance in before.reflectance_budget.items():
        np.testing.assert_array_equal(got.reflectance_budget[name], covariance)
    # numpy: E15 written out at the mean response
    v_bar = v_tilde[mask].mean(axis=0)
    features = np.exp(-0.5 * np.sum((((v_bar - mu) @ whitening.T) - np.asarray(calibration.wiener_residual.inducing)) ** 2, axis=-1))
    variance = calibration.wiener_residual.variance
    g = features @ np.asarray(variance.projection)
    component = signal * (1.0 - g @ g) + np.asarray(variance.weights) @ (g * g)
    expected = np.einsum("j,jw,jx->wx", component, P, P)
    np.testing.assert_allclose(got.reflectance_budget[uncertainty.RESIDUAL_SOURCE], expected, rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(got.reflectance_covariance, before.reflectance_covariance + expected, rtol=1e-9, atol=1e-18)
    assert np.all(got.lab_u > before.lab_u)
    jacobian = jax.jacfwd(lambda r: colorimetry.reflectance_to_lab(r, calibration.illuminant, observer=calibration.observer))(
        jnp.asarray(got.reflectance))
    np.testing.assert_allclose(got.lab_budget[uncertainty.RESIDUAL_SOURCE], np.asarray(jacobian) @ expected @ np.asarray(jacobian).T,
                               rtol=1e-6, atol=1e-12)
    assert uncertainty.RESIDUAL_SOURCE in got.to_dict()["lab_u_by_source"]


# ------------------------------------------------------------------------ held-out coverage


def _affine(V, R):
    """Least squares r = W v + r0 (W (31, B), r0 (31,))."""
    X = np.c_[V, np.ones(len(V))]
    coefficients = np.linalg.lstsq(X, R, rcond=None)[0]
    return coefficients[:-1].T, coefficients[-1]


def _marginal_likelihood_fit(U, C):
    """(lengthscale, s^2 (r,), sigma^2 (r,)) maximising the components' summed log marginal
    likelihood (Rasmussen & Williams 2006, Eq. 5.8) over an isotropic lengthscale grid and, per
    component, log grids of s^2 and sigma^2 (the kernel's eigendecomposition makes each a sum of
    n terms)."""
    variance = C.var(axis=0)
    signal_grid = np.geomspace(1e-4, 1e2, 25)[:, None, None, None] * variance
    noise_grid = np.geomspace(1e-5, 1.0, 21)[None, :, None, None] * variance
    best = (-np.inf, None)
    for lengthscale in (1.0, 2.0, 4.0, 8.0):
        eigenvalues, Q = np.linalg.eigh(rbf(U / lengthscale, U / lengthscale))
        projected = (Q.T @ C)[None, None]  # (1, 1, n, r)
        spread = signal_grid * np.maximum(eigenvalues, 0.0)[None, None, :, None] + noise_grid  # (S, N, n, r)
        likelihood = -0.5 * np.sum(projected**2 / spread + np.log(spread), axis=2).reshape(-1, C.shape[1])
        if likelihood.max(axis=0).sum() > best[0]:
            s, n = np.unravel_index(likelihood.argmax(axis=0), (signal_grid.shape[0], noise_grid.shape[1]))
            best = (likelihood.max(axis=0).sum(),
                    (lengthscale, signal_grid[s, 0, 0, np.arange(C.shape[1])], noise_grid[0, n, 0, np.arange(C.shape[1])]))
    return best[1]


#: Held out (seed 1) against the fit on seed 0: the fraction of errors within 1.96 standardised
#: and their standard deviation, as measured (`family_fit`), with the bounds asserted. On
#: shade_card the targets' scatter (the noise, mean 2.1e-6) dominates the latent variance (1.4e-7
#: at the held-out responses); on km_mixing (cotton reactive) the latent one does (1.4e-7 against
#: 8.6e-9), and there the isotropic fit here under-covers a little. Not asserted: mixed_real, 88.7 %
#: within, standard deviation 1.26 (its fluorescent and glossy members are not one smooth function).
COVERAGE = {
    # kind: (measured within, measured sd, within bounds, sd bounds, the least per wavelength: measured, bound)
    "shade_card": (0.941, 1.034, (0.91, 0.97), (0.95, 1.12), 0.905, 0.85),
    "km_mixing": (0.915, 1.152, (0.88, 0.95), (1.0, 1.25), 0.735, 0.65),
}


@pytest.fixture(scope="module", params=sorted(COVERAGE))
def family_fit(request):
    """A Gaussian process on the affine estimator's residuals of 200 targets of a family kind
    (seed 0), rank 8, every target an inducing point, hyperparameters by marginal likelihood:
    (kind, (W, r0, residual), the training responses)."""
    kind = request.param
    V, R = target_family(kind, 200, 0)
    W, r0 = _affine(V, R)
    E = R - (V @ W.T + r0)
    r0, E = r0 + E.mean(axis=0), E - E.mean(axis=0)
    P = np.linalg.svd(E, full_matrices=False)[2][:8]
    C = E @ P.T
    mu = V.mean(axis=0)
    eigenvalues, Q = np.linalg.eigh(np.cov((V - mu).T, bias=True))
    S = (Q / np.sqrt(np.maximum(eigenvalues, 1e-8 * eigenvalues.max()))).T
    lengthscale, signal, noise = _marginal_likelihood_fit((V - mu) @ S.T, C)
    Z = (V - mu) @ (S / lengthscale).T
    K = rbf(Z, Z)
    A = P.T @ posterior_weights(K, K, C, noise / signal)
    beyond = np.var(E - C @ P, axis=0) + np.einsum("j,jw->w", noise, P * P)  # beyond rank 8, and the components' noise
    variance = gp_variance(K, K, P, signal, noise, beyond)
    residual = KernelResidual(*(jnp.asarray(x) for x in (mu, S / lengthscale, Z, A)), variance=variance)
    return kind, (W, r0, residual), V


def test_held_out_errors_are_covered_by_the_predicted_variance(family_fit):
    """Targets of another draw (seed 1): their errors over sqrt(latent variance + noise) spread
    about as a unit normal (95 % within 1.96; figures in `COVERAGE`)."""
    kind, (W, r0, residual), _ = family_fit
    V, R = target_family(kind, 200, 1)
    errors = R - (V @ W.T + r0 + np.asarray(residual(jnp.asarray(V))))
    latent = np.asarray(residual.reflectance_variance(jnp.asarray(V)))
    noise = np.asarray(residual.variance.noise)
    z = errors / np.sqrt(latent + noise)
    within = np.abs(z) < 1.96
    _, _, (low, high), (sd_low, sd_high), _, least = COVERAGE[kind]
    assert low <= within.mean() <= high, within.mean()
    assert sd_low <= z.std() <= sd_high, z.std()
    assert within.mean(axis=0).min() >= least, within.mean(axis=0)
    if kind == "km_mixing":  # where the latent variance dominates, the noise alone covers less (measured 76.3 %)
        assert np.mean(np.abs(errors / np.sqrt(noise)) < 1.96) < 0.85


def test_the_variance_is_larger_far_from_the_targets(family_fit):
    """At the targets the estimator knows its residual to about the noise over the neighbours; at
    another family's responses (fluorescent whites: brightener, another material) it falls back
    towards the prior s^2 (E15), never above it. Measured on shade_card: mean latent variance
    1.8e-8 at the targets, 1.1e-6 at the fluorescent family (a median 79 times more), prior 2.1e-6."""
    _, (_, _, residual), V = family_fit
    other, _ = target_family("fluorescent", 200, 1)
    at_targets = np.asarray(residual.reflectance_variance(jnp.asarray(V)))
    away = np.asarray(residual.reflectance_variance(jnp.asarray(other)))
    prior = np.einsum("j,jw->w", np.asarray(residual.variance.prior), np.asarray(residual.variance.components) ** 2)
    assert np.median(away.mean(axis=1)) > 10 * np.median(at_targets.mean(axis=1))
    assert np.all(away <= prior * (1 + 1e-9) + 1e-18) and np.all(at_targets <= prior * (1 + 1e-9) + 1e-18)


def test_float32_gives_the_float64_variance(family_fit):
    """A uint16 frame is corrected in float32: E15's 1 - |g|^2 cancels near the targets, but with
    X from the generalised eigenproblem the float32 variance stays within 2 % of float64's at the
    targets and held out (measured, at most: shade_card 0.11 %, km_mixing 1.08 % at its targets,
    where the variance is 1e-10, a tenth of the targets' noise; medians 0.001-0.03 %)."""
    kind, (_, _, residual), V = family_fit
    held_out, _ = target_family(kind, 200, 1)
    single = residual.astype(jnp.float32)
    for responses in (V, held_out):
        double = np.asarray(residual.reflectance_variance(jnp.asarray(responses)))
        got = np.asarray(single.reflectance_variance(jnp.asarray(responses, jnp.float32)), np.float64)
        assert np.all(np.abs(got - double) <= 0.02 * double), np.max(np.abs(got - double) / double)


@pytest.mark.slow
def test_the_fitted_kernel_estimators_variance_covers_held_out_targets(kernel_scene, tmp_path):
    """`fit_kernel_estimator` fills the variance (E14-E15, marginal likelihood, forward-selected
    inducing points): on km_mixing (200 targets of seed 0, 200 of seed 1 held out) the held-out
    errors over sqrt(latent + noise) are covered as a unit normal's, the latent part is what
    covers them (the noise alone much less), the variance at another material is far above the
    one at the targets and never above the prior; and a calibration carrying it round trips through
    its file into the same propagated uncertainty. Measured (m = 48, rank 8): 94.8 % within 1.96,
    standard deviation 0.97, least per wavelength 86.5 %, noise alone 70.1 %; mean latent
    variance 3.0e-7 at the targets, 1.5e-6 at fluorescent whites (medians 8.9x; with 64
    pivoted-Cholesky points, spread over every direction, 1.0e-7 and 23x)."""
    from spherejax import estimation, io

    V, R = target_family("km_mixing", 200, 0)
    estimator = estimation.fit_kernel_estimator(V, R)
    kernel = estimator.kernel
    assert kernel.variance is not None
    held_out, truth = target_family("km_mixing", 200, 1)
    errors = truth - np.asarray(estimator(jnp.asarray(held_out)))
    latent = np.asarray(kernel.reflectance_variance(jnp.asarray(held_out)))
    noise = np.asarray(kernel.variance.noise)
    within = np.abs(errors / np.sqrt(latent + noise)) < 1.96
    assert 0.89 <= within.mean() <= 0.97, within.mean()
    assert 0.95 <= np.std(errors / np.sqrt(latent + noise)) <= 1.25
    assert within.mean(axis=0).min() >= 0.75, within.mean(axis=0)
    assert np.mean(np.abs(errors / np.sqrt(noise)) < 1.96) < 0.85
    other, _ = target_family("fluorescent", 200, 1)
    at_targets = np.asarray(kernel.reflectance_variance(jnp.asarray(V)))
    away = np.asarray(kernel.reflectance_variance(jnp.asarray(other)))
    prior = np.einsum("j,jw->w", np.asarray(kernel.variance.prior), np.asarray(kernel.variance.components) ** 2)
    assert np.median(away.mean(axis=1)) > 5 * np.median(at_targets.mean(axis=1))
    assert np.all(away <= prior * (1 + 1e-9) + 1e-18)

    raw, scene_calibration, _, _, _ = kernel_scene
    calibration = dataclasses.replace(scene_calibration, wiener=estimator.matrix, wiener_offset=estimator.offset,
                                      wiener_residual=kernel)
    path = tmp_path / "fitted.h5"
    io.save_calibration(path, calibration, instrument_id="sphere-1", band_centres_nm=list(range(400, 701, 20)))
    loaded, _ = io.load_calibration(path)
    model = sj.NoiseModel(gain=1.2, read_noise=5.0)
    a, b = sj.correct(raw, calibration, noise=model), sj.correct(raw, loaded, noise=model)
    assert np.asarray(a.reflectance_u).tobytes() == np.asarray(b.reflectance_u).tobytes()
