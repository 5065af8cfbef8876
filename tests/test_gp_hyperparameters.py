"""The kernel estimator's hyperparameters by marginal likelihood (E14,
spherejax.estimation.gp_hyperparameters) and its own predictive variance (E15,
estimation.ResidualVariance): the likelihood against a direct numpy evaluation, held-out targets
adding nothing, recovery of known lengthscales and noise from Gaussian-process draws (a relevant
direction short, an irrelevant one long), and the variance against the textbook formulas of the
deterministic training conditional and, with every target an inducing point, the exact
Gaussian-process posterior variance."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from spherejax.estimation import gp_hyperparameters, kernel_residual


def _numpy_nll(lengthscales, signal, noise, U, C):
    """-(E14) / n, written out with numpy (Rasmussen & Williams 2006, Eq. 5.8)."""
    X = U / lengthscales
    K = np.exp(-0.5 * np.sum((X[:, None] - X[None]) ** 2, axis=-1))
    total = 0.0
    for j in range(C.shape[1]):
        covariance = signal[j] * K + noise[j] * np.eye(len(U))
        _, logdet = np.linalg.slogdet(covariance)
        total += 0.5 * C[:, j] @ np.linalg.solve(covariance, C[:, j]) + 0.5 * logdet
    return total / len(U)


def _draw(rng, n=150, lengthscales=(0.7, 50.0), signal=(1.0, 0.25), noise=(0.01, 0.0025)):
    """Responses U (n, 2) and r = 2 components drawn from the model of (E14)."""
    U = rng.normal(size=(n, len(lengthscales)))
    X = U / np.asarray(lengthscales)
    K = np.exp(-0.5 * np.sum((X[:, None] - X[None]) ** 2, axis=-1))
    C = np.stack([
        np.linalg.cholesky(s * K + v * np.eye(n)) @ rng.normal(size=n) for s, v in zip(signal, noise)
    ], axis=1)
    return U, C


def test_the_objective_is_the_marginal_likelihood_e14():
    rng = np.random.default_rng(0)
    U, C = _draw(rng, n=40)
    variance = C.var(axis=0)
    raw = jnp.asarray(rng.normal(scale=0.5, size=2 + 2 * 2))
    with jax.enable_x64(True):
        lengthscales, signal, noise = (np.asarray(x) for x in gp_hyperparameters._parameters(raw, jnp.asarray(variance)))
        got = float(gp_hyperparameters.negative_log_likelihood(raw, (jnp.asarray(U), jnp.asarray(C), jnp.ones(40), jnp.asarray(variance))))
    # The objective leaves out the constant n/2 log 2 pi per component and a 1e-10 s^2 jitter.
    np.testing.assert_allclose(got, _numpy_nll(lengthscales, signal, noise, U, C), rtol=1e-7)


def test_held_out_targets_add_nothing_to_the_likelihood():
    """A fold's weights (0 for a held-out target) give the likelihood of its own targets alone,
    whatever the held-out targets' values."""
    rng = np.random.default_rng(1)
    U, C = _draw(rng, n=30)
    w = (np.arange(30) % 3 != 0).astype(np.float64)
    variance = jnp.asarray(C.var(axis=0))
    raw = jnp.asarray(rng.normal(scale=0.3, size=6))
    C_changed = C.copy()
    C_changed[w == 0] += 10.0
    U_changed = U.copy()
    U_changed[w == 0] -= 3.0
    with jax.enable_x64(True):
        masked = [float(gp_hyperparameters.negative_log_likelihood(raw, (jnp.asarray(u), jnp.asarray(c), jnp.asarray(w), variance)))
                  for u, c in ((U, C), (U_changed, C_changed))]
        subset = float(gp_hyperparameters.negative_log_likelihood(raw, (jnp.asarray(U[w > 0]), jnp.asarray(C[w > 0]),
                                                                        jnp.ones(int(w.sum())), variance)))
    np.testing.assert_allclose(masked[0], masked[1], rtol=1e-12)
    np.testing.assert_allclose(masked[0], subset, rtol=1e-9)


