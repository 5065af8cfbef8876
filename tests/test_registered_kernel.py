"""The fused CPU kernel with its registration inside its loop (kernel/call.cc, register_bands_first;
kernel/registered_rows.cc): concrete frames with a calibration that has band maps are registered row
by row into a buffer of each thread's and corrected from there, never written as registered frames.
Checked against the jax.numpy definition (`band_resampling` then the definition's correction) on
every variant this CPU runs, for uint16 and float32 raw, stacks of images, band counts with and
without code of their own, flagged pixels of every kind, and p from the patch's read box."""

from __future__ import annotations

import functools

import jax
import numpy as np
import pytest

import spherejax as sj
from spherejax._engine import fused, registered
from spherejax._engine.plan import Plan

H, W = 37, 70  # W not a multiple of the kernel's 32-pixel blocks, H not of its 32-row chunks

compiled = pytest.mark.skipif(not registered.fused_registration.applies(np.uint16, np.float32, 16),
                              reason="the fused kernel is not built here (no C++ compiler at install)")


def maps_of(bands, rng, reach=2.0):
    """(bands, 2, 3) maps: a small scale and rotation about the centre and a shift of up to `reach`
    pixels per band; band 1 a whole-pixel shift (its right and lower taps weigh 0)."""
    angle, scale = 6e-4, 1.0006
    linear = scale * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    centre = np.array([(W - 1) / 2.0, (H - 1) / 2.0])
    maps = np.zeros((bands, 2, 3))
    maps[:, :, :2] = linear
    maps[:, :, 2] = centre - linear @ centre + rng.uniform(-reach, reach, (bands, 2))
    maps[1, :, :2] = np.eye(2)
    maps[1, :, 2] = [1.0, -2.0]
    return maps


def calibration(bands, rng, saturation=60000.0):
    dark = rng.uniform(90, 110, (H, W, bands)).astype(np.float32)
    white = (rng.uniform(18000, 22000, (1, 1, bands)) * rng.uniform(0.97, 1.03, (H, W, 1))).astype(np.float32)
    white[6, 9, 2] = 50.0  # no flat field: flags the registered pixels whose taps reach it
    patch = np.zeros((H, W), bool)
    patch[14:22, 30:40] = True
    coeffs = np.tile(np.array([0.02, 1.0, -0.01, 0.001], np.float32), (bands, 1))
    wiener = (rng.uniform(0, 1, (31, bands)) / bands).astype(np.float32)
    return sj.Calibration(dark, white, patch, coeffs, wiener, saturation=saturation,
                          band_transforms=maps_of(bands, rng))


def frames(bands, rng, images, dtype):
    raw = rng.uniform(2000, 18000, (images, H, W, bands))
    raw[0, 20, 33, 3] = 60000.0  # saturated, inside the patch: p leaves its registered pixels out
    raw[-1, 30, 50, 0] = 65000.0
    if dtype == np.float32:
        raw[-1, 8, 60, 4] = np.nan
    return raw.astype(dtype)


def plans(calibration, raw, mode):
    return registered.RegisteredPlan(calibration, raw.shape, raw.dtype,
                                     make_plan=lambda c, s, d: Plan(c, s, d, kernel_mode=mode))


def check_against_the_definition(calibration, raw, variant, monkeypatch):
    calls = []
    original = fused.correct_arrays

    def spy(*args, registration=None, **kwargs):
        calls.append(registration is not None)
        return original(*args, registration=registration, **kwargs)

    monkeypatch.setattr(fused, "correct_arrays", spy)
    plan, definition = plans(calibration, raw, variant), plans(calibration, raw, None)
    assert plan.direct and not definition.direct
    got, want = plan(raw), definition(raw)
    assert calls == [True]  # one kernel call, with the registration inside it
    quality = np.asarray(want.quality)
    np.testing.assert_array_equal(np.asarray(got.quality), quality)
    np.testing.assert_allclose(np.asarray(got.p), np.asarray(want.p), rtol=2e-6)
    good = quality == 0
    assert 0.5 < good.mean() < 1
    np.testing.assert_allclose(np.asarray(got.reflectance)[good], np.asarray(want.reflectance)[good],
                               rtol=1e-5, atol=2e-6)
    np.testing.assert_allclose(np.asarray(got.lab)[good], np.asarray(want.lab)[good], rtol=1e-4, atol=2e-3)
    assert np.all(np.isnan(np.asarray(got.lab)[~good]))
    return quality


@compiled
@pytest.mark.parametrize("variant", fused.supported_variants())
@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_every_variant_registers_rows_as_the_definition(variant, dtype, monkeypatch):
    """16 bands (the AVX-512, AVX2 and generic samplers, whichever the variant allows), two
    images: the same bits on every pixel, the same values to float rounding."""
    rng = np.random.default_rng(11)
    quality = check_against_the_definition(calibration(16, rng), frames(16, rng, 2, dtype), variant, monkeypatch)
    expected = [sj.QUALITY_SATURATED, sj.QUALITY_WHITE_NOT_ABOVE_DARK, sj.QUALITY_NOT_COVERED]
    expected += [sj.QUALITY_NONFINITE] if dtype == np.float32 else []
    assert all(np.any(quality & bit) for bit in expected)


