"""The fused CPU kernel (spherejax/_engine/kernel/fused_correct.cc) against the jax.numpy path it replaces.

The jax.numpy path (`SPHEREJAX_FUSED=0`) is the definition; every branch of the kernel is
compared with it: the AVX-512 16-band code and the generic loop (other band counts), uint16 and
float32 raw, every quality bit, batches of images, several thread-pool chunks, strips, gradients
and vmap, each with a zero and a non-zero Wiener offset r0 (the kernel's bias). Values agree to float32 rounding, quality masks and NaN positions exactly.
"""

from __future__ import annotations

import platform
import re
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax._engine import fused
from spherejax.pipeline import _compute_dtype, _correct_pixels, patch_ratio
from spherejax.polynomial import PAPER_TABLE_2

from .helpers import cpu_only

SATURATION = 16383.0


def make_case(height, width, bands, *, raw_dtype=np.uint16, images=(), seed=0, saturation=SATURATION, offset=False):
    """A calibration and raw frames with every kind of bad pixel, for `bands` bands; with
    `offset`, a non-zero Wiener offset r0 of both signs (else r0 = 0)."""
    rng = np.random.default_rng(seed)
    dark = rng.uniform(95, 105, (height, width, bands)).astype(np.float32)
    white = (dark + rng.uniform(8000, 12000, (height, width, bands))).astype(np.float32)
    # Reflectances from 0.001 to 1.2: XYZ / white spans both branches of the Lab companding.
    level = np.exp(rng.uniform(np.log(1e-3), np.log(1.2), (*images, height, width, 1)))
    raw = dark + (white - dark) * level * rng.uniform(0.9, 1.1, (*images, height, width, bands))
    raw = np.clip(np.rint(raw), 0, saturation - 1)
    index = (0,) * len(images)
    raw[(*index, 3, 4, 5 % bands)] = saturation  # saturated
    white[10, 11, 2 % bands] = dark[10, 11, 2 % bands]  # white == dark
    white[12, 13, 3 % bands] = dark[12, 13, 3 % bands] - 5  # white < dark
    raw[(*index, 12, 13, 0)] = saturation  # saturated and no flat field: two bits
    # Below the dark level: by 7 % of the white signal (a dark frame 700 counts too high) ...
    dark[2, 21, 1 % bands] += 700
    raw[(*index, 2, 21, 1 % bands)] = 0
    # ... and by 0.5 %, which noise allows: not flagged.
    raw[(*index, 0, 22, 2 % bands)] = np.floor(dark[0, 22, 2 % bands] - 0.005 * (white - dark)[0, 22, 2 % bands])
    if raw_dtype == np.float32:
        white[14, 15, 1 % bands] = np.nan
        white[16, 17, 0] = np.inf
        raw[(*index, 6, 7, 0)] = np.nan
        raw[(*index, 8, 9, bands - 1)] = -np.inf
        raw[(*index, 18, 19, 0)] = np.inf
        raw[(*index, 1, 20, 0)] = -1000.0  # a raw value of -1000 counts: v about -0.11
    raw = raw.astype(raw_dtype)
    patch = np.zeros((height, width), bool)
    patch[height // 2 - 4:height // 2 + 4, width // 2 - 5:width // 2 + 5] = True
    coeffs = np.asarray(PAPER_TABLE_2[np.arange(bands) % 16], np.float32)
    wiener = (np.abs(rng.normal(0.0, 1.0, (31, bands))) / bands).astype(np.float32)
    wiener_offset = (rng.uniform(-0.05, 0.05, 31) if offset else np.zeros(31)).astype(np.float32)
    calibration = sj.Calibration(
        dark=dark, white=white, patch=patch, coeffs=coeffs, wiener=wiener, saturation=saturation,
        wiener_offset=wiener_offset,
    )
    return raw, calibration


def correct_both(monkeypatch, raw, calibration, **kwargs):
    """(with the kernel as the environment says, with the jax.numpy path)."""
    kernel = sj.correct(raw, calibration, **kwargs)
    with monkeypatch.context() as patched:
        patched.setenv(fused.SWITCH, "0")
        plain = sj.correct(raw, calibration, **kwargs)
    return kernel, plain


def assert_same_result(kernel, plain):
    quality = np.asarray(plain.quality)
    np.testing.assert_array_equal(np.asarray(kernel.quality), quality)
    np.testing.assert_array_equal(np.asarray(kernel.p), np.asarray(plain.p))
    for name, atol in (("reflectance", 2e-6), ("lab", 3e-3)):
        got, want = np.asarray(getattr(kernel, name)), np.asarray(getattr(plain, name))
        assert got.dtype == want.dtype == np.float32
        np.testing.assert_array_equal(np.isnan(got), np.broadcast_to(quality[..., None] != 0, got.shape), err_msg=name)
        np.testing.assert_allclose(got, want, rtol=2e-5, atol=atol, err_msg=name)


def lowered_text(raw, calibration, intermediates=False):
    p = patch_ratio(raw, calibration)
    mode = fused.mode(raw.dtype, _compute_dtype(raw, calibration), calibration.bands)
    return _correct_pixels.lower(raw, calibration, p, intermediates=intermediates, kernel_mode=mode).as_text()


@pytest.mark.skipif(
    not (sys.platform.startswith("linux") and platform.machine() == "x86_64"),
    reason="CI and the benchmark machines are Linux x86-64; elsewhere the build may be skipped",
)
@cpu_only("the fused kernel is an XLA CPU custom call; on another backend `correct` runs the jax.numpy path")
def test_the_kernel_was_built():
    """setup.py builds the kernel as an optional extension: a failed build must not go unnoticed
    where it is expected to work, since `correct` would silently be 3x slower."""
    assert fused.built()


pytestmark_kernel = pytest.mark.skipif(not fused.built(), reason="the fused kernel was not built")
#: Tests that need the kernel itself, not only `correct` (which on another backend compares the
#: jax.numpy path with itself): its custom call in the lowered program, or called directly.
cpu_kernel = cpu_only(
    "the fused kernel's custom call is lowered and runs for the CPU only (jax.lax.platform_dependent)"
)


@pytestmark_kernel
@cpu_kernel
@pytest.mark.parametrize("offset", [False, True], ids=["r0=0", "r0"])
@pytest.mark.parametrize("kernel_mode", [fused.AUTO, fused.PORTABLE])
@pytest.mark.parametrize("bands", [16, 7, 33])
@pytest.mark.parametrize("raw_dtype", [np.uint16, np.float32])
def test_kernel_equals_the_plain_path(monkeypatch, bands, raw_dtype, kernel_mode, offset):
    """16 bands take the AVX-512 code (on CPUs that have it, unless portable), others the
    portable loop; 96 x 100 pixels are two thread-pool chunks and a part block."""
    raw, calibration = make_case(96, 100, bands, raw_dtype=raw_dtype, offset=offset)
    monkeypatch.setenv(fused.SWITCH, kernel_mode)
    kernel, plain = correct_both(monkeypatch, raw, calibration)
    assert "spherejax_fused_correct" in lowered_text(jnp.asarray(raw), calibration)
    assert_same_result(kernel, plain)
    quality = np.asarray(kernel.quality)
    assert quality[3, 4] == sj.QUALITY_SATURATED
    assert quality[10, 11] == quality[12, 13] - sj.QUALITY_SATURATED == sj.QUALITY_WHITE_NOT_ABOVE_DARK
    assert quality[2, 21] == sj.QUALITY_BELOW_DARK and quality[0, 22] == 0
    if raw_dtype == np.float32:
        assert quality[6, 7] == quality[8, 9] == quality[18, 19] == sj.QUALITY_NONFINITE
        assert quality[14, 15] == quality[16, 17] == sj.QUALITY_WHITE_NOT_ABOVE_DARK
        assert quality[1, 20] == sj.QUALITY_BELOW_DARK
    assert (quality != 0).sum() == (10 if raw_dtype == np.float32 else 4)


@pytestmark_kernel
@pytest.mark.parametrize("offset", [False, True], ids=["r0=0", "r0"])
def test_kernel_is_as_accurate_as_the_plain_path_against_float64(monkeypatch, offset):
    """Both float32 paths against the float64 path (the float64 calibration never takes the
    kernel): the kernel's error is no worse than the plain path's, up to rounding.

    "Up to rounding" for Lab is the float32 floor of a* = 500 (f(X) - f(Y)) and b* = 200 (f(Y) -
    f(Z)): four float32 ulps of f, which no float32 path can beat. Measured with offset r0 (L*
    up to 164): the kernel 1.90e-4 (3.2 ulps of f) under every jaxlib, since it does its own
    arithmetic; the plain path 1.05e-4 under jax 0.9.2 and 8.0e-5 under 0.12 (XLA's float32 got
    more accurate), so a bound of twice the plain path's alone failed on the newest jax."""
    raw, calibration = make_case(40, 50, 16, offset=offset)
    calibration64 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float64), calibration)
    kernel, plain = correct_both(monkeypatch, raw, calibration)
    exact = sj.correct(raw, calibration64)
    assert exact.lab.dtype == jnp.float64
    good = np.asarray(exact.quality) == 0
    lab = np.asarray(exact.lab)[good]
    # The largest f(t) of the three: f(Y) = (L* + 16) / 116, f(X) and f(Z) within a*/500, b*/200 of it.
    f_max = ((lab[:, 0] + 16.0) / 116.0 + np.abs(lab[:, 1]) / 500.0 + np.abs(lab[:, 2]) / 200.0).max()
    rounding = {"reflectance": 1e-6, "lab": 500.0 * 4.0 * float(np.spacing(np.float32(f_max)))}
    for name in ("reflectance", "lab"):
        truth = np.asarray(getattr(exact, name))[good]
        err_kernel = np.abs(np.asarray(getattr(kernel, name))[good] - truth).max()
        err_plain = np.abs(np.asarray(getattr(plain, name))[good] - truth).max()
        assert err_kernel <= max(2.0 * err_plain, rounding[name]), (name, err_kernel, err_plain, rounding[name])


