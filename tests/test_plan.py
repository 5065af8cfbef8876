"""`spherejax.plan`: the correction prepared once per calibration and frame shape, which every
route of `correct` goes through (spherejax/_engine/plan.py)."""

import dataclasses
import pickle
import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax._engine import fused
from spherejax._engine import plan as plans
from spherejax.pixel_constants import PixelConstants

from .helpers import image_program

BANDS = 16


def make_calibration(size, dtype=np.float32, seed=0, patch_at=(10, 30)):
    rng = np.random.default_rng(seed)
    dark = rng.uniform(95, 105, (size, size, BANDS))
    white = dark + rng.uniform(8000, 12000, (size, size, BANDS))
    white[3, 4, 5] = dark[3, 4, 5]  # no flat field there
    patch = np.zeros((size, size), bool)
    patch[patch_at[0]:patch_at[1], patch_at[0]:patch_at[1]] = True
    return sj.Calibration(
        dark=dark.astype(dtype), white=white.astype(dtype), patch=patch,
        coeffs=(np.asarray(sj.identity_coeffs(BANDS, np.float64)) + rng.normal(0, 0.01, (BANDS, 4))).astype(dtype),
        wiener=rng.uniform(0, 0.08, (31, BANDS)).astype(dtype), saturation=16383.0,
        wiener_offset=rng.uniform(-0.02, 0.02, 31).astype(dtype),
    )


def make_frames(calibration, batch=(), seed=1, dtype=np.uint16):
    rng = np.random.default_rng(seed)
    dark, white = np.asarray(calibration.dark, np.float64), np.asarray(calibration.white, np.float64)
    raw = np.rint(dark + (white - dark) * rng.uniform(0.05, 0.95, (*batch, *dark.shape)))
    raw[..., 7, 9, 3] = 16383  # saturated
    return raw.astype(dtype)


def assert_same_bits(got, want, names=("reflectance", "lab", "quality", "p")):
    for name in names:
        np.testing.assert_array_equal(np.asarray(getattr(got, name)), np.asarray(getattr(want, name)), err_msg=name)


@pytest.fixture(scope="module")
def large():
    """256 x 256 x 16: outputs of 9 MB, large enough for the reusing routes on CPU."""
    return make_calibration(256)


def test_the_plan_is_made_once_per_calibration_and_frame_shape(large):
    raw = make_frames(large)
    first = sj.plan(large, raw.shape, dtype=raw.dtype)
    assert sj.plan(large, raw.shape, dtype=raw.dtype) is first
    sj.correct(raw, large)
    assert sj.plan(large, raw.shape, dtype=raw.dtype) is first  # what correct used
    assert sj.plan(large, (2, *raw.shape), dtype=raw.dtype) is not first
    assert sj.plan(large, raw.shape, dtype=np.float32) is not first
    other = dataclasses.replace(large, coeffs=large.coeffs * 1.0)  # a new calibration: its own plans
    assert sj.plan(other, raw.shape, dtype=raw.dtype) is not first


@pytest.mark.parametrize("kind", ["numpy uint16", "jax uint16", "numpy float32", "jax float64"])
def test_every_route_of_a_plan_gives_the_programs_bits(large, kind):
    """Each route (the kernel on NumPy frames, reused outputs, the plain program) against the
    whole-frame program on constants made afresh."""
    raw = make_frames(large, dtype=np.float64 if "float64" in kind else np.float32 if "float32" in kind else np.uint16)
    prepared = sj.plan(large, raw.shape, dtype=raw.dtype)
    if kind == "numpy uint16" and fused.enabled() and jax.default_backend() == "cpu":
        assert prepared.route == plans.DIRECT
    frames = raw if kind.startswith("numpy") else jnp.asarray(raw)
    want = image_program(raw, large, prepared.kernel_mode)
    for _ in range(3):  # the third call reuses the first call's outputs' memory
        assert_same_bits(prepared(frames), want)
        assert_same_bits(sj.correct(frames, large), want)


