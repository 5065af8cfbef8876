"""The fused CPU kernel (spherejax/_engine/kernel/) against the jax.numpy path it replaces.

The jax.numpy path (`SPHEREJAX_FUSED=0`) is the definition; every branch of the kernel is
compared with it: each instruction-set variant of the 16-band code the CPU runs (AVX-512, AVX2,
generic) and the generic loop (other band counts), uint16 and float32 raw, every quality bit,
batches of images, several thread-pool chunks, strips, gradients and vmap, each with a zero and a
non-zero Wiener offset r0 (the kernel's bias). Values agree to float32 rounding, quality masks and
NaN positions exactly. Also the choice of variant: its rule, its measurement, its cache, and the
refusal of a variant the CPU does not run.
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
from spherejax._engine import fused, fused_extension, fused_variants, variant_cache
from spherejax.calibration import compute_dtype as _compute_dtype
from spherejax.pipeline import patch_ratio
from spherejax.polynomial import PAPER_TABLE_2

from .helpers import FUSED_SATURATION as SATURATION, cpu_only, image_program, make_fused_case as make_case



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
    """The whole-frame program `correct` runs (helpers.image_program), lowered, with the kernel
    mode `correct` would take now."""
    mode = fused.mode(raw.dtype, _compute_dtype(raw, calibration), calibration.bands)
    program = jax.jit(lambda raw: image_program(raw, calibration, mode, intermediates=intermediates))
    return program.lower(raw).as_text()


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
    """16 bands take the measured variant (AUTO; PORTABLE: without AVX-512), others the generic
    loop; 96 x 100 pixels are two thread-pool chunks and a part block. Each variant forced:
    `test_each_variant_forced_equals_the_plain_path`."""
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


def _cpu_flags() -> set[str] | None:
    """The flags of the first CPU in /proc/cpuinfo, or None where there is none."""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return None


def _variants():
    """pytest params of every variant, those this CPU does not run skipped (saying so)."""
    return [
        pytest.param(name, marks=pytest.mark.skipif(
            name not in fused.supported_variants(), reason=f"this CPU does not run the kernel's {name} code"))
        for name in fused.VARIANTS
    ]


@pytestmark_kernel
@cpu_kernel
@pytest.mark.parametrize("kernel_mode", _variants())
@pytest.mark.parametrize("bands", [16, 7])
def test_kernel_cube_root_against_float64(bands, kernel_mode):
    """L* of exact Y: the kernel's cube root within 3 ulp of float64's (two Halley steps, as the
    AVX-512 code and the generic loop take it), within 1 ulp on the AVX2 code's division-free
    Newton iteration (16 bands, the avx2 variant), and the linear branch below (6/29)^3 within 1
    ulp; a part block of pixels.

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
    newton = bands == 16 and kernel_mode == fused.AVX2
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
    """`mode` names the variant that runs: for 16 bands the measured one (auto, 1, unset), the
    measured one without AVX-512 (portable) or the one SPHEREJAX_FUSED names; for other band
    counts the generic code, the only code they have."""
    f32, f64 = np.dtype(np.float32), np.dtype(np.float64)
    monkeypatch.delenv(fused.SWITCH, raising=False)
    if fused.built():
        measured = fused.measurement()
        assert fused.mode(np.uint16, f32, 16) == measured.auto
        assert fused.mode(np.float32, f32, 5) == fused.GENERIC
        monkeypatch.setenv(fused.SWITCH, "1")
        assert fused.mode(np.uint16, f32, 16) == measured.auto
        monkeypatch.setenv(fused.SWITCH, "portable")
        assert fused.mode(np.uint16, f32, 16) == measured.portable != fused.AVX512
        assert fused.mode(np.uint16, f32, 33) == fused.GENERIC
        for name in fused.supported_variants():
            monkeypatch.setenv(fused.SWITCH, name)
            assert fused.mode(np.float32, f32, 16) == name
            assert fused.mode(np.float32, f32, 7) == fused.GENERIC
    assert fused.mode(np.uint16, f64, 16) is None  # float64
    assert fused.mode(np.uint8, f32, 16) is None  # raw dtype the kernel does not read
    assert fused.mode(np.uint16, f32, fused.MAX_BANDS + 1) is None
    monkeypatch.setenv(fused.SWITCH, "0")
    assert not fused.enabled()
    assert fused.mode(np.uint16, f32, 16) is None