@compiled
@pytest.mark.parametrize("bands", [5, 17])
def test_band_counts_without_code_of_their_own(bands, monkeypatch):
    rng = np.random.default_rng(bands)
    check_against_the_definition(calibration(bands, rng), frames(bands, rng, 1, np.uint16), fused.AUTO,
                                 monkeypatch)


@compiled
def test_jax_arrays_numpy_frames_and_jit_agree():
    """A concrete jax.Array takes the kernel's route as NumPy frames do; under `jax.jit` the frames
    are traced and take the registration pass and the kernel after it: the same numbers."""
    rng = np.random.default_rng(5)
    cal = calibration(16, rng)
    raw = frames(16, rng, 1, np.uint16)[0]
    numpy_result = sj.correct(raw, cal)
    array_result = sj.correct(jax.numpy.asarray(raw), cal)
    jitted = jax.jit(functools.partial(sj.correct, calibration=cal))(raw)
    np.testing.assert_array_equal(np.asarray(array_result.quality), np.asarray(numpy_result.quality))
    np.testing.assert_array_equal(np.asarray(array_result.lab), np.asarray(numpy_result.lab))
    np.testing.assert_array_equal(np.asarray(jitted.quality), np.asarray(numpy_result.quality))
    np.testing.assert_allclose(np.asarray(jitted.lab), np.asarray(numpy_result.lab), rtol=1e-4, atol=2e-3)


@compiled
def test_p_from_the_patch_read_box_is_the_whole_frames():
    """p of concrete frames comes from the native pixels around the patch only (the calibration's
    crop to `band_resampling.read_box`): the p of the registered whole frames."""
    rng = np.random.default_rng(8)
    cal = calibration(16, rng)
    raw = frames(16, rng, 2, np.uint16)
    plan = sj.plan(cal, raw.shape)
    box = plan._patch  # made at the first call
    whole, _ = plan.register(raw)
    np.testing.assert_allclose(np.asarray(plan.patch_ratio(raw)), np.asarray(plan.inner.patch_ratio(whole)),
                               rtol=2e-6)
    assert box is None and plan._patch[0] != (0, H, 0, W)


@compiled
def test_strips_through_the_kernel_give_the_whole_frames_rows():
    """Rows with their halo (`spherejax.stripwise`'s way) corrected by the kernel with the whole
    image's p: the whole frame's rows, bits and values."""
    rng = np.random.default_rng(9)
    cal = calibration(16, rng)
    raw = frames(16, rng, 1, np.uint16)[0]
    whole = sj.correct(raw, cal)
    n0, n1 = 10, 31
    strip = sj.correct(np.ascontiguousarray(raw[n0:n1]), cal.rows(n0, n1), p=whole.p)
    keep = slice(4, 17)  # rows 14:27, beyond the maps' reach of the strip's edges
    np.testing.assert_array_equal(np.asarray(strip.quality)[keep], np.asarray(whole.quality)[14:27])
    np.testing.assert_allclose(np.asarray(strip.lab)[keep], np.asarray(whole.lab)[14:27], rtol=1e-5, atol=1e-3)


@compiled
def test_registration_arrays_of_the_wrong_shape_are_refused_in_one_line():
    """`fused.correct_arrays(registration=...)` names the array, its dtype and shape and the one
    expected, and writes nothing into the outputs."""
    rng = np.random.default_rng(12)
    cal = calibration(16, rng)
    raw = frames(16, rng, 1, np.uint16)[0]
    plan = sj.plan(cal, raw.shape)
    plan(raw)  # makes the plan's arrays
    dark, inverse, maps, saturation = plan._native
    k = plan.inner._direct
    out = (np.full((1, H * W, 31), 7.0, np.float32), np.full((1, H * W, 3), 7.0, np.float32),
           np.full((1, H * W), 7, np.uint8))
    for wrong, name in (((inverse, maps[:15], H, W), "maps"), ((inverse[:-1], maps, H, W), "inverse_signal")):
        with pytest.raises(ValueError, match=f"^{name}: expected a C-contiguous float32 array of shape") as error:
            fused.correct_arrays(raw.reshape(1, H * W, 16), dark, k["white"], np.ones((1, 16), np.float32),
                                 k["coeffs"], k["projection"], k["bias"], k["white_xyz"], saturation, fused.AUTO, out,
                                 threads=1, residual=k["residual"], registration=wrong)
        assert "\n" not in str(error.value)
    assert all(np.all(x == 7) for x in out)