@pytestmark_kernel
@pytest.mark.parametrize("offset", [False, True], ids=["r0=0", "r0"])
@pytest.mark.parametrize("kernel_mode", [fused.AUTO, fused.PORTABLE])
@pytest.mark.parametrize("bands", [16, 7])
def test_kernel_batches_of_images_with_their_own_ratio(monkeypatch, bands, kernel_mode, offset):
    raw, calibration = make_case(32, 36, bands, images=(2, 3), offset=offset)
    monkeypatch.setenv(fused.SWITCH, kernel_mode)
    kernel, plain = correct_both(monkeypatch, raw, calibration)
    assert kernel.reflectance.shape == (2, 3, 32, 36, 31)
    assert kernel.p.shape == (2, 3, bands)
    assert_same_result(kernel, plain)


@pytestmark_kernel
@pytest.mark.parametrize("raw_dtype", [np.uint16, np.float32])
def test_kernel_unusable_patch_flags_the_whole_image(monkeypatch, raw_dtype):
    raw, calibration = make_case(32, 48, 16, raw_dtype=raw_dtype, offset=True)  # NaN despite r0
    p = np.asarray(patch_ratio(raw, calibration)).copy()
    p[4] = np.nan
    kernel, plain = correct_both(monkeypatch, raw, calibration, p=p)
    assert_same_result(kernel, plain)
    assert (np.asarray(kernel.quality) & sj.QUALITY_PATCH_UNUSABLE).all()