def test_a_plan_holds_the_constants_cast_once_on_the_calibrations_device(large):
    raw = make_frames(large)
    prepared = sj.plan(large, raw.shape, dtype=raw.dtype)
    assert isinstance(prepared.constants, PixelConstants)
    arrays = jax.tree_util.tree_leaves(prepared.constants)  # every array it holds (no kernel residual here)
    assert len(arrays) == len(dataclasses.fields(PixelConstants)) - 1
    for array in arrays:
        assert array.dtype == np.float32 and array.devices() == large.dark.devices()
    np.testing.assert_array_equal(np.asarray(prepared.constants.tristimulus_weights),
                                  np.asarray(sj.colorimetry.tristimulus_weights("D65"), np.float32))
    assert prepared.box == large.patch_box == (10, 30, 10, 30)
    np.testing.assert_array_equal(np.asarray(prepared.patch.weights), np.ones((20, 20), np.float32))
    # float64 frames compute in float64, with their own constants
    wide = sj.plan(large, raw.shape, dtype=np.float64)
    assert wide.constants.dtype == np.float64 and wide.kernel_mode is None


def test_strips_intermediates_and_uncertainty_go_through_the_plan(large):
    raw = make_frames(large, seed=3)
    prepared = sj.plan(large, raw.shape, dtype=raw.dtype)
    whole = sj.correct(raw, large, intermediates=True)
    assert_same_bits(prepared(raw, intermediates=True), whole, ("reflectance", "lab", "quality", "p", "v", "v_stage2"))
    p = prepared.patch_ratio(raw)
    np.testing.assert_array_equal(np.asarray(p), np.asarray(sj.patch_ratio(raw, large)))
    rows = sj.correct(raw[100:164], large.rows(100, 164), p=p)
    for name in ("reflectance", "lab", "quality"):
        np.testing.assert_array_equal(np.asarray(getattr(rows, name)), np.asarray(getattr(whole, name))[100:164])
    noise = sj.NoiseModel(read_noise=np.full(BANDS, 2.0), gain=np.full(BANDS, 0.5))
    with_u = prepared(raw, noise=noise)
    assert_same_bits(with_u, sj.correct(raw, large, noise=noise), ("reflectance", "lab", "reflectance_u", "lab_u", "p_u"))
    np.testing.assert_array_equal(np.asarray(with_u.p_u), np.asarray(prepared.patch_ratio_u(raw, noise)))


def test_vmap_and_gradients_through_a_plan(large):
    small = make_calibration(48, patch_at=(4, 12))
    frames = make_frames(small, batch=(3,), seed=5).astype(np.float32)
    single = sj.plan(small, frames.shape[1:], dtype=frames.dtype)
    stacked = jax.vmap(single)(frames)
    assert_same_bits(stacked, sj.correct(frames, small))

    def loss(prepared_or_program, raw):
        lab = prepared_or_program(raw).lab
        return jnp.sum(jnp.where(jnp.isfinite(lab), lab, 0.0) ** 2) * 1e-6

    got = jax.grad(lambda r: loss(single, r))(frames[0])
    want = jax.grad(lambda r: loss(lambda x: image_program(x, small, single.kernel_mode), r))(frames[0])
    assert np.isfinite(np.asarray(got)).all() and np.abs(np.asarray(got)).max() > 0
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-9)

    # With respect to the calibration: the plan is built inside the trace, and nothing is kept.
    def loss_of_coeffs(coeffs):
        return loss(lambda raw: sj.correct(raw, dataclasses.replace(small, coeffs=coeffs)), frames[0])

    gradient = np.asarray(jax.grad(loss_of_coeffs)(small.coeffs))
    step = 1e-3
    bumped = np.asarray(small.coeffs).copy()
    bumped[2, 1] += step
    finite_difference = (loss_of_coeffs(jnp.asarray(bumped)) - loss_of_coeffs(small.coeffs)) / step
    np.testing.assert_allclose(gradient[2, 1], finite_difference, rtol=2e-2)


def test_float64_calibrations_compute_in_float64(large):
    wide = make_calibration(64, dtype=np.float64, patch_at=(4, 20))
    raw = make_frames(wide, seed=8)
    prepared = sj.plan(wide, raw.shape, dtype=raw.dtype)
    result = prepared(raw)
    assert result.reflectance.dtype == np.float64 and prepared.kernel_mode is None
    assert_same_bits(result, image_program(raw, wide, None))


