"""The speed-ups of the per-pixel path (benchmarks/README.md, "Where the time of `correct` goes") against the plain forms they replace.

Each fast form is checked against the straightforward one it stands for: the NaN-row projection
against `where(good, v @ M, nan)` (values and gradients), the exp/log cube root against
`jnp.cbrt`, the min/max flat-field flag against `any` over the bands, and `correct` as a whole
against the path written out plainly from the equations. The allocator setting is checked by
what it is for: page faults of a repeated correction.
"""

import functools
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax import colorimetry, equations, pipeline
from spherejax._engine import allocator, cpu_blocks, fused, gpu_kernel, steps
from spherejax._engine.plan import plan_for
from spherejax.flatfield import white_signal_usable
from spherejax.pixel_constants import PixelConstants

from .helpers import cpu_only, image_program, ulp_bound

HIGHEST = jax.lax.Precision.HIGHEST


def plain_projection(good, v, matrix, bias):
    return jnp.where(good, jnp.matmul(v, matrix, precision=HIGHEST) + bias, jnp.nan)


class TestProjectGoodPixels:
    @pytest.mark.parametrize("bias_kind", ["zeros", "random"])
    @pytest.mark.parametrize("matrix_kind", ["random", "zeros"])
    def test_equals_the_masked_product(self, dtype, matrix_kind, bias_kind):
        rng = np.random.default_rng(0)
        v = jnp.asarray(rng.uniform(0, 1, (7, 9, 16)), dtype)
        good = jnp.asarray(rng.random((7, 9, 1)) > 0.3)
        v = jnp.where(good, v, 0.0)  # the safe-where convention of the caller
        matrix = jnp.asarray(rng.normal(size=(16, 31)) if matrix_kind == "random" else np.zeros((16, 31)), dtype)
        bias = jnp.asarray(rng.normal(size=31) if bias_kind == "random" else np.zeros(31), dtype)
        fast = np.asarray(equations.project_good_pixels(good, v, matrix, bias))
        plain = np.asarray(plain_projection(good, v, matrix, bias))
        assert np.isnan(fast[~np.asarray(good)[..., 0]]).all()  # NaN in every channel, even x 0
        np.testing.assert_array_equal(np.isnan(fast), np.isnan(plain))
        np.testing.assert_allclose(fast, plain, rtol=1e-6 if dtype == np.float32 else 1e-13)
        if bias_kind == "zeros":
            # A zero offset leaves the product's bits as they were before the offset existed.
            unbiased = np.asarray(jnp.matmul(jnp.where(good, v, jnp.nan), matrix, precision=HIGHEST))
            np.testing.assert_array_equal(fast, unbiased)

    def test_gradients_equal_the_masked_product(self):
        rng = np.random.default_rng(1)
        v = jnp.asarray(rng.uniform(0, 1, (40, 16)))
        good = jnp.asarray(rng.random((40, 1)) > 0.25)
        v = jnp.where(good, v, 0.0)
        matrix = jnp.asarray(rng.normal(size=(16, 3)))
        bias = jnp.asarray(rng.normal(size=3))
        weights = jnp.asarray(rng.normal(size=(40, 3)))

        def loss(projection, v, matrix, bias):
            out = projection(good, v, matrix, bias)
            return jnp.sum(jnp.where(good, out, 0.0) * weights)

        fast = jax.grad(lambda *a: loss(equations.project_good_pixels, *a), argnums=(0, 1, 2))(v, matrix, bias)
        plain = jax.grad(lambda *a: loss(plain_projection, *a), argnums=(0, 1, 2))(v, matrix, bias)
        for f, p in zip(fast, plain):
            assert np.isfinite(np.asarray(f)).all()
            np.testing.assert_allclose(np.asarray(f), np.asarray(p), rtol=1e-12, atol=1e-15)