@pytestmark_kernel
@pytest.mark.parametrize("raw_dtype", [np.uint16, np.float32])
def test_kernel_without_a_saturation_level(monkeypatch, raw_dtype):
    """None: the full scale of uint16 counts (65535), and no check at all for float raw."""
    raw, calibration = make_case(24, 40, 16, raw_dtype=raw_dtype, saturation=60000.0)
    calibration = sj.Calibration(
        dark=calibration.dark, white=calibration.white, patch=calibration.patch,
        coeffs=calibration.coeffs, wiener=calibration.wiener, saturation=None,
    )
    raw[5, 6, 7] = 65535
    kernel, plain = correct_both(monkeypatch, raw, calibration)
    assert_same_result(kernel, plain)
    expected = sj.QUALITY_SATURATED if raw_dtype == np.uint16 else 0
    assert np.asarray(kernel.quality)[5, 6] == expected


def _cpu_has_avx2() -> bool:
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            return any(line.startswith("flags") and " avx2 " in line + " " and " fma " in line for line in cpuinfo)
    except OSError:
        return False


@pytestmark_kernel
@cpu_kernel
@pytest.mark.parametrize("kernel_mode", [fused.AUTO, fused.PORTABLE])
@pytest.mark.parametrize("bands", [16, 7])
def test_kernel_cube_root_against_float64(bands, kernel_mode):
    """L* of exact Y: the kernel's cube root within 3 ulp of float64's (two Halley steps, as the
    AVX-512 code and the generic loop take it), within 1 ulp on the AVX2 code's division-free
    Newton iteration (16 bands, portable, on an AVX2 CPU), and the linear branch below
    (6/29)^3 within 1 ulp; a part block of pixels.

    The problem is made so that the kernel's XYZ are its raw values exactly: dark 0, white 1,
    Stage II gain 1 and offset 0, and a projection that copies bands 0, 1, 2 to X, Y, Z.
    """
    pixels = 4 * 1024 + 7
    rng = np.random.default_rng(3)
    xyz = np.exp(rng.uniform(np.log(1e-4), np.log(1.5), (pixels, 3))).astype(np.float32)
    raw = np.zeros((1, pixels, bands), np.float32)
    raw[0, :, :3] = xyz
    coeffs = np.tile(np.float32([0.0, 1.0, 0.0, 0.0]), (bands, 1))  # v_tilde = v
    projection = np.zeros((bands, 34), np.float32)
    projection[0, 31] = projection[1, 32] = projection[2, 33] = 1.0
    white_xyz = np.float32([0.95, 1.0, 1.09])
    call = jax.jit(fused._kernel_call, static_argnames=("saturation", "kernel_mode"))
    _, lab, quality = call(
        raw, np.zeros((pixels, bands), np.float32), np.ones((pixels, bands), np.float32), np.ones((1, bands), np.float32),
        coeffs, projection, np.zeros(34, np.float32), white_xyz, saturation=None, kernel_mode=kernel_mode,
    )
    assert not np.asarray(quality).any()
    lightness = np.asarray(lab, np.float64)[0, :, 0]
    t = xyz[:, 1].astype(np.float64)  # Y / Yn, Yn = 1
    root = t > 216 / 24389
    assert root.any() and (~root).any()
    f = np.where(root, np.cbrt(t), (24389 / 27 * t + 16) / 116)
    # f back from L* = 116 f - 16, which float32 rounds once: half an ulp of L*.
    error = np.abs((lightness + 16) / 116 - f) - np.spacing(lightness.astype(np.float32)).astype(np.float64) / 2 / 116
    ulps = error / np.spacing(f.astype(np.float32)).astype(np.float64)
    newton = bands == 16 and kernel_mode == fused.PORTABLE and _cpu_has_avx2()
    assert ulps[root].max() <= (1.0 if newton else 3.0), ulps[root].max()
    assert ulps[~root].max() <= 1.0, ulps[~root].max()


