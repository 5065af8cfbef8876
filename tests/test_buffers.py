"""spherejax._engine.buffers: `correct` reuses the memory of outputs the caller dropped, and of its own
staging of NumPy frames, and never of anything still in use; NumPy frames go to the fused kernel
directly (`Plan._correct_directly`), with the bits of the XLA path.

Outputs of 256 x 256 pixels (9 MB) are above `buffers.MIN_BYTES`, so they take this path.
"""

import os
import select
import signal
import threading
import warnings

import jax
import numpy as np
import pytest

import spherejax as sj
from spherejax import pipeline
from spherejax._engine import buffers, fused

from .helpers import cpu_only, image_program

SIZE, BANDS = 256, 16

pytestmark = [
    pytest.mark.skipif(not fused.enabled(), reason="the reuse is part of the fused CPU kernel's path"),
    cpu_only("correct reuses outputs' memory, stages NumPy frames and hands them to the fused kernel "
             "only for arrays on the CPU (spherejax._engine.plan: its routes, buffers.stageable)"),
]


@pytest.fixture(autouse=True)
def empty_pool():
    buffers.release()
    yield
    buffers.release()


@pytest.fixture(scope="module")
def calibration():
    rng = np.random.default_rng(0)
    dark = (100.0 + rng.normal(0, 2, (SIZE, SIZE, BANDS))).astype(np.float32)
    white = (dark + rng.uniform(9000, 11000, (SIZE, SIZE, BANDS))).astype(np.float32)
    patch = np.zeros((SIZE, SIZE), bool)
    patch[4:20, 4:20] = True
    return sj.Calibration(
        dark=dark, white=white, patch=patch, coeffs=np.asarray(sj.identity_coeffs(BANDS, np.float32)),
        wiener=rng.uniform(0, 0.1, (31, BANDS)).astype(np.float32), saturation=16383.0,
    )


def _frames(count, seed=1):
    rng = np.random.default_rng(seed)
    frames = rng.integers(200, 12000, (count, SIZE, SIZE, BANDS)).astype(np.uint16)
    frames[:, 7, 9, 3] = 16383  # a saturated pixel in each
    return list(frames)


def _reference(raw, calibration):
    """The same program without any reuse."""
    kernel_mode = fused.mode(raw.dtype, np.float32, BANDS)
    result = image_program(raw, calibration, kernel_mode)
    return {name: np.array(getattr(result, name)) for name in ("reflectance", "lab", "quality", "p")}


def _same(result, reference):
    for name, want in reference.items():
        np.testing.assert_array_equal(np.asarray(getattr(result, name)), want, err_msg=name)


def test_a_plain_loop_reuses_memory_and_gives_the_same_bits(calibration):
    frames = _frames(5)
    pointers = []
    for raw in frames:
        result = sj.correct(raw, calibration)
        _same(result, _reference(raw, calibration))
        pointers.append(result.reflectance.unsafe_buffer_pointer())
    # From the third call on, the outputs of the call before the last are reused.
    assert pointers[2] == pointers[0] and pointers[3] == pointers[1] and pointers[3] == pointers[1] and pointers[4] == pointers[2]
    assert buffers.kept() == 2


@pytest.mark.parametrize("switch", ["0", "portable"])
def test_the_jax_numpy_path_and_float64_reuse_too(calibration, monkeypatch, switch):
    monkeypatch.setenv(fused.SWITCH, switch)
    frames = _frames(4, seed=6)
    kernel_mode = fused.mode(np.uint16, np.float32, BANDS)
    for raw in frames:
        result = sj.correct(raw, calibration)
        plain = image_program(raw, calibration, kernel_mode)
        for name in ("reflectance", "lab", "quality"):
            np.testing.assert_array_equal(np.asarray(getattr(result, name)), np.asarray(getattr(plain, name)), err_msg=name)
    calibration64 = sj.Calibration(
        dark=np.asarray(calibration.dark, np.float64), white=np.asarray(calibration.white, np.float64),
        patch=calibration.patch, coeffs=np.asarray(calibration.coeffs, np.float64),
        wiener=np.asarray(calibration.wiener, np.float64), saturation=16383.0,
    )
    pointers = []
    for raw in frames:
        result = sj.correct(raw, calibration64)
        assert result.reflectance.dtype == np.float64
        pointers.append(result.reflectance.unsafe_buffer_pointer())
    assert pointers[2] == pointers[0] and pointers[3] == pointers[1]