@pytest.mark.parametrize("value", ["off", "false", "no", "", "AUTO", " 0", "AVX2", "avx512f", "sse2"])
def test_an_undocumented_switch_value_is_refused(monkeypatch, value):
    """A value such as SPHEREJAX_FUSED=off is refused rather than leaving the kernel on."""
    raw, calibration = make_case(24, 24, 16)
    monkeypatch.setenv(fused.SWITCH, value)
    expected = "'auto', '1', 'portable', 'avx512', 'avx2', 'generic', '0'"
    with pytest.raises(ValueError, match=rf"SPHEREJAX_FUSED: expected one of {expected} or unset, got {re.escape(repr(value))}"):
        sj.correct(raw, calibration)


@pytestmark_kernel
@cpu_kernel
def test_intermediates_do_not_change_the_main_outputs(monkeypatch):
    """Asking for v, v_stage1, v_stage2 leaves the main outputs the kernel's: bit-identical to the
    call without them (the jax.numpy path's Lab differs by up to 1.5e-4)."""
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
    mode = fused.mode(raw.dtype, _compute_dtype(raw, calibration), calibration.bands)
    assert mode == fused.measurement().auto

    def step(raw):
        return image_program(raw, calibration, mode)

    exported = jax.export.export(jax.jit(step), platforms=["cuda"])(raw)
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
        reason = fused_extension._try_register(refuse)
    assert caplog.messages == [reason]  # said once, on the log, when it happens
    major, minor = fused._fused_correct.ffi_api_version()
    assert reason.startswith(f"the fused kernel (XLA FFI API {major}.{minor}) was refused by jaxlib ")
    assert "the handler's API version (0.5) is incompatible with the framework's API version (0.3)" in reason
    assert "JAX frames" not in reason and "\n" not in reason
    assert "pip install --no-build-isolation --force-reinstall --no-deps" in reason

    monkeypatch.delenv(fused.SWITCH, raising=False)
    # Both the registration (fused_extension.register) and the reason given (unavailable_reason) read it.
    monkeypatch.setattr(fused_extension, "registration_refusal", lambda: reason)
    monkeypatch.setattr(fused_variants, "registration_refusal", lambda: reason)
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
        reason = fused_extension._try_register(lambda *args, **kwargs: pytest.fail("registered without a CPU backend"))
    assert caplog.messages == []  # expected there: nothing to warn about
    assert reason == ("the fused kernel runs on XLA's CPU backend, which this process does not have "
                      "(Unknown backend cpu. Available: ['cuda'])")


# --------------------------------------------------------------------------------------------
# The instruction-set variants and the choice between them


def test_the_choice_rule_prefers_the_wider_variant_unless_a_narrower_one_is_clearly_faster():
    """`choose_variant` with made-up times: the widest unless a narrower one is faster by more
    than the margin (a narrower time x 1.1 below the choice's), step by step from the widest."""
    choose = fused.choose_variant
    assert fused.MARGIN == 0.10
    assert choose({"avx512": 1.0, "avx2": 1.0, "generic": 1.0}) == "avx512"  # a tie: the widest
    assert choose({"avx512": 1.0, "avx2": 0.92, "generic": 0.95}) == "avx512"  # 8.7 % faster: not clearly
    assert choose({"avx512": 1.1, "avx2": 1.0}) == "avx512"  # exactly the margin: still the wider
    assert choose({"avx512": 1.0, "avx2": 0.8, "generic": 0.9}) == "avx2"  # the Intel case turned round
    assert choose({"avx512": 1.0, "avx2": 0.95, "generic": 0.8}) == "generic"  # 25 % faster than avx512
    assert choose({"avx512": 1.0, "avx2": 0.85, "generic": 0.8}) == "avx2"  # generic only 6 % past avx2
    assert choose({"avx512": 0.5, "avx2": 1.0, "generic": 2.0}) == "avx512"
    # The order of the mapping does not matter, only the order of VARIANTS.
    assert choose({"generic": 0.8, "avx2": 0.95, "avx512": 1.0}) == "generic"
    # Subsets: PORTABLE's (no avx512) and a CPU with the generic code alone.
    assert choose({"avx2": 1.0, "generic": 0.95}) == "avx2"
    assert choose({"avx2": 1.0, "generic": 0.85}) == "generic"
    assert choose({"generic": 3.0}) == "generic"
    # margin 0: the fastest, a tie still to the wider.
    assert choose({"avx512": 1.0, "avx2": 0.99}, margin=0.0) == "avx2"
    assert choose({"avx512": 1.0, "avx2": 1.0}, margin=0.0) == "avx512"
    for bad in ({}, {"avx512": 1.0, "sse2": 0.5}):
        with pytest.raises(ValueError, match="times_s: expected seconds for some of"):
            choose(bad)