class TestCubeRoot:
    def test_agrees_with_cbrt(self, dtype):
        x = np.geomspace(1e-6, 1e6, 20001).astype(dtype)
        fast = np.asarray(colorimetry._cube_root_positive(jnp.asarray(x)))
        exact = np.cbrt(x.astype(np.float64))
        ulp = np.spacing(exact.astype(dtype)).astype(np.float64)
        # float64: the Newton correction is evaluated in float64 itself, so its own rounding
        # (y*y, the division, the subtraction) leaves up to 3 ulp; which points reach 3 depends
        # on the CPU's exp/log code (AVX2 here, 0.1 % of points; 2 ulp on AVX-512 machines).
        # float32 on a GPU: 1.07 ulp measured (an H200, jax 0.11.2; the Newton step's division is
        # a reciprocal and a multiply there): 1.25 on any backend but the CPU.
        float32_bound = ulp_bound(cpu=1, gpu=1.25)
        assert np.max(np.abs(fast - exact) / ulp) <= {np.float32: float32_bound, np.float64: 3}[dtype]

    def test_lab_of_the_whites_and_greys(self, dtype):
        """Exact points: the white is L* 100 and Y/Yn = 1/8 is L* 116/2 - 16 = 42."""
        white = jnp.asarray([95.047, 100.0, 108.883], dtype)
        lab = np.asarray(sj.xyz_to_lab(jnp.stack([white, white / 8]), white))
        tolerance = 2e-5 if dtype == np.float32 else 1e-12
        np.testing.assert_allclose(lab[:, 0], [100.0, 42.0], atol=tolerance)
        np.testing.assert_allclose(lab[:, 1:], 0.0, atol=tolerance)


class TestNoFlatField:
    def test_equals_any_over_the_bands(self, dtype):
        rng = np.random.default_rng(2)
        dark = rng.uniform(90, 110, (64, 16)).astype(dtype)
        white = (dark + rng.uniform(-50, 1000, (64, 16))).astype(dtype)
        specials = [np.nan, np.inf, -np.inf, 0.0]
        for row in range(0, 64, 3):
            band = rng.integers(0, 16)
            target = white if row % 2 else dark
            target[row, band] = specials[row % 4]
        white[5] = dark[5]  # white == dark in every band
        # NaN in the first, a middle and the last band: a vectorised minimum may drop NaN
        # depending on where it sits (YNNPACK's does).
        white[[7, 8, 10], [0, 15, 9]] = np.nan
        fast = np.asarray(equations.flat_field_unusable(jnp.asarray(dark), jnp.asarray(white)))
        plain = np.asarray(jnp.any(~white_signal_usable(jnp.asarray(dark), jnp.asarray(white)), axis=-1))
        np.testing.assert_array_equal(fast, plain)
        assert 0 < fast.sum() < 64

    def test_correct_remembers_each_calibrations_flags(self, monkeypatch):
        """The jax.numpy path of `correct` on large frames reads the no-flat-field flags from
        its plan (`spherejax._engine.plan`), worked out once for each calibration and frame shape: two
        calibrations that share their dark frame, used in turn, each get their own flags, and
        the same bits as the program that works the flags out itself."""
        rng = np.random.default_rng(8)
        height, width, bands = 256, 256, 16  # outputs of 9 MB: `correct` reuses their memory
        dark_frame = rng.uniform(95, 105, (height, width, bands)).astype(np.float32)
        whites = [dark_frame + rng.uniform(8000, 12000, dark_frame.shape).astype(np.float32) for _ in range(2)]
        whites[0][10, 20, 3] = dark_frame[10, 20, 3]  # white == dark
        whites[1][200, 30, 15] = dark_frame[200, 30, 15] - 1.0
        whites[1][40, 250, 0] = np.nan
        dark = jnp.asarray(dark_frame)
        expected = [{(10, 20)}, {(200, 30), (40, 250)}]
        patch = np.zeros((height, width), bool)
        patch[100:120, 100:120] = True
        coeffs = np.asarray(sj.identity_coeffs(bands, np.float32))
        wiener = rng.uniform(0, 0.1, (31, bands)).astype(np.float32)
        calibrations = [
            sj.Calibration(dark=dark, white=white, patch=patch, coeffs=coeffs, wiener=wiener, saturation=16383.0)
            for white in whites
        ]
        assert calibrations[0].dark is calibrations[1].dark
        raw = np.rint(dark_frame + 5000 * rng.uniform(0.05, 0.95, dark.shape)).astype(np.uint16)
        monkeypatch.setenv(fused.SWITCH, "0")
        monkeypatch.setenv(gpu_kernel.SWITCH, "0")  # on a GPU the jax.numpy path too
        for turn in range(4):
            calibration, bad = calibrations[turn % 2], expected[turn % 2]
            result = sj.correct(raw, calibration)
            flagged = np.argwhere(np.asarray(result.quality) & sj.QUALITY_WHITE_NOT_ABOVE_DARK)
            assert set(map(tuple, flagged.tolist())) == bad
            inline = image_program(raw, calibration, None)
            for name in ("reflectance", "lab", "quality"):
                np.testing.assert_array_equal(np.asarray(getattr(result, name)), np.asarray(getattr(inline, name)), err_msg=name)
        remembered = sj.plan(calibrations[0], raw.shape, dtype=raw.dtype).no_flat_field
        assert remembered is not None and sj.plan(calibrations[0], raw.shape, dtype=raw.dtype).no_flat_field is remembered
        assert sj.plan(calibrations[1], raw.shape, dtype=raw.dtype).no_flat_field is not remembered