def test_results_the_caller_keeps_are_never_overwritten(calibration):
    frames = _frames(5, seed=2)
    results = [sj.correct(raw, calibration) for raw in frames]
    for raw, result in zip(frames, results):
        _same(result, _reference(raw, calibration))
    assert len({r.reflectance.unsafe_buffer_pointer() for r in results}) == 5


def test_views_and_single_outputs_that_are_kept_are_not_reused(calibration):
    frames = _frames(6, seed=3)
    lab_view = np.asarray(sj.correct(frames[0], calibration).lab)  # the result is dropped, a view kept
    reflectance = sj.correct(frames[1], calibration).reflectance  # one output kept
    lab_copy, reflectance_copy = lab_view.copy(), np.array(reflectance)
    for raw in frames[2:]:
        sj.correct(raw, calibration)
    np.testing.assert_array_equal(lab_view, lab_copy)
    np.testing.assert_array_equal(np.asarray(reflectance), reflectance_copy)


def test_the_callers_frames_are_read_not_kept(calibration):
    raw = _frames(1, seed=4)[0]
    before = raw.copy()
    result = sj.correct(raw, calibration)
    np.testing.assert_array_equal(raw, before)
    raw[:] = 0  # the caller reuses its array: the result must not change
    _same(result, _reference(before, calibration))


def test_calls_in_flight_and_threads(calibration):
    frames = _frames(8, seed=5)
    # Dispatched without waiting: each call's staged frames and outputs are in use until done.
    results = [sj.correct(raw, calibration) for raw in frames[:4]]
    for raw, result in zip(frames[:4], results):
        _same(result, _reference(raw, calibration))
    del results
    errors = []

    def work(indices):
        try:
            for i in indices:
                for _ in range(2):
                    result = sj.correct(frames[i], calibration)
                    _same(result, _reference(frames[i], calibration))
        except AssertionError as error:  # pragma: no cover - the failure is reported below
            errors.append(error)

    threads = [threading.Thread(target=work, args=(range(k, 8, 2),)) for k in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors, errors[0]


def test_small_images_and_traced_calls_keep_nothing(calibration):
    small = sj.Calibration(
        dark=np.asarray(calibration.dark)[:32, :32], white=np.asarray(calibration.white)[:32, :32],
        patch=np.asarray(calibration.patch)[:32, :32], coeffs=calibration.coeffs, wiener=calibration.wiener,
        saturation=16383.0,
    )
    sj.correct(_frames(1)[0][:32, :32], small)
    assert buffers.kept() == 0
    jax.jit(lambda r: sj.correct(r, calibration).lab)(_frames(1)[0])
    assert buffers.kept() == 0
    sj.correct(_frames(1)[0], calibration)
    assert buffers.kept() == 1
    buffers.release()
    assert buffers.kept() == 0


def test_aligned_staging():
    array = buffers._aligned_empty((3, 5, 7), np.uint16)
    assert array.ctypes.data % buffers.ALIGNMENT == 0 and array.shape == (3, 5, 7) and array.flags.c_contiguous


@pytest.mark.parametrize("cpus", [1, 2, 3, 8])
@pytest.mark.parametrize("shape", [(1021, 1033, 4), (3, 5 << 20), (1, 9 << 20), (5 << 20,)])
def test_staging_copies_in_parts_whole(monkeypatch, cpus, shape):
    """The staging copy, split among threads over the first axis, copies every element, for
    first axes that the parts do not divide, shorter than the number of parts, or 1-D."""
    monkeypatch.setattr(buffers, "cpus", lambda: cpus)
    source = np.random.default_rng(cpus).integers(0, 1 << 16, shape, dtype=np.uint16)
    destination = np.zeros_like(source)
    monkeypatch.setattr(buffers, "_copiers", None)
    buffers._copy_in_parts(destination, source)
    np.testing.assert_array_equal(destination, source)
    split = cpus > 1 and shape[0] > 1 and source.nbytes >= 2 * buffers.COPY_PART_BYTES
    assert (buffers._copiers is not None) == split


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this platform")
def test_a_forked_child_stages_with_threads_of_its_own():
    """After fork the parent's copying threads do not exist in the child: a child that stages
    a frame must not wait on them (it would hang; the parent's pool is made first here)."""
    source = np.arange(3 * buffers.COPY_PART_BYTES, dtype=np.uint8).reshape(6, -1)
    buffers._copy_in_parts(np.empty_like(source), source)
    read, write = os.pipe()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # fork() with threads running (Python's, JAX's warning): the point here
        pid = os.fork()
    if pid == 0:  # the child: copy, report, and leave without running the parent's atexit hooks
        os.close(read)
        ok = False
        try:
            destination = np.empty_like(source)
            buffers._copy_in_parts(destination, source)
            ok = bool(np.array_equal(destination, source))
        finally:
            os.write(write, b"1" if ok else b"0")
            os._exit(0)
    os.close(write)
    ready, _, _ = select.select([read], [], [], 30)
    try:
        assert ready, "the forked child's staging copy did not finish within 30 s"
        assert os.read(read, 1) == b"1"
    finally:
        os.close(read)
        if not ready:
            os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)