def test_the_choice_does_not_flip_on_noise_between_equal_variants():
    """Two variants equally fast, timed with the noise the measurement shows (+-4 %): the choice
    is the wider every time; one truly 25 % faster is chosen every time despite the same noise."""
    rng = np.random.default_rng(5)
    noise = rng.uniform(0.96, 1.04, (2000, 3))
    equal = {choose for choose in (fused.choose_variant(dict(zip(fused.VARIANTS, 1e-3 * n))) for n in noise)}
    assert equal == {"avx512"}
    faster = {fused.choose_variant({"avx512": 1e-3 * a, "avx2": 0.75e-3 * b, "generic": 1e-3 * c}) for a, b, c in noise}
    assert faster == {"avx2"}


@pytestmark_kernel
def test_supported_variants_are_what_the_cpu_has():
    """The kernel's own report (its __builtin_cpu_supports checks) against /proc/cpuinfo: AVX-512
    needs avx512f, bw, dq, vl (and fma), AVX2 needs avx2 and fma; the generic code runs anywhere.
    Widest first, in the order of VARIANTS."""
    supported = fused.supported_variants()
    assert supported[-1] == fused.GENERIC
    assert list(supported) == [name for name in fused.VARIANTS if name in supported]
    assert supported == fused._fused_correct.supported_variants()
    flags = _cpu_flags()
    if flags is None or platform.machine() != "x86_64":
        pytest.skip("no /proc/cpuinfo flags of an x86-64 CPU to compare with")
    has_avx512 = {"avx512f", "avx512bw", "avx512dq", "avx512vl", "fma"} <= flags
    has_avx2 = {"avx2", "fma"} <= flags
    assert (fused.AVX512 in supported) == has_avx512
    assert (fused.AVX2 in supported) == has_avx2


@pytestmark_kernel
def test_measure_variants_times_every_supported_variant():
    """A real (short) measurement: a positive, finite CPU time for each variant the CPU runs;
    the slices go round more memory than the last-level cache, so that calls read from memory."""
    times = fused.measure_variants(pixels=4096, repeats=2)
    assert tuple(times) == fused.supported_variants()
    assert all(0.0 < t < 1.0 for t in times.values()), times
    per_slice = fused.PROBE_PIXELS * fused_variants._BYTES_PER_PIXEL
    slices = fused_variants._probe_slices(fused.PROBE_PIXELS)
    # Between two turns of one slice the others pass through: 1.5 x the cache, or the cap.
    assert (slices - 1) * per_slice >= min(1.5 * fused_variants._last_level_cache_bytes(),
                                           fused_variants._MAX_PROBE_BYTES - 2 * per_slice)
    assert 3 <= slices and slices * per_slice <= fused_variants._MAX_PROBE_BYTES