def plain_correct(raw, calibration, p):
    """The per-pixel path as the equations read, with one `where` per output (no fast forms)."""
    dtype = np.float64
    raw_f = jnp.asarray(raw, dtype)
    dark, white = jnp.asarray(calibration.dark, dtype), jnp.asarray(calibration.white, dtype)
    usable = white_signal_usable(dark, white)
    saturated = jnp.any(jnp.isfinite(raw_f) & (raw_f >= calibration.saturation), axis=-1)
    nonfinite = jnp.any(~jnp.isfinite(raw_f), axis=-1)
    no_flat_field = jnp.any(~usable, axis=-1)
    bits = [(saturated, sj.QUALITY_SATURATED), (nonfinite, sj.QUALITY_NONFINITE),
            (no_flat_field, sj.QUALITY_WHITE_NOT_ABOVE_DARK)]
    quality = sum(np.where(np.asarray(flag), bit, 0) for flag, bit in bits).astype(np.uint8)
    good = (quality == 0)[..., None]
    v = sj.flat_field(raw_f, dark, white)
    v_tilde = sj.stage2(v, p, calibration.coeffs)
    reflectance = jnp.where(good, sj.wiener(v_tilde, calibration.wiener) + calibration.wiener_offset, jnp.nan)
    lab = jnp.where(good, sj.reflectance_to_lab(jnp.where(good, reflectance, 0.0), calibration.illuminant), jnp.nan)
    return reflectance, lab, quality


@pytest.mark.parametrize("with_offset", [False, True])
def test_correct_equals_the_plain_path_with_bad_pixels(with_offset):
    rng = np.random.default_rng(3)
    H, W, B = 24, 30, 16
    dark = rng.uniform(95, 105, (H, W, B))
    white = dark + rng.uniform(8000, 12000, (H, W, B))
    raw = np.rint(dark + (white - dark) * rng.uniform(0.05, 0.95, (H, W, B)))
    raw[3, 4, 5] = 16383.0
    raw[6, 7, 0] = np.nan
    raw[8, 9, 15] = -np.inf
    white[10, 11, 2] = dark[10, 11, 2]
    white[12, 13, 3] = np.nan
    raw[12, 13, 4] = 16383.0  # saturated and no flat field: both bits
    patch = np.zeros((H, W), bool)
    patch[18:22, 20:26] = True
    calibration = sj.Calibration(
        dark=dark, white=white, patch=patch, coeffs=np.asarray(sj.identity_coeffs(B, np.float64)),
        wiener=rng.normal(0, 0.3, (31, B)), illuminant="D65", saturation=16383.0,
        wiener_offset=rng.uniform(-0.05, 0.05, 31) if with_offset else np.zeros(31),
    )
    result = sj.correct(raw, calibration)
    reflectance, lab, quality = plain_correct(raw, calibration, result.p)
    np.testing.assert_array_equal(np.asarray(result.quality), np.asarray(quality))
    assert np.asarray(result.quality)[12, 13] == sj.QUALITY_SATURATED | sj.QUALITY_WHITE_NOT_ABOVE_DARK
    assert (np.asarray(quality) != 0).sum() == 5
    np.testing.assert_allclose(np.asarray(result.reflectance), np.asarray(reflectance), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(result.lab), np.asarray(lab), rtol=1e-10, atol=1e-10)


