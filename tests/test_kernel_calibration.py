"""A calibration whose estimator has a kernel residual (Calibration.wiener_residual, E8): every
route of `correct` applies r = W v_tilde + r0 + A k(v_tilde), its Lab is that reflectance's, its
strips are the whole image's, its gradients are finite and its propagated uncertainty is the
first-order one through the residual too."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax import estimation
from tests.batch_support import B, frame, make_calibration


@pytest.fixture(scope="module")
def calibrations():
    rng = np.random.default_rng(0)
    affine, _, _ = make_calibration(rng)
    residual = estimation.KernelResidual(
        jnp.asarray(rng.uniform(0.2, 0.6, B), jnp.float32), jnp.asarray(np.eye(B) * 3.0, jnp.float32),
        jnp.asarray(rng.normal(size=(8, B)), jnp.float32), jnp.asarray(rng.normal(scale=0.05, size=(31, 8)), jnp.float32),
    )
    return affine, dataclasses.replace(affine, wiener_residual=residual), frame(rng)


def _numpy_estimate(v, calibration):
    """W v + r0 + A k(v) in float64, the kernel written out (E9-E10)."""
    k = calibration.wiener_residual
    u = (v - np.asarray(k.centre, np.float64)) @ np.asarray(k.whitening, np.float64).T
    features = np.exp(-0.5 * np.sum((u[..., None, :] - np.asarray(k.inducing, np.float64)) ** 2, axis=-1))
    return (v @ np.asarray(calibration.wiener, np.float64).T + np.asarray(calibration.wiener_offset, np.float64)
            + features @ np.asarray(k.weights, np.float64).T)


def test_correct_applies_the_residual_and_lab_follows_the_reflectance(calibrations):
    _, kernel, raw = calibrations
    result = sj.correct(raw, kernel, intermediates=True)
    good = np.asarray(result.quality) == 0
    assert good.mean() > 0.9
    expected = _numpy_estimate(np.asarray(result.v_stage2, np.float64), kernel)
    got = np.asarray(result.reflectance, np.float64)
    np.testing.assert_allclose(got[good], expected[good], atol=2e-5)
    assert np.isnan(got[~good]).all()
    lab = np.asarray(sj.reflectance_to_lab(result.reflectance))
    np.testing.assert_allclose(np.asarray(result.lab)[good], lab[good], atol=2e-3)


def test_the_plan_takes_the_jax_numpy_path_and_strips_give_the_whole_image(calibrations):
    affine, kernel, raw = calibrations
    assert sj.plan(kernel, raw.shape, dtype=raw.dtype).kernel_mode is None
    whole = sj.correct(raw, kernel)
    p = sj.patch_ratio(raw, kernel)
    rows = sj.correct(raw[10:26], kernel.rows(10, 26), p=p)
    for name in ("reflectance", "lab", "quality"):
        np.testing.assert_array_equal(np.asarray(getattr(rows, name)), np.asarray(getattr(whole, name))[10:26])
    # Without a residual the estimate is the affine one: zero weights change nothing.
    zero = dataclasses.replace(kernel, wiener_residual=dataclasses.replace(kernel.wiener_residual, weights=jnp.zeros((31, 8), jnp.float32)))
    np.testing.assert_allclose(np.asarray(sj.correct(raw, zero).reflectance), np.asarray(sj.correct(raw, affine).reflectance),
                               atol=2e-6)


def test_gradients_with_respect_to_the_residual_are_finite(calibrations):
    _, kernel, raw = calibrations

    def loss(calibration):
        return jnp.nanmean(sj.correct(raw, calibration).reflectance)

    grads = eqx.filter_grad(loss)(kernel)
    weights = np.asarray(grads.wiener_residual.weights)
    assert np.isfinite(weights).all() and np.abs(weights).max() > 0


def test_the_propagated_uncertainty_goes_through_the_residual(calibrations):
    """reflectance_u at a few pixels against the first order written out: the Jacobian of the
    whole estimate (jax.jacfwd of W v + r0 + A k(v)) and each band's variance, the latter taken
    from the affine calibration's result (the bands' variances do not depend on the estimator)."""
    affine, kernel, raw = calibrations
    noise = sj.NoiseModel(gain=2.0, read_noise=3.0, dark_frames=16, white_frames=8)
    with_kernel = sj.correct(raw, kernel, noise=noise, intermediates=True)
    plain = sj.correct(raw, affine, noise=noise)
    W = np.asarray(kernel.wiener, np.float64)
    # Band variances from the affine result: u_r^2 = (W^2) var, solved by least squares.
    checked = 0
    for i, j in [(5, 7), (20, 30), (33, 2), (12, 40)]:
        if int(with_kernel.quality[i, j]) != 0:
            continue
        checked += 1
        var = np.linalg.lstsq(W**2, np.asarray(plain.reflectance_u[i, j], np.float64) ** 2, rcond=None)[0]
        v = jnp.asarray(with_kernel.v_stage2[i, j], jnp.float64)
        J = np.asarray(jax.jacfwd(lambda x: _jax_estimate(x, kernel))(v))
        expected = np.sqrt((J**2) @ var)
        np.testing.assert_allclose(np.asarray(with_kernel.reflectance_u[i, j]), expected, rtol=2e-3)
    assert checked >= 3


def _jax_estimate(v, calibration):
    k = calibration.wiener_residual.astype(jnp.float64)
    return jnp.asarray(calibration.wiener, jnp.float64) @ v + jnp.asarray(calibration.wiener_offset, jnp.float64) + k(v)


def test_a_residual_of_other_bands_is_refused(calibrations):
    affine, _, _ = calibrations
    other = estimation.KernelResidual(jnp.zeros(8), jnp.eye(8), jnp.zeros((4, 8)), jnp.zeros((31, 4)))
    with pytest.raises(ValueError, match=r"wiener_residual: expected a residual of the 16 bands, got one of 8"):
        dataclasses.replace(affine, wiener_residual=other)


def test_large_frames_get_the_residual_too():
    """Frames of 8 MiB of outputs and more take the plan's prepared-constants route, which built
    its constants without the residual (found at 1024 x 1024: the kernel calibration corrected as
    the affine one)."""
    rng = np.random.default_rng(1)
    H = W = 256
    dark = rng.uniform(90, 110, (H, W, B)).astype(np.float32)
    white = rng.uniform(9000, 11000, (H, W, B)).astype(np.float32)
    patch = np.zeros((H, W), bool)
    patch[10:40, 10:40] = True
    affine = sj.Calibration(dark=dark, white=white, patch=patch, coeffs=np.tile([0.0, 1.0, 0.0, 0.0], (B, 1)).astype(np.float32),
                            wiener=rng.normal(scale=0.1, size=(31, B)).astype(np.float32), wiener_offset=np.zeros(31, np.float32))
    residual = estimation.KernelResidual(
        jnp.full(B, 0.5, jnp.float32), jnp.eye(B, dtype=jnp.float32) * 3, jnp.asarray(rng.normal(size=(16, B)), jnp.float32),
        jnp.asarray(rng.normal(scale=0.01, size=(31, 16)), jnp.float32),
    )
    kernel = dataclasses.replace(affine, wiener_residual=residual)
    raw = (dark + rng.uniform(0.2, 0.8, (H, W, B)) * (white - dark)).astype(np.uint16)
    got = np.asarray(sj.correct(raw, kernel).reflectance, np.float64)
    v = np.asarray(sj.correct(raw, kernel, intermediates=True).v_stage2, np.float64)
    np.testing.assert_allclose(got, _numpy_estimate(v, kernel), atol=2e-5)


def test_a_residual_that_is_not_a_kernel_residual_is_refused(calibrations):
    affine, kernel, _ = calibrations
    with pytest.raises(ValueError, match=r"wiener_residual: expected an estimation.KernelResidual or None, got dict"):
        dataclasses.replace(affine, wiener_residual={"weights": kernel.wiener_residual.weights})
