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
from spherejax import estimation, pixel_constants
from spherejax._engine import fused
from tests.batch_support import B, frame, make_calibration
from tests.helpers import numpy_kernel_estimate


@pytest.fixture(scope="module")
def calibrations():
    rng = np.random.default_rng(0)
    affine, _, _ = make_calibration(rng)
    residual = estimation.KernelResidual(
        jnp.asarray(rng.uniform(0.2, 0.6, B), jnp.float32), jnp.asarray(np.eye(B) * 3.0, jnp.float32),
        jnp.asarray(rng.normal(size=(8, B)), jnp.float32), jnp.asarray(rng.normal(scale=0.05, size=(31, 8)), jnp.float32),
    )
    return affine, dataclasses.replace(affine, wiener_residual=residual), frame(rng)


def test_correct_applies_the_residual_and_lab_follows_the_reflectance(calibrations):
    _, kernel, raw = calibrations
    result = sj.correct(raw, kernel, intermediates=True)
    good = np.asarray(result.quality) == 0
    assert good.mean() > 0.9
    expected = numpy_kernel_estimate(np.asarray(result.v_stage2, np.float64), kernel)
    got = np.asarray(result.reflectance, np.float64)
    np.testing.assert_allclose(got[good], expected[good], atol=2e-5)
    assert np.isnan(got[~good]).all()
    lab = np.asarray(sj.reflectance_to_lab(result.reflectance))
    np.testing.assert_allclose(np.asarray(result.lab)[good], lab[good], atol=2e-3)


def test_strips_give_the_whole_image_and_zero_weights_the_affine_estimate(calibrations):
    affine, kernel, raw = calibrations
    whole = sj.correct(raw, kernel)
    p = sj.patch_ratio(raw, kernel)
    rows = sj.correct(raw[10:26], kernel.rows(10, 26), p=p)
    for name in ("reflectance", "lab", "quality"):
        np.testing.assert_array_equal(np.asarray(getattr(rows, name)), np.asarray(getattr(whole, name))[10:26])
    # Without a residual the estimate is the affine one: zero weights change nothing.
    zero = dataclasses.replace(kernel, wiener_residual=dataclasses.replace(kernel.wiener_residual, weights=jnp.zeros((31, 8), jnp.float32)))
    np.testing.assert_allclose(np.asarray(sj.correct(raw, zero).reflectance), np.asarray(sj.correct(raw, affine).reflectance),
                               atol=2e-6)


@pytest.fixture(scope="module")
def near_the_frame():
    """A calibration whose residual matters on its frame: whitened on the frame's own Stage II
    responses, inducing points at 24 of its pixels, lengthscale 2 (so k(v) spans 1 down to
    nothing), weights of rank 24 (more than the fused kernel's RESIDUAL_RANK) and the same cut to
    that rank, as the fit cuts them."""
    rng = np.random.default_rng(5)
    affine, _, _ = make_calibration(rng)
    raw = frame(rng)
    result = sj.correct(raw, affine, intermediates=True)
    v = np.asarray(result.v_stage2, np.float64)[np.asarray(result.quality) == 0]
    mu, S = estimation.kernel_residual.whitening_of(v)
    S = S / 2.0
    Z = (v[rng.choice(len(v), 24, replace=False)] - mu) @ S.T
    A = rng.normal(scale=0.05, size=(31, 24))
    full = estimation.KernelResidual(*(jnp.asarray(x, jnp.float32) for x in (mu, S, Z, A)))
    cut_weights = estimation.kernel_residual._at_rank(jnp.asarray(A), estimation.kernel_residual.RESIDUAL_RANK)
    cut = dataclasses.replace(full, weights=jnp.asarray(cut_weights, jnp.float32))
    return affine, dataclasses.replace(affine, wiener_residual=full), dataclasses.replace(affine, wiener_residual=cut), raw


#: The fused kernel's variants that apply a kernel residual (all of them; tests/test_fused_residual.py
#: covers each in depth), among those this CPU runs.
RESIDUAL_VARIANTS = [name for name in (fused.AVX512, fused.AVX2, fused.GENERIC) if name in fused.supported_variants()]