FAULTS_SCRIPT = textwrap.dedent("""
    import resource, sys
    import numpy as np
    import spherejax as sj
    from spherejax._engine import buffers
    from spherejax._engine.allocator import keep_freed_memory
    applied = keep_freed_memory() if sys.argv[1] == "reuse" else False
    release = sys.argv[2] == "release"  # drop spherejax's kept outputs: glibc alone decides
    import jax
    size, bands = 768, 16
    rng = np.random.default_rng(0)
    dark = np.full((size, size, bands), 100.0, np.float32)
    white = dark + 10000.0
    raw = (dark + 5000.0 * rng.uniform(0.2, 0.9, (size, size, bands))).astype(np.uint16)
    patch = np.zeros((size, size), bool); patch[8:40, 8:40] = True
    calibration = sj.Calibration(dark=dark, white=white, patch=patch,
                                 coeffs=np.asarray(sj.identity_coeffs(bands, np.float32)),
                                 wiener=np.full((31, bands), 1.0 / bands, np.float32), saturation=16383.0)
    raw = jax.numpy.asarray(raw)
    for _ in range(3):
        jax.block_until_ready(sj.correct(raw, calibration))
    faults = []
    for _ in range(9):
        if release:
            buffers.release()
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        jax.block_until_ready(sj.correct(raw, calibration))
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    print(applied, int(np.median(faults)))
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc settings are Linux-only")
@cpu_only("page faults of XLA's CPU buffers, which come from glibc malloc, and spherejax's reuse of them")
def test_repeated_corrections_do_not_page_fault_by_default_nor_with_the_setting():
    """A 768 x 768 correction writes blocks above glibc's mmap threshold (32 MiB; the reflectance
    is 73 MB). By default `correct` reuses the memory of outputs the caller dropped
    (`spherejax._engine.buffers`), so a repeated call in a plain loop touches no fresh page, with no
    process-wide setting. With those kept outputs released before every call, glibc unmaps the
    freed blocks and every call faults them in again, unless `keep_freed_memory` is on.

    The median call is compared, not the mean: XLA's threads allocate in a varying order, so the
    single heap now and then grows once more (about 18 000 pages in one call of a dozen, seen on
    the CI machine as a mean of 5 761 a call over five)."""
    def median_faults(mode, release):
        out = subprocess.run([sys.executable, "-c", FAULTS_SCRIPT, mode, release], capture_output=True, text=True, check=True)
        applied, count = out.stdout.split()
        assert applied == str(mode == "reuse")
        return int(count)

    faults = {}
    for mode, release in (("default", "keep"), ("default", "release"), ("reuse", "release")):
        faults[mode, release] = median_faults(mode, release)
    # With the setting, which glibc arena each of XLA's threads gets is decided as they start,
    # and on a loaded machine one process in a few has every call fault its outputs in (CI, the
    # oldest set under the full suite: 17 856 a call; alone, the same environment passed every
    # time). The property is that the setting lets a process reuse freed memory: the best of
    # three fresh processes is held to the bound.
    for _ in range(2):
        if faults["reuse", "release"] < 500:
            break
        faults["reuse", "release"] = min(faults["reuse", "release"], median_faults("reuse", "release"))
    assert faults["default", "keep"] < 500, faults  # spherejax reuses its outputs' memory
    assert faults["default", "release"] > 15000, faults  # the reflectance alone is 18 000 pages
    assert faults["reuse", "release"] < 500, faults


@cpu_only("the jax.numpy path's block loop, which runs on CPU only")
@pytest.mark.parametrize("dtype_name", ["float32", "float64"])
def test_the_jax_numpy_path_has_no_image_sized_temporaries(monkeypatch, dtype_name):
    """The jax.numpy path (kernel off, or float64) on CPU runs in blocks of pixels (`cpu_blocks`)
    and writes its outputs into the memory of dropped ones (`steps.image_step_into`). On the
    whole image its Stage II cube (38 MB in float32 at 768 x 768 x 16) and its projections were
    temporaries of every call, allocated and faulted afresh (19,587 pages a call in float32,
    39,170 in float64).

    Checked on the program `correct` runs (the plan's compiled `image_step_into`), by XLA's own
    buffer assignment: its temporaries stay within the two blocks a turn of its loop corrects,
    under half the Stage II cube, and its outputs alias the donated arrays. The whole-image program of the
    same equations is measured beside it, so the check sees temporaries when they are there.
    (This replaces a count of page faults in a child process, which depends on how glibc trims
    its heap and ranged from 0 to 106,000 pages a call between machines and test runs.)"""
    monkeypatch.setenv(fused.SWITCH, "0")
    dtype = np.dtype(dtype_name)
    size, bands = 768, 16
    dark = np.full((size, size, bands), 100.0, dtype)
    patch = np.zeros((size, size), bool)
    patch[8:40, 8:40] = True
    calibration = sj.Calibration(dark=dark, white=dark + 10000.0, patch=patch,
                                 coeffs=np.asarray(sj.identity_coeffs(bands, dtype)),
                                 wiener=np.full((31, bands), 1.0 / bands, dtype), saturation=16383.0)
    plan = plan_for(calibration, (size, size, bands), np.dtype(np.uint16))
    assert plan.kernel_mode is None  # the jax.numpy path
    blocked = plan._into_executable().memory_analysis()

    cube = size * size * bands * dtype.itemsize  # the Stage II cube, the smallest temporary it had
    outputs = size * size * (31 + 3) * dtype.itemsize + size * size  # reflectance, Lab, quality
    # Each turn of the loop corrects two blocks side by side, about 100 values a pixel each.
    two_blocks = 2 * cpu_blocks.CPU_BLOCK_PIXELS * 100 * dtype.itemsize
    assert blocked.temp_size_in_bytes <= two_blocks < cube / 2, (blocked.temp_size_in_bytes, two_blocks)
    assert blocked.alias_size_in_bytes >= outputs  # the outputs are the donated arrays

    whole = jax.jit(functools.partial(equations.pixel_outputs, saturation=16383.0, intermediates=False)).lower(
        jax.ShapeDtypeStruct((size, size, bands), np.uint16), jax.ShapeDtypeStruct((bands,), dtype), plan.constants,
    ).compile().memory_analysis()
    assert whole.temp_size_in_bytes >= cube, whole.temp_size_in_bytes


def outputs(raw, dark, white, p, coeffs, wiener, offset, weights, **options):
    """`equations.pixel_outputs` with its constants given one by one."""
    return equations.pixel_outputs(raw, p, PixelConstants(dark, white, coeffs, wiener, offset, weights), **options)


def blocks(raw, dark, white, p, coeffs, wiener, offset, weights, **options):
    """`cpu_blocks.pixel_outputs_in_blocks` with its constants given one by one."""
    return cpu_blocks.pixel_outputs_in_blocks(raw, p, PixelConstants(dark, white, coeffs, wiener, offset, weights), **options)


def test_keep_freed_memory_is_idempotent():
    first = allocator.keep_freed_memory()
    assert allocator.keep_freed_memory() is first


class TestBlocks:
    """`cpu_blocks.pixel_outputs_in_blocks`, the jax.numpy path as it runs on CPU, against the
    whole-image `_pixel_outputs` it loops over: every pixel, a last block shorter than the
    others, batches, bad pixels of every kind, donated outputs, and derivatives."""

    @staticmethod
    def inputs(dtype, batch=(), height=130, width=170, bands=16, raw_dtype=np.uint16, seed=0):
        rng = np.random.default_rng(seed)
        dark = rng.uniform(95, 105, (height, width, bands))
        white = dark + rng.uniform(8000, 12000, (height, width, bands))
        raw = np.rint(dark + (white - dark) * rng.uniform(0.05, 0.95, (*batch, height, width, bands)))
        raw[..., 3, 4, 5] = 16383.0
        white[10, 11, 2] = dark[10, 11, 2]  # no flat field
        if raw_dtype == np.float32:
            raw[..., 6, 7, 0] = np.nan
            raw[..., 120, 160, 9] = np.inf
        p = rng.uniform(0.9, 1.1, (*batch, bands))
        coeffs = np.asarray(sj.identity_coeffs(bands, np.float64)) + rng.normal(0, 0.02, (bands, 4))
        wiener = rng.normal(0, 0.3, (31, bands))
        offset = rng.uniform(-0.05, 0.05, 31)
        weights = np.asarray(colorimetry.tristimulus_weights("D65"))
        floats = (dark, white, p, coeffs, wiener, offset, weights)
        return (jnp.asarray(raw.astype(raw_dtype)), *(jnp.asarray(x, dtype) for x in floats))

    @staticmethod
    def assert_same(blocked, whole, dtype):
        # On a GPU the blocks and the whole image are other fusions of the same ops, rounded
        # apart: 23 of 198,900 float32 Lab values of the batch differed by up to 1.5e-5 (1.6e-5
        # relative) on an H100 with jax 0.11.2. float64 there: not measured, kept tight.
        tolerance = ulp_bound(1e-6, 3e-5) if dtype == np.float32 else 1e-13
        names = ("reflectance", "lab", "quality")
        for name, got, want in zip(names, blocked, whole):
            got, want = np.asarray(got), np.asarray(want)
            assert got.shape == want.shape and got.dtype == want.dtype, name
            np.testing.assert_array_equal(np.isnan(got), np.isnan(want), err_msg=name)
            np.testing.assert_allclose(got, want, rtol=tolerance, atol=tolerance, err_msg=name)

    @pytest.mark.parametrize("batch", [(), (3,)], ids=["image", "batch"])
    @pytest.mark.parametrize("raw_dtype", [np.uint16, np.float32])
    def test_equals_the_whole_image(self, dtype, batch, raw_dtype):
        arrays = self.inputs(dtype, batch, raw_dtype=raw_dtype)
        whole = jax.jit(lambda *a: outputs(*a, saturation=16383.0))(*arrays)
        # 22 100 pixels an image: 5 blocks of 4 096 (two a turn of the loop, the odd one after it)
        # and one of 1 620; 3 images: 16 blocks of 1 365 rows each (8 turns) and one of 260.
        blocked = jax.jit(lambda *a: blocks(*a, saturation=16383.0, block_pixels=4096))(*arrays)
        self.assert_same(blocked, whole, dtype)
        quality = np.asarray(blocked[2])
        assert (quality != 0).sum() == (4 if raw_dtype == np.float32 else 2) * max(1, int(np.prod(batch)))
        assert np.isfinite(np.asarray(blocked[0])[quality == 0]).all()

    def test_donated_outputs_are_written_whatever_they_held(self, dtype):
        arrays = self.inputs(dtype)
        whole = jax.jit(lambda *a: outputs(*a, saturation=16383.0))(*arrays)
        garbage = tuple(jnp.full_like(x, 7) for x in whole)
        pointers = [x.unsafe_buffer_pointer() for x in garbage]
        into = jax.jit(
            lambda out, *a: blocks(*a, saturation=16383.0, out=out, block_pixels=4096),
            donate_argnums=0,
        )
        blocked = into(garbage, *arrays)
        self.assert_same(blocked, whole, dtype)
        assert [x.unsafe_buffer_pointer() for x in blocked] == pointers  # written in place
        assert all(x.is_deleted() for x in garbage)

    def test_small_images_take_the_whole_image_path(self):
        arrays = self.inputs(np.float32, height=20, width=30)
        program = jax.jit(lambda *a: blocks(*a, saturation=16383.0, block_pixels=4096))
        assert "while" not in program.lower(*arrays).as_text()
        assert "while" in jax.jit(
            lambda *a: blocks(*a, saturation=16383.0, block_pixels=64)
        ).lower(*arrays).as_text()

    def test_derivatives_equal_the_whole_images(self):
        arrays = self.inputs(np.float64, height=40, width=50)
        raw, dark, white, p, coeffs, wiener, offset, weights = arrays

        def loss(outputs_of, coeffs, wiener, p):
            reflectance, lab, quality = outputs_of(raw, dark, white, p, coeffs, wiener, offset, weights, saturation=16383.0)
            good = (quality == 0)[..., None]
            return jnp.sum(jnp.where(good, lab, 0.0) ** 2) + jnp.sum(jnp.where(good, reflectance, 0.0))

        blocked = functools.partial(blocks, block_pixels=300)
        grad = jax.jit(jax.grad(loss, argnums=(1, 2, 3)), static_argnums=0)
        for got, want in zip(grad(blocked, coeffs, wiener, p), grad(outputs, coeffs, wiener, p)):
            assert np.all(np.isfinite(got))
            np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-9)
        forward = jax.jit(lambda c: jax.jvp(lambda c: blocked(*arrays[:4], c, *arrays[5:], saturation=16383.0)[1], (c,), (jnp.ones_like(c),))[1])
        plain = jax.jit(lambda c: jax.jvp(lambda c: outputs(*arrays[:4], c, *arrays[5:], saturation=16383.0)[1], (c,), (jnp.ones_like(c),))[1])
        np.testing.assert_allclose(forward(coeffs), plain(coeffs), rtol=1e-10, atol=1e-9)

    @cpu_only("correct lowers the block loop for the CPU only (jax.lax.platform_dependent), and the fused kernel is CPU-only")
    def test_correct_runs_in_blocks_on_cpu_and_agrees_with_the_kernel(self, monkeypatch):
        """An image above CPU_BLOCK_PIXELS through `correct` with the kernel off, against the kernel."""
        rng = np.random.default_rng(4)
        height, width, bands = 288, 128, 16  # 36 864 pixels: two whole blocks (one loop turn) and a short one
        assert height * width > 2 * cpu_blocks.CPU_BLOCK_PIXELS
        dark = rng.uniform(95, 105, (height, width, bands)).astype(np.float32)
        white = (dark + rng.uniform(8000, 12000, (height, width, bands))).astype(np.float32)
        raw = np.rint(dark + (white - dark) * rng.uniform(0.05, 0.95, (height, width, bands))).astype(np.uint16)
        raw[100, 120, 3] = 16383
        patch = np.zeros((height, width), bool)
        patch[4:20, 4:20] = True
        calibration = sj.Calibration(
            dark=dark, white=white, patch=patch, coeffs=np.asarray(sj.identity_coeffs(bands, np.float32)),
            wiener=rng.uniform(0, 0.1, (31, bands)).astype(np.float32), saturation=16383.0,
            wiener_offset=rng.uniform(-0.02, 0.02, 31).astype(np.float32),
        )
        kernel = sj.correct(raw, calibration)
        monkeypatch.setenv(fused.SWITCH, "0")
        lowered = jax.jit(lambda raw: image_program(raw, calibration, None)).lower(jnp.asarray(raw))
        assert "while" in lowered.as_text()
        numpy_path = sj.correct(raw, calibration)
        np.testing.assert_array_equal(np.asarray(numpy_path.quality), np.asarray(kernel.quality))
        assert np.asarray(kernel.quality)[100, 120] == sj.QUALITY_SATURATED
        np.testing.assert_allclose(np.asarray(numpy_path.reflectance), np.asarray(kernel.reflectance), rtol=2e-5, atol=2e-6)
        np.testing.assert_allclose(np.asarray(numpy_path.lab), np.asarray(kernel.lab), rtol=2e-5, atol=2e-4)