@pytestmark_kernel
@pytest.mark.parametrize("offset", [False, True], ids=["r0=0", "r0"])
@pytest.mark.parametrize("kernel_mode", [fused.AUTO, fused.PORTABLE])
@pytest.mark.parametrize("bands", [16, 7])
def test_kernel_strips_equal_the_whole_image_bit_for_bit(monkeypatch, bands, kernel_mode, offset):
    """Each pixel goes through the same code wherever it lies in a block or a chunk."""
    raw, calibration = make_case(97, 101, bands, offset=offset)
    monkeypatch.setenv(fused.SWITCH, kernel_mode)
    whole = sj.correct(raw, calibration)
    p = patch_ratio(raw, calibration)
    for row0, row1 in ((0, 1), (1, 40), (40, 97), (13, 14)):
        strip = sj.correct(raw[row0:row1], calibration.rows(row0, row1), p=p)
        for name in ("reflectance", "lab", "quality"):
            np.testing.assert_array_equal(
                np.asarray(getattr(strip, name)), np.asarray(getattr(whole, name))[row0:row1]
            )


@pytestmark_kernel
@cpu_kernel
def test_kernel_gradients_are_the_plain_paths(monkeypatch):
    """The kernel's outputs carry the JVP of the jax.numpy path (fused.correct_pixels), with
    respect to the Wiener offset too."""
    raw, calibration = make_case(24, 24, 16, offset=True)

    def loss(coeffs, wiener, wiener_offset):
        cal = sj.Calibration(
            dark=calibration.dark, white=calibration.white, patch=calibration.patch, coeffs=coeffs,
            wiener=wiener, saturation=SATURATION, wiener_offset=wiener_offset,
        )
        result = sj.correct(raw, cal)
        return jnp.nansum(result.lab[..., 0]) + jnp.nansum(result.lab[..., 2]) + jnp.nansum(result.reflectance)

    grad = jax.grad(loss, argnums=(0, 1, 2))
    arguments = (calibration.coeffs, calibration.wiener, calibration.wiener_offset)
    with_kernel = grad(*arguments)
    assert "spherejax_fused_correct" in lowered_text(jnp.asarray(raw), calibration)
    monkeypatch.setenv(fused.SWITCH, "0")
    without = grad(*arguments)
    for got, want in zip(with_kernel, without):
        assert np.isfinite(np.asarray(got)).all()
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-3)
    # d(sum of reflectance)/d r0_k is the number of good pixels; Lab adds its own share.
    assert np.abs(np.asarray(with_kernel[2])).min() > 0