@pytest.mark.parametrize("variant", RESIDUAL_VARIANTS)
def test_the_fused_kernel_applies_the_residual_as_the_jax_numpy_path_does(near_the_frame, monkeypatch, variant):
    affine, _, cut, raw = near_the_frame
    monkeypatch.setenv(fused.SWITCH, variant)
    assert sj.plan(cut, raw.shape, dtype=raw.dtype).kernel_mode == variant
    got = sj.correct(raw, cut, intermediates=True)
    monkeypatch.setenv(fused.SWITCH, "0")
    assert sj.plan(cut, raw.shape, dtype=raw.dtype).kernel_mode is None
    want = sj.correct(raw, cut)
    np.testing.assert_array_equal(np.asarray(got.quality), np.asarray(want.quality))
    good = np.asarray(want.quality) == 0
    # The residual is no small part of the estimate here, and the kernel gives it as the
    # jax.numpy path and as float64 numpy (E9-E10 written out) do.
    residual = np.asarray(want.reflectance) - np.asarray(sj.correct(raw, affine).reflectance)
    assert np.abs(residual[good]).max() > 0.02
    np.testing.assert_allclose(np.asarray(got.reflectance)[good], np.asarray(want.reflectance)[good], atol=2e-6)
    np.testing.assert_allclose(np.asarray(got.lab)[good], np.asarray(want.lab)[good], atol=2e-4)
    expected = numpy_kernel_estimate(np.asarray(got.v_stage2, np.float64), cut)
    np.testing.assert_allclose(np.asarray(got.reflectance, np.float64)[good], expected[good], atol=1e-5)
    assert np.isnan(np.asarray(got.reflectance)[~good]).all() and np.isnan(np.asarray(got.lab)[~good]).all()


def test_a_residual_the_kernel_does_not_fit_takes_the_jax_numpy_path(near_the_frame, monkeypatch):
    """Weights of rank 24 (a calibration file not made by the fit, which keeps RESIDUAL_RANK) are not
    cut: the plan takes the jax.numpy path, which applies them whole. The AVX2 variant applies a
    residual the kernel fits, as the other variants do (the kernel contract)."""
    _, full, cut, raw = near_the_frame
    assert not fused.residual_fits(full.wiener_residual) and fused.residual_fits(cut.wiener_residual)
    assert sj.plan(full, raw.shape, dtype=raw.dtype).kernel_mode is None
    good = np.asarray(sj.correct(raw, full).quality) == 0
    expected = numpy_kernel_estimate(np.asarray(sj.correct(raw, full, intermediates=True).v_stage2, np.float64), full)
    np.testing.assert_allclose(np.asarray(sj.correct(raw, full).reflectance, np.float64)[good], expected[good], atol=1e-5)
    if fused.AVX2 in fused.supported_variants():
        monkeypatch.setenv(fused.SWITCH, fused.AVX2)
        assert sj.plan(cut, raw.shape, dtype=raw.dtype).kernel_mode == fused.AVX2
        assert sj.plan(cut.rows(0, 8), (8, *raw.shape[1:]), dtype=raw.dtype).kernel_mode == fused.AVX2
        assert sj.plan(full, raw.shape, dtype=raw.dtype).kernel_mode is None
        got = sj.correct(raw, cut)
        expected = numpy_kernel_estimate(np.asarray(sj.correct(raw, cut, intermediates=True).v_stage2, np.float64), cut)
        np.testing.assert_allclose(np.asarray(got.reflectance, np.float64)[good], expected[good], atol=1e-5)


def _direct_arrays(calibration, raw):
    """The arrays the fused kernel reads for one frame (`fused.correct_arrays`)."""
    c = pixel_constants.PixelConstants.of(calibration, jnp.float32)
    projection, bias, white_xyz = fused.kernel_constants(c.wiener, c.wiener_offset, c.tristimulus_weights)
    residual = fused.residual_constants(c.wiener_residual, c.tristimulus_weights, B)
    pixels = raw.shape[0] * raw.shape[1]
    return {
        "raw": np.ascontiguousarray(raw.reshape(1, pixels, B)), "pixels": pixels,
        "dark": np.asarray(c.dark).reshape(pixels, B), "white": np.asarray(c.white).reshape(pixels, B),
        "p": np.asarray(sj.patch_ratio(raw, calibration), np.float32).reshape(1, B), "coeffs": np.asarray(c.coeffs),
        "projection": np.asarray(projection), "bias": np.asarray(bias), "white_xyz": np.asarray(white_xyz),
        "residual": tuple(np.asarray(x) for x in residual),
    }