def test_kept_memory_is_bounded(calibration, monkeypatch):
    one_set = SIZE * SIZE * (4 * 34 + 1)
    monkeypatch.setattr(buffers, "MAX_BYTES", int(1.5 * one_set))
    frames = _frames(3, seed=7)
    results = [sj.correct(raw, calibration) for raw in frames]
    assert buffers.kept() == 1  # the newest set only: two would exceed MAX_BYTES
    monkeypatch.setattr(buffers, "MAX_BYTES", one_set - 1)
    buffers.release()
    results.append(sj.correct(frames[0], calibration))
    assert buffers.kept() == 0  # a set larger than MAX_BYTES is not kept at all
    for raw, result in zip(frames + [frames[0]], results):
        _same(result, _reference(raw, calibration))


def test_vmap_over_frames_reuses_memory_like_the_stack(calibration):
    """`jax.vmap(lambda r: sj.correct(r, calibration))` over frames of one calibration is
    `correct` on the stack (`Plan._correct_mappable`): the same bits, and the memory of
    dropped outputs is reused, for NumPy and JAX frames alike. Before, the mapped call ran on
    tracers and kept nothing: every call wrote into fresh pages."""
    frames = np.stack(_frames(3, seed=8))
    stack = sj.correct(frames, calibration)
    want = {name: np.array(getattr(stack, name)) for name in ("reflectance", "lab", "quality", "p")}
    del stack
    buffers.release()
    mapped = jax.vmap(lambda r: sj.correct(r, calibration))
    for inputs in (frames, jax.numpy.asarray(frames), frames):
        _same(mapped(inputs), want)
        assert buffers.kept() >= 1
    lab_only = jax.vmap(lambda r: sj.correct(r, calibration).lab)
    np.testing.assert_array_equal(np.asarray(lab_only(frames)), want["lab"])
    # Under jit the mapping is traced: XLA owns the memory, nothing is kept, the numbers are the
    # same up to float32 rounding (XLA folds the closed-over calibration's constant products).
    buffers.release()
    jitted = jax.jit(lab_only)(frames)
    assert buffers.kept() == 0
    np.testing.assert_array_equal(np.isnan(np.asarray(jitted)), np.isnan(want["lab"]))
    np.testing.assert_allclose(np.asarray(jitted), want["lab"], rtol=1e-5, atol=2e-3)