@pytestmark_kernel
def test_kernel_under_vmap_over_calibrations(monkeypatch):
    raw, calibration = make_case(24, 28, 16, offset=True)
    scales = jnp.asarray([0.5, 1.0, 2.0], jnp.float32)

    def lab_for(scale):
        cal = sj.Calibration(
            dark=calibration.dark, white=calibration.white, patch=calibration.patch,
            coeffs=calibration.coeffs, wiener=calibration.wiener * scale, saturation=SATURATION,
            wiener_offset=calibration.wiener_offset * scale,
        )
        return sj.correct(raw, cal).lab

    mapped = jax.vmap(lab_for)(scales)
    looped = np.stack([np.asarray(lab_for(s)) for s in scales])
    # The (B, 34) projection is a batched product under vmap: rounding differs in the last bits,
    # which a* = 500 (f_x - f_y) magnifies.
    np.testing.assert_allclose(np.asarray(mapped), looped, rtol=2e-5, atol=2e-3)
    monkeypatch.setenv(fused.SWITCH, "0")
    np.testing.assert_allclose(np.asarray(jax.vmap(lab_for)(scales)), looped, rtol=2e-5, atol=3e-3)


def test_when_the_kernel_applies(monkeypatch):
    f32, f64 = np.dtype(np.float32), np.dtype(np.float64)
    monkeypatch.delenv(fused.SWITCH, raising=False)
    if fused.built():
        assert fused.mode(np.uint16, f32, 16) == fused.AUTO
        assert fused.mode(np.float32, f32, 5) == fused.AUTO
        monkeypatch.setenv(fused.SWITCH, "1")
        assert fused.mode(np.uint16, f32, 16) == fused.AUTO
        monkeypatch.setenv(fused.SWITCH, "portable")
        assert fused.mode(np.uint16, f32, 16) == fused.PORTABLE
    assert fused.mode(np.uint16, f64, 16) is None  # float64
    assert fused.mode(np.uint8, f32, 16) is None  # raw dtype the kernel does not read
    assert fused.mode(np.uint16, f32, fused.MAX_BANDS + 1) is None
    monkeypatch.setenv(fused.SWITCH, "0")
    assert not fused.enabled()
    assert fused.mode(np.uint16, f32, 16) is None


@pytest.mark.parametrize("value", ["off", "false", "no", "", "AUTO", " 0"])
def test_an_undocumented_switch_value_is_refused(monkeypatch, value):
    """SPHEREJAX_FUSED=off used to leave the kernel on."""
    raw, calibration = make_case(24, 24, 16)
    monkeypatch.setenv(fused.SWITCH, value)
    with pytest.raises(ValueError, match=rf"SPHEREJAX_FUSED: expected one of 'auto', '1', 'portable', '0' or unset, got {re.escape(repr(value))}"):
        sj.correct(raw, calibration)


