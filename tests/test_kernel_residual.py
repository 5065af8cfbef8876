"""The residual kernel estimator (spherejax.estimation.kernel_residual, E8-E11): its equations line
by line against numpy in float64 and float32, the fit (E11) against a direct solve, recovery of a
known nonlinear map, the fall-back to the affine mean away from the targets, finite gradients, and
what it is for: held-out targets of a Kubelka-Munk family of the training material."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spherejax import estimation, kubelka_munk
from spherejax.estimation import kernel_residual

from .helpers import nonlinear_targets


def _numpy_features(v, mu, S, Z):
    """exp(-|S (v - mu) - z_j|^2 / 2), the direct way (E9-E10, lengthscale folded in)."""
    u = (v - mu) @ S.T
    return np.exp(-0.5 * np.sum((u[:, None, :] - Z[None]) ** 2, axis=-1))


def _random_estimator(rng, bands=16, m=12, dtype=np.float64):
    affine = estimation.WienerEstimator(jnp.asarray(rng.normal(size=(31, bands)), dtype), jnp.asarray(rng.normal(size=31), dtype))
    return kernel_residual.ResidualKernelEstimator(affine, kernel_residual.KernelResidual(
        jnp.asarray(rng.normal(size=bands), dtype), jnp.asarray(rng.normal(size=(bands, bands)) / 4, dtype),
        jnp.asarray(rng.normal(size=(m, bands)), dtype), jnp.asarray(rng.normal(size=(31, m)), dtype),
    ))


@pytest.mark.parametrize("dtype, tolerance", [(np.float64, 1e-12), (np.float32, 2e-5)])
def test_the_estimate_is_the_affine_mean_plus_the_kernel_residual_line_by_line(dtype, tolerance):
    rng = np.random.default_rng(0)
    estimator = _random_estimator(rng, dtype=dtype)
    v = rng.normal(size=(50, 16)).astype(dtype)
    features = _numpy_features(*(np.asarray(x, np.float64) for x in (v, estimator.kernel.centre, estimator.kernel.whitening, estimator.kernel.inducing)))
    expected = (v.astype(np.float64) @ np.asarray(estimator.matrix, np.float64).T + np.asarray(estimator.offset, np.float64)
                + features @ np.asarray(estimator.kernel.weights, np.float64).T)
    got = estimation.wiener(jnp.asarray(v), estimator)
    assert got.dtype == dtype and got.shape == (50, 31)
    np.testing.assert_allclose(np.asarray(got, np.float64), expected, rtol=tolerance, atol=tolerance * np.abs(expected).max())
    k = kernel_residual.kernel_features(jnp.asarray(v), estimator.kernel.centre, estimator.kernel.whitening, estimator.kernel.inducing)
    np.testing.assert_allclose(np.asarray(k, np.float64), features, atol=tolerance * 10)


def test_the_fit_solves_equation_e11_and_keeps_rank_e12():
    """A^T = (K_mn D K_nm + lambda K_mm + eps I)^-1 K_mn D E (E11), against numpy's solve, cut to
    its best approximation of rank RESIDUAL_RANK (E12): numpy's SVD cut, of that rank, and no
    nearer to the full solution could one of that rank be (Eckart-Young: the Frobenius error is
    the root sum of the singular values dropped)."""
    rng = np.random.default_rng(1)
    m = 12  # more than RESIDUAL_RANK inducing points, so that the cut takes something away
    U, Z = rng.normal(size=(40, 5)), rng.normal(size=(m, 5))
    E, w = rng.normal(size=(40, 31)), (rng.random(40) > 0.3).astype(np.float64)
    K_nm, K_mm = _numpy_features(U, 0.0, np.eye(5), Z), _numpy_features(Z, 0.0, np.eye(5), Z)
    full = np.linalg.solve(K_nm.T @ (w[:, None] * K_nm) + 0.01 * K_mm + 1e-8 * m * np.eye(m), K_nm.T @ (w[:, None] * E)).T
    r = kernel_residual.RESIDUAL_RANK
    assert r < m
    U_, singular, Vt = np.linalg.svd(full, full_matrices=False)
    expected = (U_[:, :r] * singular[:r]) @ Vt[:r]
    got = np.asarray(kernel_residual._residual_weights(jnp.asarray(K_nm), jnp.asarray(K_mm), jnp.asarray(E), jnp.asarray(w), 0.01))
    np.testing.assert_allclose(got, expected, rtol=1e-8, atol=1e-10)
    assert np.linalg.matrix_rank(got, tol=1e-9 * singular[0]) == r
    np.testing.assert_allclose(np.linalg.norm(full - got), np.sqrt(np.sum(singular[r:] ** 2)), rtol=1e-8)


def test_a_fitted_residual_is_one_the_fused_kernel_applies():
    """The fit's rank (E12) is no more than the fused CPU kernel's, so that a fitted kernel
    calibration takes the kernel, not the jax.numpy fallback (fused.residual_fits)."""
    from spherejax._engine import fused

    assert kernel_residual.RESIDUAL_RANK <= fused.RESIDUAL_RANK
    rng = np.random.default_rng(2)
    V = rng.uniform(0.05, 0.9, (150, 16))
    R = np.clip(V @ rng.uniform(0, 0.2, (16, 31)) + 0.3 * np.sin(3 * V[:, :1]), 0, 1)
    estimator = estimation.fit_kernel_estimator(V, R)
    assert fused.residual_fits(estimator.kernel.astype(jnp.float32))
    assert np.linalg.matrix_rank(np.asarray(estimator.kernel.weights, np.float64), tol=1e-5) <= fused.RESIDUAL_RANK


def test_whitening_gives_unit_covariance_and_inducing_points_are_cluster_centres():
    rng = np.random.default_rng(2)
    V = rng.normal(size=(300, 4)) @ np.array([[3.0, 0, 0, 0], [1, 0.5, 0, 0], [0, 0, 0.01, 0], [0, 0, 0, 2]])
    mu, S = kernel_residual.whitening_of(V)
    U = (V - mu) @ S.T
    np.testing.assert_allclose(np.cov(U.T, bias=True), np.eye(4), atol=1e-10)
    Z = kernel_residual.inducing_points_of(U, 10)
    assert Z.shape == (10, 4)
    # Every centre is the mean of the points nearest it (a k-means fixed point).
    nearest = np.argmin(np.sum((U[:, None] - Z[None]) ** 2, axis=2), axis=1)
    np.testing.assert_allclose(np.stack([U[nearest == j].mean(axis=0) for j in range(10)]), Z, atol=1e-12)
    np.testing.assert_array_equal(kernel_residual.inducing_points_of(U[:7], 10), U[:7])


def test_a_nonlinear_map_is_recovered_where_the_affine_estimator_cannot_follow():
    rng = np.random.default_rng(3)
    V, R = nonlinear_targets(rng, 200)
    Vt, Rt = nonlinear_targets(rng, 200)
    folds = np.arange(200) % 5
    kernel = estimation.fit_kernel_estimator(V, R, groups=folds)
    affine = kernel.affine  # what "auto" would take of the affine methods
    assert affine.method == estimation.fit_wiener(V, R, groups=folds, method=affine.method).method
    rms = lambda e: float(np.sqrt(np.mean((np.asarray(estimation.wiener(Vt, e)) - Rt) ** 2)))  # noqa: E731
    assert rms(kernel) < 0.3 * rms(affine), (rms(kernel), rms(affine))
    report = kernel.cross_validation
    assert report[0].method == "kernel" and [r.method for r in report[1:]] == [r.method for r in affine.cross_validation]
    settings = dict(report[0].settings)
    assert settings["mean"] == affine.method and settings["inducing_points"] == kernel_residual.INDUCING_POINTS
    assert report[0].folds == "leave one group out (5 groups)"  # groups given: held out whole, as the affine methods'
    # "auto" takes it: a gain far beyond KERNEL_MIN_GAIN, z far beyond KERNEL_MIN_Z.
    assert settings["gain"] > 0.5 and settings["paired_z"] > 5
    chosen = estimation.fit_wiener(V, R, groups=folds)
    assert chosen.method == "kernel"
    np.testing.assert_array_equal(np.asarray(chosen.kernel.weights), np.asarray(kernel.kernel.weights))
    assert settings["lengthscale"] in kernel_residual.KERNEL_LENGTHSCALE_GRID and settings["ridge"] in kernel_residual.KERNEL_RIDGE_GRID
    assert report[0].spectral_rms < 0.5 * report[1].spectral_rms and np.isfinite(report[0].delta_e_d65)
    # The mean is the affine estimator fit_wiener chooses, in the caller's units.
    np.testing.assert_allclose(np.asarray(kernel.affine.matrix), np.asarray(affine.matrix), rtol=1e-6, atol=1e-9)


def test_far_from_the_targets_it_is_the_affine_estimator():
    rng = np.random.default_rng(4)
    V, R = nonlinear_targets(rng, 120)
    kernel = estimation.fit_kernel_estimator(V, R)
    far = V[:5] + 50.0  # hundreds of whitened standard deviations away
    np.testing.assert_allclose(np.asarray(estimation.wiener(far, kernel)), np.asarray(estimation.wiener(far, kernel.affine)), rtol=0, atol=1e-12)
    near = np.asarray(estimation.wiener(V[:5], kernel)) - np.asarray(estimation.wiener(V[:5], kernel.affine))
    assert np.abs(near).max() > 1e-3  # where the targets are, the residual is at work


def test_the_units_of_the_responses_do_not_change_the_estimate():
    """Fitted on responses x 2^40 (the fit's power-of-two scaling), the estimate of the scaled
    responses is the estimate of the unscaled ones."""
    rng = np.random.default_rng(5)
    V, R = nonlinear_targets(rng, 100)
    one = estimation.fit_kernel_estimator(V, R)
    big = estimation.fit_kernel_estimator(V * 2.0**40, R)
    np.testing.assert_allclose(np.asarray(estimation.wiener(V * 2.0**40, big)), np.asarray(estimation.wiener(V, one)), rtol=1e-9, atol=1e-12)


def test_gradients_are_finite_and_match_finite_differences():
    rng = np.random.default_rng(6)
    estimator = _random_estimator(rng, m=6)
    v = jnp.asarray(rng.normal(size=16))

    def loss(v, estimator):
        return jnp.sum(estimation.wiener(v, estimator) ** 2)

    grad_v = jax.grad(loss)(v, estimator)
    grad_e = eqx.filter_grad(lambda e, v: loss(v, e))(estimator, v)
    assert np.isfinite(np.asarray(grad_v)).all()
    assert all(np.isfinite(np.asarray(leaf)).all() for leaf in jax.tree_util.tree_leaves(grad_e))
    step = 1e-6
    for i in (0, 7, 15):
        e = jnp.zeros(16).at[i].set(step)
        numeric = (loss(v + e, estimator) - loss(v - e, estimator)) / (2 * step)
        np.testing.assert_allclose(float(grad_v[i]), float(numeric), rtol=1e-6)


def test_it_is_a_pytree_that_jit_takes():
    rng = np.random.default_rng(7)
    estimator = _random_estimator(rng)
    v = jnp.asarray(rng.normal(size=(3, 16)))
    np.testing.assert_allclose(np.asarray(jax.jit(estimation.wiener)(v, estimator)), np.asarray(estimation.wiener(v, estimator)), rtol=1e-12)
    leaves, tree = jax.tree_util.tree_flatten(estimator)
    assert len(leaves) == 6 and jax.tree_util.tree_unflatten(tree, leaves).method == "kernel"


def test_bad_arguments_are_refused_in_one_line():
    rng = np.random.default_rng(8)
    V, R = nonlinear_targets(rng, 30)
    with pytest.raises(ValueError, match=r"inducing_points: expected an integer >= 1, got 0"):
        estimation.fit_kernel_estimator(V, R, inducing_points=0)
    with pytest.raises(ValueError, match=r"mean: expected one of .*got 'wiener'"):
        estimation.fit_kernel_estimator(V, R, mean="wiener")
    with pytest.raises(ValueError, match=r"inducing: expected shape \(m, 16\)"):
        kernel_residual.KernelResidual(jnp.zeros(16), jnp.eye(16), jnp.zeros((4, 3)), jnp.zeros((31, 4)))
    with pytest.raises(ValueError, match=r"kernel: expected a residual of the affine estimator's 16 bands, got 8"):
        kernel_residual.ResidualKernelEstimator(
            estimation.WienerEstimator(jnp.zeros((31, 16)), jnp.zeros(31)),
            kernel_residual.KernelResidual(jnp.zeros(8), jnp.eye(8), jnp.zeros((4, 8)), jnp.zeros((31, 4))),
        )


def test_held_out_targets_of_a_kubelka_munk_family_are_estimated_better_than_by_the_affine_estimator():
    """What it is for (the issue's validation): the default estimator ("auto"), trained on one
    family's targets, takes the kernel estimator, and on other recipes of that family (a second
    draw) its spectral rms is at most 0.8x the affine estimator's (its mean, what "auto" took
    before) on every family. On the other three families it stays within 2 % of the affine
    estimator on at least 11 of the 12 pairs and within 3 % on all (measured: 0.97-1.021, the
    one above 2 % polyester disperse -> wool acid)."""
    train = kubelka_munk.km_family_responses(seed=0, n=200)
    test = kubelka_munk.km_family_responses(seed=1, n=200)

    def rms(estimator, family):
        Vt, Rt, _ = test[family]
        return float(np.sqrt(np.mean((np.asarray(estimation.wiener(Vt, estimator)) - Rt) ** 2)))

    chosen = {name: estimation.fit_wiener(V, R) for name, (V, R, _) in train.items()}
    for name, estimator in chosen.items():
        assert estimator.method == "kernel", (name, estimator.cross_validation[0])
    ratios = {name: rms(e, name) / rms(e.affine, name) for name, e in chosen.items()}
    assert max(ratios.values()) <= 0.8, ratios
    across = {(a, b): rms(chosen[a], b) / rms(chosen[a].affine, b) for a in train for b in train if a != b}
    assert sum(r <= 1.02 for r in across.values()) >= 11 and max(across.values()) < 1.03, across