def test_the_kernel_refuses_residual_widths_that_are_not_whole_vectors(near_the_frame):
    _, _, cut, raw = near_the_frame
    arrays = _direct_arrays(cut, raw)
    whitening, inducing, factor, basis = arrays["residual"]
    out = (np.empty((1, arrays["pixels"], 31), np.float32), np.empty((1, arrays["pixels"], 3), np.float32),
           np.empty((1, arrays["pixels"]), np.uint8))
    with pytest.raises(ValueError, match="whitening and inducing rows in eights"):
        fused.correct_arrays(arrays["raw"], arrays["dark"], arrays["white"], arrays["p"], arrays["coeffs"],
                             arrays["projection"], arrays["bias"], arrays["white_xyz"], None, fused.GENERIC, out, 1,
                             residual=(whitening, inducing[:22], factor[:22], basis))


def test_gradients_with_respect_to_the_residual_are_finite(calibrations):
    _, kernel, raw = calibrations

    def loss(calibration):
        return jnp.nanmean(sj.correct(raw, calibration).reflectance)

    grads = eqx.filter_grad(loss)(kernel)
    weights = np.asarray(grads.wiener_residual.weights)
    assert np.isfinite(weights).all() and np.abs(weights).max() > 0


def test_gradients_with_respect_to_the_residual_are_finite_beside_an_unusable_image(calibrations):
    """A stack of two frames, the second's patch saturated (p NaN: every pixel flagged 8): the
    gradient with respect to the residual's weights is finite and is the first frame's alone (the
    kernel of NaN responses made it NaN before the safe-where in equations.pixel_outputs)."""
    _, kernel, raw = calibrations
    box = kernel.patch_box
    unusable = np.array(raw)
    unusable[box[0]:box[1], box[2]:box[3]] = 65535
    stack = np.stack([np.asarray(raw), unusable])

    def loss(calibration, frames):
        return jnp.nansum(sj.correct(frames, calibration).reflectance)

    result = sj.correct(stack, kernel)
    assert (np.asarray(result.quality[1]) & sj.Quality.PATCH_UNUSABLE).all()
    both = np.asarray(eqx.filter_grad(loss)(kernel, stack).wiener_residual.weights)
    first = np.asarray(eqx.filter_grad(loss)(kernel, stack[:1]).wiener_residual.weights)
    assert np.isfinite(both).all() and np.abs(first).max() > 0
    np.testing.assert_allclose(both, first, rtol=1e-5, atol=1e-6)


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
        jnp.asarray(rng.normal(scale=0.01, size=(31, 8)) @ rng.normal(size=(8, 16)), jnp.float32),  # rank 8: the fused kernel's
    )
    kernel = dataclasses.replace(affine, wiener_residual=residual)
    raw = (dark + rng.uniform(0.2, 0.8, (H, W, B)) * (white - dark)).astype(np.uint16)
    plan = sj.plan(kernel, raw.shape, dtype=raw.dtype)
    # The fused kernel's direct route: every variant applies the residual (AVX-512, AVX2, generic).
    assert fused.variant().name in fused._fused_correct.capabilities()["residual_variants"]
    assert plan.kernel_mode == fused.variant().name and plan.route == "direct"
    got = np.asarray(sj.correct(raw, kernel).reflectance, np.float64)
    v = np.asarray(sj.correct(raw, kernel, intermediates=True).v_stage2, np.float64)
    np.testing.assert_allclose(got, numpy_kernel_estimate(v, kernel), atol=2e-5)

    # The same residual built from NumPy arrays: its fields become jax.Arrays, so the calibration
    # names its device and takes the same route with the same bits (before: its plan had no
    # device, took the whole-program route, copying the frames and faulting fresh output pages
    # every call, 1.7x the time at 64 inducing points).
    from_numpy = estimation.KernelResidual(*(np.asarray(x) for x in (residual.centre, residual.whitening,
                                                                     residual.inducing, residual.weights)))
    assert all(isinstance(x, jax.Array) for x in jax.tree_util.tree_leaves(from_numpy))
    numpy_built = dataclasses.replace(affine, wiener_residual=from_numpy)
    assert sj.plan(numpy_built, raw.shape, dtype=raw.dtype).route == "direct"
    np.testing.assert_array_equal(np.asarray(sj.correct(raw, numpy_built).reflectance), got.astype(np.float32))