@pytestmark_kernel
@cpu_kernel
def test_intermediates_do_not_change_the_main_outputs(monkeypatch):
    """Asking for v, v_stage1, v_stage2 used to switch the kernel off, so Lab moved by up to
    1.5e-4 and reflectance was not bit-identical to the call without them."""
    monkeypatch.delenv(fused.SWITCH, raising=False)
    raw, calibration = make_case(40, 48, 16)
    plain = sj.correct(raw, calibration)
    with_cubes = sj.correct(raw, calibration, intermediates=True)
    for name in ("reflectance", "lab", "quality", "p"):
        np.testing.assert_array_equal(np.asarray(getattr(with_cubes, name)), np.asarray(getattr(plain, name)), err_msg=name)
    assert "spherejax_fused_correct" in lowered_text(jnp.asarray(raw), calibration, intermediates=True)
    monkeypatch.setenv(fused.SWITCH, "0")
    reference = sj.correct(raw, calibration, intermediates=True)
    for name in ("v", "v_stage1", "v_stage2"):
        np.testing.assert_array_equal(np.asarray(getattr(with_cubes, name)), np.asarray(getattr(reference, name)), err_msg=name)


@pytestmark_kernel
def test_switched_off_the_kernel_is_not_lowered(monkeypatch):
    raw, calibration = make_case(24, 24, 16)
    monkeypatch.setenv(fused.SWITCH, "0")
    assert "spherejax_fused_correct" not in lowered_text(jnp.asarray(raw), calibration)


@pytestmark_kernel
def test_lowered_for_a_gpu_the_jax_numpy_path_runs(monkeypatch):
    """`jax.lax.platform_dependent` keeps the CPU kernel out of a GPU program. No GPU is needed
    to check: the step is exported (lowered) for CUDA on this machine."""
    raw, calibration = make_case(24, 24, 16)
    raw = jnp.asarray(raw)
    p = patch_ratio(raw, calibration)
    mode = fused.mode(raw.dtype, _compute_dtype(raw, calibration), calibration.bands)
    assert mode == fused.AUTO

    def step(raw, calibration, p):
        return _correct_pixels(raw, calibration, p, intermediates=False, kernel_mode=mode)

    exported = jax.export.export(jax.jit(step), platforms=["cuda"])(raw, calibration, p)
    text = exported.mlir_module()
    assert "spherejax_fused_correct" not in text
    assert "dot_general" in text  # the jax.numpy path's two products


@pytestmark_kernel
@cpu_kernel
def test_kernel_under_vmap_over_frames_is_one_call_on_the_stack():
    """Frames mapped over one calibration are more images of one kernel call (the batching rule
    of `fused._kernel_call`), not one call per frame in an XLA loop that copies each frame out."""
    raw, calibration = make_case(24, 28, 16, images=(3,), offset=True)
    mapped = jax.jit(jax.vmap(lambda r: sj.correct(r, calibration)))
    text = mapped.lower(jnp.asarray(raw)).as_text()
    assert text.count("spherejax_fused_correct") == 1 and "while" not in text
    got, want = mapped(raw), sj.correct(raw, calibration)
    np.testing.assert_array_equal(np.asarray(got.quality), np.asarray(want.quality))
    # Under jit XLA folds the closed-over calibration's constant products: float32 rounding.
    np.testing.assert_allclose(np.asarray(got.lab), np.asarray(want.lab), rtol=2e-5, atol=2e-3)
    np.testing.assert_allclose(np.asarray(got.reflectance), np.asarray(want.reflectance), rtol=2e-5, atol=2e-6)
    # Mapped over calibrations as well as frames: one call per element, the same numbers.
    scales = jnp.asarray([0.5, 2.0, 1.0], jnp.float32)

    def lab_for(frame, scale):
        cal = sj.Calibration(
            dark=calibration.dark, white=calibration.white, patch=calibration.patch, coeffs=calibration.coeffs,
            wiener=calibration.wiener * scale, saturation=SATURATION, wiener_offset=calibration.wiener_offset * scale,
        )
        return sj.correct(frame, cal).lab

    both = jax.vmap(lab_for)(jnp.asarray(raw), scales)
    looped = np.stack([np.asarray(lab_for(frame, scale)) for frame, scale in zip(raw, scales)])
    np.testing.assert_allclose(np.asarray(both), looped, rtol=2e-5, atol=3e-3)