def test_known_lengthscales_and_noise_are_recovered():
    """Drawn from the model with a relevant direction (l = 0.7) and an irrelevant one (l = 50):
    the fit finds the first within 25 % and sends the second to the upper bound of
    `LENGTHSCALE_BOUNDS` (the least it may count), with signal and noise variances within a
    factor of 2; folds fit their own."""
    rng = np.random.default_rng(2)
    U, C = _draw(rng)
    fit = gp_hyperparameters.fit_hyperparameters(U, C)
    assert abs(fit.lengthscales[0] / 0.7 - 1) < 0.25, fit.lengthscales
    assert fit.lengthscales[1] > 0.95 * gp_hyperparameters.LENGTHSCALE_BOUNDS[1], fit.lengthscales
    np.testing.assert_allclose(fit.signal, [1.0, 0.25], rtol=1.0)
    np.testing.assert_allclose(fit.noise, [0.01, 0.0025], rtol=1.0)
    np.testing.assert_allclose(fit.ridge, fit.noise / fit.signal)
    folds = np.ones((2, len(U)))
    folds[1, ::2] = 0.0
    per_fold = gp_hyperparameters.fit_hyperparameters(U, C, folds)
    assert per_fold.lengthscales.shape == (2, 2) and per_fold.signal.shape == (2, 2)
    np.testing.assert_allclose(per_fold.lengthscales[0], fit.lengthscales, rtol=1e-6)
    alone = gp_hyperparameters.fit_hyperparameters(U[1::2], C[1::2])
    np.testing.assert_allclose(per_fold.lengthscales[1], alone.lengthscales, rtol=1e-4)


def _kernel(X, Y):
    return np.exp(-0.5 * np.sum((X[:, None] - Y[None]) ** 2, axis=-1))


def test_the_variance_is_the_dtc_predictive_variance_e15():
    """(E15) against the deterministic training conditional's predictive variance written as in
    Quinonero-Candela & Rasmussen (2005), Eq. 20: s^2 (1 - q) + s^2 k*^T (K_mm + s^2/sigma^2
    K_mn K_nm)^-1 k* s^2 / s^2 ... in its ridge form sigma^2 k*^T (lambda K_mm + K_mn K_nm)^-1 k*;
    with every target an inducing point, the exact posterior variance s^2 (1 - k*^T (K +
    lambda I)^-1 k*) (Rasmussen & Williams 2006, Eq. 2.26, noise-free latent)."""
    rng = np.random.default_rng(3)
    X, Z, Xs = rng.normal(size=(50, 3)), rng.normal(size=(12, 3)), rng.normal(size=(7, 3)) * 1.5
    P = np.linalg.qr(rng.normal(size=(31, 2)))[0].T
    signal, noise = np.array([0.8, 0.1]), np.array([0.02, 0.005])
    ridges = noise / signal
    K_nm, K_mm, K_sm = _kernel(X, Z), _kernel(Z, Z), _kernel(Xs, Z)
    variance = kernel_residual.residual_variance(K_nm, K_mm, P, signal, noise, ridges, np.zeros(31))
    with jax.enable_x64(True):
        got = np.asarray(variance.component_variance(jnp.asarray(K_sm)))
    jitter = 1e-8 * 12 * np.eye(12)
    for j in range(2):
        q = np.sum(K_sm * np.linalg.solve(K_mm + jitter, K_sm.T).T, axis=1)
        second = noise[j] * np.sum(K_sm * np.linalg.solve(ridges[j] * (K_mm + jitter) + K_nm.T @ K_nm, K_sm.T).T, axis=1)
        np.testing.assert_allclose(got[:, j], signal[j] * (1 - q) + second, rtol=1e-6, atol=1e-9)
    # Every target an inducing point: the exact Gaussian-process posterior variance.
    K = _kernel(X, X)
    exact = kernel_residual.residual_variance(K, K, P, signal, noise, ridges, np.zeros(31))
    K_s = _kernel(Xs, X)
    with jax.enable_x64(True):
        got = np.asarray(exact.component_variance(jnp.asarray(K_s)))
    for j in range(2):
        expected = signal[j] * (1 - np.sum(K_s * np.linalg.solve(K + ridges[j] * np.eye(50), K_s.T).T, axis=1))
        np.testing.assert_allclose(got[:, j], expected, rtol=1e-4, atol=1e-7)
    # Far from every target: the prior.
    with jax.enable_x64(True):
        far = np.asarray(exact.component_variance(jnp.zeros((1, 50))))
        per_wavelength = np.asarray(exact.reflectance_variance(jnp.zeros((1, 50))))
    np.testing.assert_allclose(far[0], signal, rtol=1e-12)
    np.testing.assert_allclose(per_wavelength[0], (P * P).T @ signal, rtol=1e-12)