def test_derivatives_with_respect_to_frames_are_unchanged_by_the_mapping(calibration):
    """`correct` of traced frames and a concrete calibration goes through a custom_vmap, which
    has no transpose; its custom_jvp must keep `jax.grad` with respect to the frames, alone and
    under vmap, equal to that of the plain program."""
    # 64 x 64 frames: the mapping applies whatever the size (a traced call keeps nothing).
    size = 64
    calibration = sj.Calibration(
        dark=np.asarray(calibration.dark)[:size, :size], white=np.asarray(calibration.white)[:size, :size],
        patch=np.asarray(calibration.patch)[:size, :size], coeffs=calibration.coeffs, wiener=calibration.wiener,
        saturation=16383.0,
    )
    frames = np.stack(_frames(2, seed=9))[:, :size, :size].astype(np.float32)
    kernel_mode = fused.mode(np.float32, np.float32, BANDS)

    def loss_of(correct):
        def loss(raw):
            lab = correct(raw).lab
            return jax.numpy.sum(jax.numpy.where(jax.numpy.isfinite(lab), lab, 0.0) ** 2) * 1e-6
        return loss

    through_correct = loss_of(lambda raw: sj.correct(raw, calibration))
    plain = loss_of(lambda raw: image_program(raw, calibration, kernel_mode))
    for got, want in (
        (jax.grad(through_correct)(frames[0]), jax.grad(plain)(frames[0])),
        (jax.vmap(jax.grad(through_correct))(frames), jax.vmap(jax.grad(plain))(frames)),
        (jax.grad(lambda f: jax.vmap(through_correct)(f).sum())(frames), jax.grad(lambda f: jax.vmap(plain)(f).sum())(frames)),
    ):
        got, want = np.asarray(got), np.asarray(want)
        assert np.isfinite(got).all() and np.abs(got).max() > 0
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-9)


# ------------------------------------------------------------------------------ the direct path


def _calls_of(monkeypatch, module, name):
    """Counts the calls of module.name (still calling it)."""
    calls = []
    original = getattr(module, name)

    def counted(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, counted)
    return calls


@pytest.mark.parametrize("mode", ["auto", "portable"])
@pytest.mark.parametrize("batch", [(), (2,)], ids=["image", "batch"])
@pytest.mark.parametrize("raw_dtype", [np.uint16, np.float32])
def test_numpy_frames_go_to_the_kernel_directly_with_the_bits_of_the_xla_path(calibration, monkeypatch, mode, batch, raw_dtype):
    """NumPy frames are read in place by the kernel (`fused.correct_arrays`), never staged into
    XLA's memory, and give what the same frames as a jax.Array give through XLA, bit for bit:
    saturated, non-finite and patch pixels included."""
    monkeypatch.setenv(fused.SWITCH, mode)
    rng = np.random.default_rng(11)
    raw = rng.integers(200, 12000, (*batch, SIZE, SIZE, BANDS)).astype(raw_dtype)
    raw[..., 7, 9, 3] = 16383  # saturated
    raw[..., 5, 5, 2] = 16383  # saturated, in the patch: left out of p
    if raw_dtype == np.float32:
        raw[..., 30, 40, 0] = np.nan
        raw[..., 31, 41, 5] = np.inf
    direct = _calls_of(monkeypatch, fused, "correct_arrays")
    staged = _calls_of(monkeypatch, buffers, "stage")
    result = sj.correct(raw, calibration)
    assert len(direct) == 1 and not staged
    through_xla = sj.correct(jax.numpy.asarray(raw), calibration)
    assert len(direct) == 1
    for name in ("reflectance", "lab", "quality", "p"):
        got, want = np.asarray(getattr(result, name)), np.asarray(getattr(through_xla, name))
        assert got.shape == want.shape and got.dtype == want.dtype, name
        np.testing.assert_array_equal(got, want, err_msg=name)
    quality = np.asarray(result.quality)
    # The two saturated pixels (one of them in the patch: left out of p, flagged all the same),
    # and with floats the NaN and the inf.
    assert (quality != 0).sum() == (4 if raw_dtype == np.float32 else 2) * max(1, int(np.prod(batch)))