@pytest.mark.skipif(not fused.built(), reason="the fused kernel was not built")
def test_a_kernel_the_running_jaxlib_refuses_runs_the_plain_path(monkeypatch, caplog):
    """A kernel compiled against newer XLA FFI headers than the running jaxlib speaks (built in
    pip's isolated environment with the newest jaxlib, beside an older jaxlib already installed)
    made XLA raise from inside the first `correct` (jaxlib 0.9.2: "the handler's API version (0.5)
    is incompatible with the framework's API version (0.3)"). It is now refused once, with the
    reason and the remedy, and `correct` runs the jax.numpy path: the same numbers."""
    xla_refusal = ("INVALID_ARGUMENT: XLA FFI handler registration for spherejax_fused_correct on platform Host "
                   "(canonical host) failed because the handler's API version (0.5) is incompatible with the "
                   "framework's API version (0.3). Minimum supported API version is (0.1).\n-----\nJAX frames")

    def refuse(name, capsule, platform):
        assert (name, platform) == (fused.TARGET, "cpu")
        raise RuntimeError(xla_refusal)

    with caplog.at_level("WARNING", logger="spherejax._engine.fused"):
        reason = fused._try_register(refuse)
    assert caplog.messages == [reason]  # said once, on the log, when it happens
    major, minor = fused._fused_correct.ffi_api_version()
    assert reason.startswith(f"the fused kernel (XLA FFI API {major}.{minor}) was refused by jaxlib ")
    assert "the handler's API version (0.5) is incompatible with the framework's API version (0.3)" in reason
    assert "JAX frames" not in reason and "\n" not in reason
    assert "pip install --no-build-isolation --force-reinstall --no-deps" in reason

    monkeypatch.delenv(fused.SWITCH, raising=False)
    monkeypatch.setattr(fused, "_registration", lambda: reason)
    assert not fused.enabled()
    assert fused.unavailable_reason() == reason
    assert fused.mode(np.uint16, np.dtype(np.float32), 16) is None
    raw, calibration = make_case(24, 32, 16)
    refused = sj.correct(raw, calibration)
    monkeypatch.setenv(fused.SWITCH, "0")
    assert fused.unavailable_reason() == "SPHEREJAX_FUSED=0 switches the fused kernel off"
    plain = sj.correct(raw, calibration)
    for name in ("reflectance", "lab", "quality"):
        np.testing.assert_array_equal(np.asarray(getattr(refused, name)), np.asarray(getattr(plain, name)))


@pytest.mark.skipif(not fused.built(), reason="the fused kernel was not built")
def test_the_kernel_is_compiled_against_ffi_headers_the_running_jaxlib_takes(monkeypatch):
    """setup.py compiles against the installed jaxlib's headers where there is one: the XLA here
    registers the kernel, whose FFI version is at least that of jaxlib 0.10.2 (the lower bound)."""
    monkeypatch.delenv(fused.SWITCH, raising=False)
    major, minor = fused._fused_correct.ffi_api_version()
    assert (major, minor) >= (0, 3)  # jaxlib 0.10.2's
    assert fused.unavailable_reason() is None
    assert fused.enabled()


@pytest.mark.skipif(not fused.built(), reason="the fused kernel was not built")
def test_a_process_without_the_cpu_backend_is_told_why_not_an_error(monkeypatch, caplog):
    """JAX_PLATFORMS=cuda (a GPU-only process) has no CPU backend: jax.devices("cpu") raises,
    and registering the kernel must say so instead of failing `correct`."""
    def no_cpu(backend=None):
        raise RuntimeError("Unknown backend cpu. Available: ['cuda']")

    monkeypatch.setattr(jax, "devices", no_cpu)
    with caplog.at_level("WARNING", logger="spherejax._engine.fused"):
        reason = fused._try_register(lambda *args, **kwargs: pytest.fail("registered without a CPU backend"))
    assert caplog.messages == []  # expected there: nothing to warn about
    assert reason == ("the fused kernel runs on XLA's CPU backend, which this process does not have "
                      "(Unknown backend cpu. Available: ['cuda'])")