def test_the_probe_goes_round_enough_memory_to_leave_the_cache(monkeypatch):
    """_probe_slices from made-up cache sizes: one and a half times the cache between two turns
    of a slice, at least 3 slices, at most _MAX_PROBE_BYTES in all."""
    per_slice = fused.PROBE_PIXELS * fused_variants._BYTES_PER_PIXEL  # 9.7 MB
    cap = fused_variants._MAX_PROBE_BYTES
    for cache, expected in ((32 << 20, 7), (1 << 20, 3), (96 << 20, 17), (1 << 30, cap // per_slice)):
        monkeypatch.setattr(fused_variants, "_last_level_cache_bytes", lambda cache=cache: cache)
        assert fused_variants._probe_slices(fused.PROBE_PIXELS) == expected, cache
    assert cap // per_slice == 27


@pytestmark_kernel
def test_the_choice_is_measured_once_and_cached(monkeypatch, caplog, tmp_path):
    """The first use on a machine measures (made-up times here, in an empty cache folder, so that
    the choice is known), logs the times and the choice at DEBUG, and every later `mode`,
    `variant` and kernel call takes the same choice without measuring again. The process's real
    choice is put back afterwards."""
    monkeypatch.delenv(fused.SWITCH, raising=False)
    real = fused.measurement()
    assert real.auto in fused.supported_variants() and real.portable in fused.supported_variants()
    assert real.portable != fused.AVX512
    assert real.auto == fused.choose_variant(real.times_s)
    assert set(real.times_s) == set(fused.supported_variants())
    assert fused.measurement() is real  # cached

    supported = fused.supported_variants()
    # The narrowest variant made 30 % faster than all others: chosen for auto and portable alike.
    made_up = {name: 1e-3 for name in supported}
    made_up[supported[-1]] = 0.7e-3
    calls = []

    def fake_measure(variants=None, **kwargs):
        calls.append(variants)
        return dict(made_up)

    monkeypatch.setattr(fused_variants, "measure_variants", fake_measure)
    monkeypatch.setenv(variant_cache.CACHE_DIR, str(tmp_path))  # nothing kept yet: measured
    fused_variants._measured.cache_clear()
    try:
        with caplog.at_level("DEBUG", logger="spherejax._engine.fused"):
            assert fused.mode(np.uint16, np.float32, 16) == supported[-1]
        assert len(calls) == 1
        assert [r.levelname for r in caplog.records] == ["DEBUG"]
        message = caplog.messages[0]
        assert f"auto runs {supported[-1]}" in message and f"portable {supported[-1]}" in message
        assert f"{supported[-1]} 0.70 ms" in message
        for _ in range(3):
            assert fused.mode(np.uint16, np.float32, 16) == supported[-1]
            assert fused.variant() == (supported[-1], fused.AUTO, fused.measurement())
        monkeypatch.setenv(fused.SWITCH, "portable")
        assert fused.mode(np.float32, np.float32, 16) == supported[-1]
        assert len(calls) == 1  # measured once
    finally:
        # Put the process's real choice back, as other tests' traced programs assume it.
        monkeypatch.setattr(fused_variants, "measure_variants", lambda variants=None, **kwargs: dict(real.times_s))
        monkeypatch.setenv(variant_cache.CACHE_DIR, str(tmp_path / "real"))
        fused_variants._measured.cache_clear()
        assert fused.measurement().auto == real.auto


@pytestmark_kernel
def test_variant_reports_what_runs(monkeypatch):
    monkeypatch.delenv(fused.SWITCH, raising=False)
    chosen = fused.variant()
    assert chosen.name == fused.measurement().auto and chosen.setting == fused.AUTO
    assert chosen.measurement is fused.measurement()
    monkeypatch.setenv(fused.SWITCH, "portable")
    assert fused.variant().name == fused.measurement().portable
    for name in fused.supported_variants():
        monkeypatch.setenv(fused.SWITCH, name)
        assert fused.variant()[:2] == (name, name)
    monkeypatch.setenv(fused.SWITCH, "0")
    assert fused.variant() is None


@pytestmark_kernel
@cpu_kernel
@pytest.mark.parametrize("raw_dtype", [np.uint16, np.float32])
@pytest.mark.parametrize("variant", _variants())
def test_each_variant_forced_equals_the_plain_path(monkeypatch, variant, raw_dtype):
    """SPHEREJAX_FUSED=<variant> runs that variant (its code in the custom call's `variant`
    attribute) and gives the jax.numpy path's numbers within the tolerances of every other test;
    the direct NumPy route gives the XLA route's bits under it."""
    raw, calibration = make_case(96, 100, 16, raw_dtype=raw_dtype, offset=True)
    monkeypatch.setenv(fused.SWITCH, variant)
    assert fused.mode(raw.dtype, np.float32, 16) == variant
    code = getattr(fused._fused_correct, f"VARIANT_{variant.upper()}")
    assert f"variant = {code} : i32" in lowered_text(jnp.asarray(raw), calibration)
    kernel, plain = correct_both(monkeypatch, raw, calibration)
    assert_same_result(kernel, plain)
    assert (np.asarray(kernel.quality) != 0).sum() == (10 if raw_dtype == np.float32 else 4)

    # The same constants through both routes: `_kernel_call` (XLA) and `correct_arrays` (direct).
    images, pixels, bands = 1, 96 * 100, 16
    p = np.asarray(patch_ratio(raw, calibration)).reshape(images, bands)
    weights = sj.colorimetry.tristimulus_weights(calibration.illuminant, observer=calibration.observer)
    projection, bias, white_xyz = (np.asarray(x, np.float32) for x in fused.kernel_constants(
        jnp.asarray(calibration.wiener, jnp.float32), jnp.asarray(calibration.wiener_offset, jnp.float32),
        jnp.asarray(weights, jnp.float32)))
    arrays = (raw.reshape(images, pixels, bands), np.asarray(calibration.dark).reshape(pixels, bands),
              np.asarray(calibration.white).reshape(pixels, bands), p, np.asarray(calibration.coeffs, np.float32),
              projection, bias, white_xyz)
    call = jax.jit(fused._kernel_call, static_argnames=("saturation", "kernel_mode"))
    through_xla = call(*arrays, saturation=SATURATION, kernel_mode=variant)
    direct = (np.empty((images, pixels, 31), np.float32), np.empty((images, pixels, 3), np.float32),
              np.empty((images, pixels), np.uint8))
    fused.correct_arrays(*arrays, SATURATION, variant, direct, threads=2)
    for got, want in zip(direct, through_xla):
        np.testing.assert_array_equal(got, np.asarray(want))


@pytestmark_kernel
def test_a_variant_the_cpu_does_not_run_is_refused(monkeypatch):
    """Forcing a variant the CPU lacks is refused, naming the variable and what the CPU runs,
    rather than run something else under its name (or die of an illegal instruction): by
    `switch` (so by `correct` and up front by the command line), by `correct_arrays`, and by the
    kernel itself (its own check, whichever entry is called) for a code it does not know."""
    cpu_without_avx512 = lambda: (fused.AVX2, fused.GENERIC)  # noqa: E731
    monkeypatch.setattr(fused_variants, "supported_variants", cpu_without_avx512)
    monkeypatch.setattr(fused, "supported_variants", cpu_without_avx512)
    monkeypatch.setenv(fused.SWITCH, "avx512")
    message = ("SPHEREJAX_FUSED='avx512': this CPU does not run the fused kernel's avx512 code; "
               "it runs 'avx2', 'generic' ('auto' takes the fastest of them)")
    with pytest.raises(ValueError, match=re.escape(message)):
        fused.switch()
    raw, calibration = make_case(24, 24, 16)
    with pytest.raises(ValueError, match=re.escape(message)):
        sj.correct(raw, calibration)
    monkeypatch.setenv(fused.SWITCH, "avx2")
    assert fused.switch() == "avx2"

    images, pixels, bands = 1, 64, 16
    arrays = (np.zeros((images, pixels, bands), np.uint16), np.zeros((pixels, bands), np.float32),
              np.ones((pixels, bands), np.float32), np.ones((images, bands), np.float32),
              np.zeros((bands, 4), np.float32), np.zeros((bands, 34), np.float32), np.zeros(34, np.float32),
              np.ones(3, np.float32))
    out = (np.empty((images, pixels, 31), np.float32), np.empty((images, pixels, 3), np.float32),
           np.empty((images, pixels), np.uint8))
    with pytest.raises(ValueError, match=r"the fused kernel's 'avx512' variant: not among those this CPU runs"):
        fused.correct_arrays(*arrays, None, "avx512", out, threads=1)
    with pytest.raises(ValueError, match="kernel_mode: expected one of"):
        fused.correct_arrays(*arrays, None, "sse2", out, threads=1)

    # The kernel's own check, below the Python one: codes it does not know (and, on a CPU that
    # lacks one, the variants it does not run) are refused by the CPython entry and the FFI handler.
    no_residual = tuple(np.asarray(x) for x in fused.residual_constants(None, None, bands))
    unsupported = [getattr(fused._fused_correct, f"VARIANT_{name.upper()}")
                   for name in fused.VARIANTS if name not in fused._fused_correct.supported_variants()]
    for code in (9, -1, *unsupported):
        with pytest.raises(ValueError, match=rf"correct_arrays: variant: .*, got {code}"):
            fused._fused_correct.correct_arrays(arrays[0], True, *arrays[1:], *no_residual, images, pixels, bands,
                                                0, 0, float("nan"), code, 1, *out)
    out_types = (jax.ShapeDtypeStruct((images, pixels, 31), jnp.float32),
                 jax.ShapeDtypeStruct((images, pixels, 3), jnp.float32),
                 jax.ShapeDtypeStruct((images, pixels), jnp.uint8))
    assert fused.register()
    ffi = jax.ffi.ffi_call(fused.TARGET, out_types)
    with pytest.raises(Exception, match=r"variant: expected 0 \(the widest this CPU runs\)"):
        jax.block_until_ready(ffi(*arrays, *no_residual, saturation=np.float32(np.nan), variant=np.int32(9)))
    # Code 0 leaves the choice to the kernel (the widest the CPU runs): accepted by both entries.
    fused._fused_correct.correct_arrays(arrays[0], True, *arrays[1:], *no_residual, images, pixels, bands, 0, 0,
                                        float("nan"), 0, 1, *out)
    assert (out[2] == 0).all()
    jax.block_until_ready(ffi(*arrays, *no_residual, saturation=np.float32(np.nan), variant=np.int32(0)))