def test_a_residual_that_is_not_a_kernel_residual_is_refused(calibrations):
    affine, kernel, _ = calibrations
    with pytest.raises(ValueError, match=r"wiener_residual: expected an estimation.KernelResidual or None, got dict"):
        dataclasses.replace(affine, wiener_residual={"weights": kernel.wiener_residual.weights})


def test_the_kernel_refuses_a_residual_without_whitening_and_shapes_that_do_not_match(near_the_frame):
    """Both entries check the residual below the Python one: the CPython entry refuses inducing
    rows without whitening rows, the XLA handler residual arrays of the wrong shape."""
    _, _, cut, raw = near_the_frame
    arrays = _direct_arrays(cut, raw)
    whitening, inducing, factor, basis = arrays["residual"]
    pixels = arrays["pixels"]
    out = (np.empty((1, pixels, 31), np.float32), np.empty((1, pixels, 3), np.float32), np.empty((1, pixels), np.uint8))
    inputs = (arrays["raw"], True, arrays["dark"], arrays["white"], arrays["p"], arrays["coeffs"], arrays["projection"],
              arrays["bias"], arrays["white_xyz"])
    with pytest.raises(ValueError, match="^residual: inducing points without a whitening$"):
        fused._fused_correct.correct_arrays(*inputs, whitening[:0], inducing, factor, basis, 1, pixels, B, 0,
                                            inducing.shape[0], float("nan"), 0, 1, *out)
    assert fused.register()
    out_types = (jax.ShapeDtypeStruct((1, pixels, 31), jnp.float32), jax.ShapeDtypeStruct((1, pixels, 3), jnp.float32),
                 jax.ShapeDtypeStruct((1, pixels), jnp.uint8))
    ffi = jax.ffi.ffi_call(fused.TARGET, out_types)
    with pytest.raises(Exception, match=r"residual: shapes do not match raw \(N, P, B\)"):
        jax.block_until_ready(ffi(arrays["raw"], *inputs[2:], whitening, inducing, factor[:, :4], basis,
                                  saturation=np.float32(np.nan), variant=np.int32(0)))



def test_the_plan_reads_what_the_fused_kernel_declares(near_the_frame, monkeypatch):
    """The kernel contract: the plan takes the fused kernel for a kernel calibration only where the
    compiled kernel declares that its variant applies a residual (`fused.capabilities`), and says
    why not otherwise."""
    from spherejax._engine import kernels

    _, _, cut, raw = near_the_frame
    declared = fused.capabilities()
    assert set(declared["residual_variants"]) == set(fused.VARIANTS) and declared["residual_rank"] == fused.RESIDUAL_RANK
    variant = fused.mode(raw.dtype, np.float32, cut.bands)
    assert sj.plan(cut, raw.shape, dtype=raw.dtype).kernel_mode == variant
    without = {**declared, "residual_variants": tuple(v for v in declared["residual_variants"] if v != variant)}
    monkeypatch.setattr(fused, "capabilities", lambda: without)
    kernel, reason = kernels.choose(fused.AUTO, raw.dtype, np.float32, cut.bands, cut.wiener_residual, True, jax.devices("cpu")[0])
    assert kernel == kernels.DEFINITION and reason == f"the fused kernel's {variant} code does not apply a kernel residual"
    assert kernels.choose(fused.AUTO, raw.dtype, np.float32, cut.bands, None, True, jax.devices("cpu")[0]) == (
        kernels.FusedCpu(variant), None)