def test_frames_the_kernel_cannot_read_in_place_take_the_xla_path(calibration, monkeypatch):
    """A strided view, a dtype the kernel does not read, a float64 calibration: not direct, and
    the strided view gives the contiguous frames' numbers."""
    frames = np.stack(_frames(2, seed=12), axis=0)
    direct = _calls_of(monkeypatch, fused, "correct_arrays")
    wide = np.zeros((SIZE, SIZE, 2 * BANDS), np.uint16)
    wide[..., ::2] = frames[0]
    strided = wide[..., ::2]  # image 0 as an (H, W, B) view that is not C-contiguous
    assert not strided.flags.c_contiguous
    _same(sj.correct(strided, calibration), _reference(np.ascontiguousarray(strided), calibration))
    sj.correct(frames[0].astype(np.int32), calibration)
    calibration64 = sj.Calibration(
        dark=np.asarray(calibration.dark, np.float64), white=np.asarray(calibration.white, np.float64),
        patch=calibration.patch, coeffs=calibration.coeffs, wiener=calibration.wiener, saturation=16383.0,
    )
    sj.correct(frames[0], calibration64)
    assert not direct
    sj.correct(frames[0], calibration)
    assert len(direct) == 1


def test_the_direct_kernel_refuses_what_it_cannot_read():
    """dtypes and shapes are checked before the kernel runs; the extension checks every buffer's
    size itself, so that a wrong call cannot read or write past a buffer."""
    images, pixels, bands = 1, 64, BANDS
    good = dict(
        raw=np.zeros((images, pixels, bands), np.uint16), dark=np.zeros((pixels, bands), np.float32),
        white=np.ones((pixels, bands), np.float32), p=np.ones((images, bands), np.float32),
        coeffs=np.zeros((bands, 4), np.float32), projection=np.zeros((bands, 34), np.float32),
        bias=np.zeros(34, np.float32), white_xyz=np.ones(3, np.float32),
    )
    out = (np.empty((images, pixels, 31), np.float32), np.empty((images, pixels, 3), np.float32),
           np.empty((images, pixels), np.uint8))
    fused.correct_arrays(**good, saturation=None, kernel_mode="auto", out=out, threads=2)
    assert (out[2] == 0).all() and np.isfinite(out[0]).all()
    with pytest.raises(ValueError, match=r"dark: expected a C-contiguous float32 array of shape \(64, 16\), got float64"):
        fused.correct_arrays(**{**good, "dark": good["dark"].astype(np.float64)}, saturation=None, kernel_mode="auto", out=out, threads=2)
    with pytest.raises(ValueError, match=r"lab: expected a C-contiguous float32 array of shape \(1, 64, 3\)"):
        fused.correct_arrays(**good, saturation=None, kernel_mode="auto", out=(out[0], out[1][:, :32], out[2]), threads=2)
    no_residual = (np.asarray(x) for x in fused.residual_constants(None, None, bands))
    arguments = [good["raw"], True, *(good[k] for k in ("dark", "white", "p", "coeffs", "projection", "bias", "white_xyz")),
                 *no_residual, images, pixels, bands, 0, 0, float("nan"), False, 2, *out]
    arguments[14] = 2 * pixels  # pixels the buffers do not hold
    with pytest.raises(ValueError, match="buffer sizes do not match"):
        fused._fused_correct.correct_arrays(*arguments)


def test_numpy_and_jax_frames_of_two_shapes_in_turn_all_reuse_memory(calibration):
    """NumPy output memory (the direct path) and XLA's outputs count their shapes apart: a loop
    over a NumPy frame, the same frame as a jax.Array and a NumPy stack of two would otherwise
    keep three shapes in a pool of two, each evicting another, so that no call reused anything."""
    frames = _frames(2, seed=13)
    single, as_jax, stack = frames[0], jax.numpy.asarray(frames[1]), np.stack(frames)
    pointers = {"single": [], "jax": [], "stack": []}
    for _ in range(4):
        for name, raw in (("single", single), ("jax", as_jax), ("stack", stack)):
            result = sj.correct(raw, calibration)
            pointers[name].append(result.reflectance.unsafe_buffer_pointer())
            del result
    for name, seen in pointers.items():
        # Each call's outputs are dropped before the next call of its kind: the memory of the
        # call before comes back from the second call on, or at the latest from the third.
        assert seen[2] in seen[:2] and seen[3] in seen[:2], name