def test_the_kernel_switch_takes_effect_at_the_next_call(large, monkeypatch):
    if not fused.enabled():
        pytest.skip(f"the fused kernel is not in use here: {fused.unavailable_reason()}")
    raw = make_frames(large, seed=11)
    with_kernel = sj.correct(raw, large)
    monkeypatch.setenv(fused.SWITCH, "0")
    without = sj.correct(raw, large)
    assert sj.plan(large, raw.shape, dtype=raw.dtype).kernel_mode is None
    assert_same_bits(without, image_program(raw, large, None))
    np.testing.assert_allclose(np.asarray(without.reflectance), np.asarray(with_kernel.reflectance), rtol=2e-5, atol=2e-6)


def test_plans_are_not_pickled_and_a_calibration_keeps_a_few():
    calibration = make_calibration(32, patch_at=(2, 8))
    for images in range(1, 12):
        sj.plan(calibration, (images, 32, 32, BANDS), dtype=np.uint16)
    assert len(calibration.__dict__["_plans"]) == 8  # the last eight shapes
    restored = pickle.loads(pickle.dumps(calibration))
    assert "_plans" not in restored.__dict__ and "_patch_box" not in restored.__dict__
    raw = make_frames(calibration, seed=2)
    assert_same_bits(sj.correct(raw, restored), sj.correct(raw, calibration))


def test_threads_share_one_plan(large):
    calibration = make_calibration(128, seed=4)
    raw = make_frames(calibration, seed=6)
    results, seen = [None] * 4, [None] * 4

    def work(k):
        results[k] = sj.correct(raw, calibration)
        seen[k] = sj.plan(calibration, raw.shape, dtype=raw.dtype)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert all(plan is seen[0] for plan in seen)
    for result in results[1:]:
        assert_same_bits(result, results[0])


def test_a_kept_plan_is_found_before_anything_is_worked_out(monkeypatch):
    """The second call of a shape finds its plan by the frames' shape and dtype and the kernels'
    switches alone: the calibration's device, dtypes and kernel mode are worked out once (they
    cost about 0.2 ms a call, benchmarks/bench_call_overhead.py); a device-resident frame is not
    converted again. A switch set between calls still takes effect (another key)."""
    calibration = make_calibration(32, seed=3)
    raw = jnp.asarray(make_frames(calibration, seed=5))
    first = sj.correct(raw, calibration)

    def worked_out(*args):
        raise AssertionError("worked out again for a kept plan")

    monkeypatch.setattr(plans, "_device_of", worked_out)
    monkeypatch.setattr(plans, "_concrete", worked_out)
    monkeypatch.setattr(jnp, "asarray", worked_out)
    assert_same_bits(sj.correct(raw, calibration), first)
    monkeypatch.setenv(fused.SWITCH, "0")
    with pytest.raises(AssertionError, match="worked out again"):
        sj.correct(raw, calibration)


@pytest.mark.parametrize("shape, dtype, message", [
    ((256, 256), np.uint16, r"shape: expected \(H, W, B\) or \(\.\.\., H, W, B\) with H, W, B = \(256, 256, 16\), got \(256, 256\)"),
    ((256, 255, 16), np.uint16, r"shape: expected .* got \(256, 255, 16\)"),
    ("256x256", np.uint16, r"shape: expected .*"),
    ((256, 256, 16), np.complex64, "dtype: expected integer counts or floats, got complex64"),
    ((256, 256, 16), "not a dtype", "dtype: expected a NumPy dtype, got 'not a dtype'"),
])
def test_plan_refuses_what_it_cannot_prepare(large, shape, dtype, message):
    with pytest.raises(ValueError, match=message):
        sj.plan(large, shape, dtype=dtype)


def test_plan_refuses_what_is_not_a_calibration():
    with pytest.raises(ValueError, match="calibration: expected a spherejax.Calibration, got dict"):
        sj.plan({}, (4, 4, 16))


def test_a_dropped_calibration_is_freed_with_its_plans_at_once():
    """A calibration keeps its plans and a plan refers to its calibration weakly: no reference
    cycle, so dropping the calibration frees both (and their frames) without waiting for the
    cycle collector."""
    import gc
    import weakref

    calibration = make_calibration(128, seed=9)
    raw = make_frames(calibration, seed=10)
    sj.correct(raw, calibration)
    prepared = weakref.ref(sj.plan(calibration, raw.shape, dtype=raw.dtype))
    gone = weakref.ref(calibration)
    gc.disable()
    try:
        del calibration
        assert gone() is None and prepared() is None
    finally:
        gc.enable()
