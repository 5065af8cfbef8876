"""The Pallas prototype of the per-pixel step (spherejax/_engine/gpu_kernel.py) against the
jax.numpy path it would replace on GPUs (`equations.pixel_outputs`).

Run in Pallas's interpret mode, so on the CPU, on small frames: the kernel's indexing, masks,
flags and arithmetic are the ones a GPU runs, its compilation by Triton and its speed are not
(benchmarks/bench_gpu_kernel.py checks and times it on a GPU). Quality masks and NaN positions agree
exactly, values to float32 rounding (the projection sums in another order). One test lowers the
kernel to Triton IR for an H100 without a GPU, which checks what the Triton lowering refuses
(block sizes that are not powers of two, operations it has no rule for).
"""

from __future__ import annotations

import dataclasses
import logging
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax import equations, pipeline
from spherejax._engine import fused, gpu_kernel, gpu_residual
from spherejax._engine import kernels
from spherejax._engine.gpu_kernel import pixel_outputs_pallas
from spherejax._engine.plan import Plan
from spherejax.estimation import kernel_residual
from spherejax.pixel_constants import PixelConstants
from spherejax.polynomial import PAPER_TABLE_2

SATURATION = 16383.0
BANDS = 16


def make_case(height, width, *, raw_dtype, images=(), seed=0):
    """Frames with every kind of bad pixel, their calibration's constants (float32, a non-zero
    Wiener offset) and p, NaN in one band of the last image's p if there are several images."""
    raw, p, calibration = make_calibration_case(height, width, raw_dtype=raw_dtype, images=images, seed=seed)
    return raw, p, PixelConstants.of(calibration, np.float32)


def make_calibration_case(height, width, *, raw_dtype, images=(), seed=0):
    """`make_case`'s frames and p with the `Calibration` itself."""
    rng = np.random.default_rng(seed)
    bands = BANDS
    dark = rng.uniform(95, 105, (height, width, bands)).astype(np.float32)
    white = (dark + rng.uniform(8000, 12000, (height, width, bands))).astype(np.float32)
    # Reflectances from 0.001 to 1.2: XYZ / white spans both branches of the Lab companding.
    level = np.exp(rng.uniform(np.log(1e-3), np.log(1.2), (*images, height, width, 1)))
    raw = dark + (white - dark) * level * rng.uniform(0.9, 1.1, (*images, height, width, bands))
    raw = np.clip(np.rint(raw), 0, SATURATION - 1)
    first = (0,) * len(images)
    raw[(*first, 3, 4, 5)] = SATURATION  # saturated
    white[10, 11, 2] = dark[10, 11, 2]  # white == dark: no flat field
    white[12, 13, 3] = dark[12, 13, 3] - 5  # white < dark
    raw[(*first, 12, 13, 0)] = SATURATION  # saturated and no flat field: two bits
    dark[2, 21, 1] += 700  # below the dark level by 7 % of the white signal
    raw[(*first, 2, 21, 1)] = 0
    # Below by 0.5 %, which noise allows: not flagged.
    raw[(*first, 0, 22, 2)] = np.floor(dark[0, 22, 2] - 0.005 * (white - dark)[0, 22, 2])
    if raw_dtype == np.float32:
        white[14, 15, 1] = np.nan
        white[16, 17, 0] = np.inf
        raw[(*first, 6, 7, 0)] = np.nan
        raw[(*first, 8, 9, bands - 1)] = -np.inf
        raw[(*first, 18, 19, 0)] = np.inf
        raw[(*first, 1, 20, 0)] = -1000.0  # v about -0.11: below dark
        raw[(*first, 5, 30, 4)] = np.inf  # +inf: non-finite, not saturated
    raw = raw.astype(raw_dtype)
    patch = np.zeros((height, width), bool)
    patch[height // 2 - 4:height // 2 + 4, width // 2 - 5:width // 2 + 5] = True
    calibration = sj.Calibration(
        dark=dark, white=white, patch=patch, coeffs=np.asarray(PAPER_TABLE_2, np.float32),
        wiener=(np.abs(rng.normal(0.0, 1.0, (31, bands))) / bands).astype(np.float32), saturation=SATURATION,
        wiener_offset=rng.uniform(-0.05, 0.05, 31).astype(np.float32),
    )
    p = np.asarray(pipeline.patch_ratio(raw, calibration))
    if images:
        p = p.copy()
        p[(*(n - 1 for n in images), 3)] = np.nan  # the last image's patch is unusable
    return jnp.asarray(raw), jnp.asarray(p), calibration


def assert_agree(got, want):
    reflectance, lab, quality = (np.asarray(x) for x in got)
    want_reflectance, want_lab, want_quality = (np.asarray(x) for x in want)
    assert quality.dtype == np.uint8 and quality.shape == want_quality.shape
    np.testing.assert_array_equal(quality, want_quality)
    bad = want_quality != 0
    for name, value, expected, atol in (
        ("reflectance", reflectance, want_reflectance, 2e-6), ("lab", lab, want_lab, 3e-4),
    ):
        assert value.dtype == np.float32 and value.shape == expected.shape, name
        # NaN in every channel of a flagged pixel and nowhere else.
        np.testing.assert_array_equal(np.isnan(value), np.broadcast_to(bad[..., None], value.shape), err_msg=name)
        np.testing.assert_allclose(value, expected, rtol=2e-5, atol=atol, err_msg=name)


def test_uint16_batch_equals_the_jax_numpy_path():
    """Two 24 x 40 frames of uint16 counts: saturated, no flat field (white == dark and white <
    dark), both at once, below dark and the last frame's patch unusable; 960 pixels in blocks of
    64 (the grid's two axes, no partial block)."""
    raw, p, constants = make_case(24, 40, raw_dtype=np.uint16, images=(2,))
    got = pixel_outputs_pallas(raw, p, constants, saturation=SATURATION, block_pixels=64, interpret=True)
    want = equations.pixel_outputs(raw, p, constants, saturation=SATURATION)
    assert_agree(got, want)
    quality = np.asarray(want[2])
    assert quality[0, 3, 4] == sj.QUALITY_SATURATED
    assert quality[0, 10, 11] == quality[0, 12, 13] - sj.QUALITY_SATURATED == sj.QUALITY_WHITE_NOT_ABOVE_DARK
    assert quality[0, 2, 21] == sj.QUALITY_BELOW_DARK and quality[0, 0, 22] == 0
    assert np.all(quality[1] & sj.QUALITY_PATCH_UNUSABLE) and not np.any(quality[0] & sj.QUALITY_PATCH_UNUSABLE)
    assert np.count_nonzero(quality[0]) < 10  # the rest of the first frame is good, and compared


def test_float32_frame_with_the_flat_field_mask_equals_the_jax_numpy_path():
    """One 24 x 40 float32 frame with NaN and infinite raw and white values and a raw value far
    below dark; the (H, W) no-flat-field mask given as the plan gives it; blocks of 128, so that
    the last of the 960 pixels' blocks is partial (masked loads and stores)."""
    raw, p, constants = make_case(24, 40, raw_dtype=np.float32)
    mask = equations.flat_field_unusable(constants.dark, constants.white)
    got = pixel_outputs_pallas(raw, p, constants, saturation=SATURATION, no_flat_field=mask, interpret=True)
    want = equations.pixel_outputs(raw, p, constants, saturation=SATURATION, no_flat_field=mask)
    assert_agree(got, want)
    quality = np.asarray(want[2])
    assert quality[6, 7] == quality[8, 9] == quality[18, 19] == quality[5, 30] == sj.QUALITY_NONFINITE
    assert quality[14, 15] == quality[16, 17] == sj.QUALITY_WHITE_NOT_ABOVE_DARK
    assert quality[1, 20] == quality[2, 21] == sj.QUALITY_BELOW_DARK
    assert quality[3, 4] == sj.QUALITY_SATURATED


def test_no_saturation_level():
    """saturation None (float raw without a level): no saturated bit; the saturated count is then
    an ordinary value, as in the jax.numpy path."""
    raw, p, constants = make_case(24, 40, raw_dtype=np.uint16)
    got = pixel_outputs_pallas(raw, p, constants, saturation=None, block_pixels=256, interpret=True)
    want = equations.pixel_outputs(raw, p, constants, saturation=None)
    assert_agree(got, want)
    assert not np.any(np.asarray(want[2]) & sj.QUALITY_SATURATED)


@pytest.mark.parametrize(
    ("change", "error"),
    [
        (lambda raw, constants: (raw[..., :8], constants.pixels(constants.dark[..., :8], constants.white[..., :8])),
         NotImplementedError),
        (lambda raw, constants: (raw.astype(jnp.int32), constants), NotImplementedError),
        (lambda raw, constants: (raw[:, :-1], constants), ValueError),
    ],
    ids=["8 bands", "int32 raw", "shape"],
)
def test_refuses_what_it_does_not_take(change, error):
    raw, p, constants = make_case(24, 40, raw_dtype=np.uint16)
    raw, constants = change(raw, constants)
    with pytest.raises(error):
        pixel_outputs_pallas(raw, p[..., :raw.shape[-1]], constants, saturation=SATURATION, interpret=True)


@pytest.mark.parametrize("points", [None, 64, 200], ids=["affine", "residual of 64 points", "residual of 200 points"])
def test_lowers_to_triton_for_an_h100(points):
    """The kernel as a GPU would compile it (interpret=False), lowered to Triton IR for an
    abstract H100 on this machine: every array the kernel loads or stores has a power-of-two size
    and every operation has a Triton lowering rule; with a kernel residual of one chunk of
    inducing points and of four (the chunks' loop, `gpu_residual`). What Triton then makes of the
    IR (PTX) needs a GPU. jax 0.11.2 and 0.12 warn at this lowering that the Pallas Triton backend
    is deprecated (in favour of Mosaic GPU): expected here, not an error."""
    from jax.sharding import AbstractDevice, AbstractMesh

    raw, p, constants = make_case(24, 40, raw_dtype=np.uint16, images=(2,))
    if points is not None:
        constants = with_residual(raw, p, constants, points)
    mesh = AbstractMesh(
        (1,), ("x",), abstract_device=AbstractDevice(device_kind="NVIDIA H100 80GB HBM3", num_cores=132, platform="gpu")
    )
    program = jax.jit(lambda raw, p, constants: pixel_outputs_pallas(raw, p, constants, saturation=SATURATION))
    with jax.sharding.use_abstract_mesh(mesh), warnings.catch_warnings():
        warnings.filterwarnings("ignore", "The Pallas Triton backend is deprecated", DeprecationWarning)
        text = program.trace(raw, p, constants).lower(lowering_platforms=("cuda",)).as_text()
    assert "__gpu$xla.gpu.triton" in text


# -------------------------------------------------------------------------------------------------
# The kernel residual (E8-E10, `gpu_residual`) against the jax.numpy path and float64 numpy.


def with_residual(raw, p, constants, points, *, seed=1, lengthscale=2.0):
    """`constants` with a kernel residual of `points` inducing points that matters on these frames
    (full-rank weights, as a file may hold them): whitened on the frames' good Stage II responses
    (`kernel_residual.whitening_of`), inducing points at `points` of them, the lengthscale folded
    in, weights A (31, m) drawn from N(0, 0.05^2)."""
    rng = np.random.default_rng(seed)
    *_, quality, _, _, v_tilde = equations.pixel_outputs(raw, p, constants, saturation=SATURATION, intermediates=True)
    v = np.asarray(v_tilde, np.float64)[np.asarray(quality) == 0]
    mu, S = kernel_residual.whitening_of(v)
    S = S / lengthscale
    Z = (v[rng.choice(len(v), points, replace=False)] - mu) @ S.T
    A = rng.normal(scale=0.05, size=(31, points))
    residual = kernel_residual.KernelResidual(*(jnp.asarray(x, jnp.float32) for x in (mu, S, Z, A)))
    return residual_of(constants, residual)


def residual_of(constants, residual):
    """`constants` with `residual` as their kernel residual (None: affine)."""
    c = constants
    return PixelConstants(c.dark, c.white, c.coeffs, c.wiener, c.wiener_offset, c.tristimulus_weights, residual)


def numpy_estimate(v_tilde, constants):
    """W v + r0 + A k(v) in float64 numpy, E9-E10 written out (the distance taken directly)."""
    k = constants.wiener_residual
    as64 = lambda x: np.asarray(x, np.float64)  # noqa: E731
    u = (v_tilde - as64(k.centre)) @ as64(k.whitening).T
    features = np.exp(-0.5 * np.sum((u[..., None, :] - as64(k.inducing)) ** 2, axis=-1))
    return v_tilde @ as64(constants.wiener).T + as64(constants.wiener_offset) + features @ as64(k.weights).T


@pytest.mark.parametrize(
    ("raw_dtype", "images", "points", "block_pixels", "mask"),
    [
        (np.uint16, (2,), 64, 64, False),
        (np.float32, (), 8, 128, True),
        (np.uint16, (), 200, 128, False),
        (np.float32, (2,), 200, 64, False),
    ],
    ids=["uint16, 64 points", "float32 with the mask, 8 points, partial block", "uint16, 200 points, partial block",
         "float32, 200 points"],
)
def test_a_kernel_residual_equals_the_jax_numpy_path(raw_dtype, images, points, block_pixels, mask):
    """The kernel with a residual that moves reflectance by more than 0.02: quality bit for bit,
    NaN on the same pixels, reflectance and Lab to float32 rounding of the jax.numpy path, and
    reflectance within 1e-5 of float64 numpy. 8 points are one chunk of 16 (8 padding points), 64
    one chunk, 200 four chunks of 64 (the loop; 56 padding points); 960 pixels in blocks of 128
    leave a partial last block."""
    raw, p, affine = make_case(24, 40, raw_dtype=raw_dtype, images=images)
    constants = with_residual(raw, p, affine, points)
    no_flat_field = equations.flat_field_unusable(affine.dark, affine.white) if mask else None
    got = pixel_outputs_pallas(raw, p, constants, saturation=SATURATION, no_flat_field=no_flat_field,
                               block_pixels=block_pixels, interpret=True)
    *want, _, _, v_tilde = equations.pixel_outputs(raw, p, constants, saturation=SATURATION, intermediates=True,
                                                   no_flat_field=no_flat_field)
    assert_agree(got, want)
    good = np.asarray(want[2]) == 0
    assert good.sum() > 900  # the flagged pixels are few: nearly every pixel is compared
    affine_reflectance = np.asarray(equations.pixel_outputs(raw, p, affine, saturation=SATURATION)[0])
    assert np.abs(np.asarray(want[0]) - affine_reflectance)[good].max() > 0.02
    expected = numpy_estimate(np.asarray(v_tilde, np.float64), constants)
    np.testing.assert_allclose(np.asarray(got[0], np.float64)[good], expected[good], atol=1e-5)


def test_an_inducing_point_of_zero_weight_adds_exactly_nothing():
    """What the padding of the inducing points rests on: 8 more points, anywhere, with zero
    weights leave every output bit for bit as it was (both 16 points in one chunk)."""
    raw, p, affine = make_case(24, 40, raw_dtype=np.uint16)
    constants = with_residual(raw, p, affine, 8)
    k = constants.wiener_residual
    more = kernel_residual.KernelResidual(
        k.centre, k.whitening, jnp.concatenate([k.inducing, k.inducing[::-1] * 0.5 + 0.25]),
        jnp.concatenate([k.weights, jnp.zeros((31, 8), jnp.float32)], axis=1),
    )
    got = pixel_outputs_pallas(raw, p, residual_of(affine, more), saturation=SATURATION, interpret=True)
    want = pixel_outputs_pallas(raw, p, constants, saturation=SATURATION, interpret=True)
    for name, x, y in zip(("reflectance", "lab", "quality"), got, want):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=name)


def test_the_residual_constants_are_padded_chunks():
    """`gpu_residual.residual_constants` of 200 points: 4 chunks of 64, the 56 padding points
    z = 0, |z|^2 = 0 with zero weights, A^T's 32nd column 0; the values are the residual's."""
    rng = np.random.default_rng(3)
    mu, S, Z, A = rng.normal(size=16), rng.normal(size=(16, 16)), rng.normal(size=(200, 16)), rng.normal(size=(31, 200))
    weights = rng.uniform(size=(31, 3))
    residual = kernel_residual.KernelResidual(*(jnp.asarray(x, jnp.float32) for x in (mu, S, Z, A)))
    c = gpu_residual.residual_constants(residual, jnp.asarray(weights, jnp.float32))
    assert c.inducing.shape == (4, 16, 64) and c.inducing_squared.shape == (4, 64) and c.weights.shape == (4, 64, 32)
    assert c.centre.shape == (16,) and c.whitening.shape == (16, 16) and c.tristimulus.shape == (4, 32)
    inducing = np.asarray(c.inducing).transpose(0, 2, 1).reshape(256, 16)
    np.testing.assert_array_equal(inducing[:200], Z.astype(np.float32))
    np.testing.assert_array_equal(inducing[200:], 0.0)
    np.testing.assert_allclose(np.asarray(c.inducing_squared).reshape(256)[:200], np.sum(Z**2, axis=1), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(c.inducing_squared).reshape(256)[200:], 0.0)
    transposed = np.asarray(c.weights).reshape(256, 32)
    np.testing.assert_array_equal(transposed[:200, :31], A.T.astype(np.float32))
    np.testing.assert_array_equal(transposed[200:], 0.0)
    np.testing.assert_array_equal(transposed[:, 31], 0.0)
    np.testing.assert_array_equal(np.asarray(c.whitening), S.T.astype(np.float32))
    np.testing.assert_array_equal(np.asarray(c.tristimulus)[:3, :31], weights.T.astype(np.float32))
    assert not np.any(np.asarray(c.tristimulus)[3]) and not np.any(np.asarray(c.tristimulus)[:, 31])


@pytest.mark.parametrize(("points", "chunk", "expected"),
                         [(0, 64, 16), (8, 64, 16), (17, 64, 32), (64, 64, 64), (200, 64, 64), (200, 256, 256),
                          (1024, 16, 16)])
def test_chunk_sizes(points, chunk, expected):
    assert gpu_residual.chunk_of(points, chunk) == expected


def test_which_residuals_the_kernel_applies():
    """Up to MAX_INDUCING_POINTS (1024) inducing points of B a power of two >= 16, weights of any
    rank; more points are refused by the kernel; chunks that are not powers of two >= 16 too."""
    def residual(bands, points):
        return kernel_residual.KernelResidual(jnp.zeros(bands), jnp.eye(bands), jnp.zeros((points, bands)),
                                              jnp.zeros((31, points)))

    assert gpu_kernel.MAX_INDUCING_POINTS == 1024
    assert gpu_kernel.applies_residual(None) and gpu_kernel.applies_residual(residual(16, 1024))
    assert gpu_kernel.applies_residual(residual(32, 1)) and not gpu_kernel.applies_residual(residual(16, 1025))
    assert not gpu_kernel.applies_residual(residual(8, 8)) and not gpu_kernel.applies_residual(residual(24, 8))
    raw, p, affine = make_case(24, 40, raw_dtype=np.uint16)
    with pytest.raises(NotImplementedError, match="at most 1024 inducing points, got 1025"):
        pixel_outputs_pallas(raw, p, residual_of(affine, residual(16, 1025)), saturation=SATURATION, interpret=True)
    with pytest.raises(ValueError, match="inducing chunk: expected a power of two >= 16, got 48"):
        gpu_residual.chunk_of(8, 48)
    with pytest.raises(ValueError, match="prepared: expected prepare"):
        pixel_outputs_pallas(raw, p, residual_of(affine, residual(16, 8)), saturation=SATURATION, interpret=True,
                             prepared=gpu_kernel.prepare(affine))


def test_a_residual_through_pixel_outputs_prepared_mapped_and_differentiated():
    """`gpu_kernel.pixel_outputs` (how steps call the kernel) with a residual: with `prepare`'s
    constants made once, as without; frames mapped with jax.vmap; and the JVP with respect to raw
    and the derivative with respect to the residual's weights those of the jax.numpy path."""
    raw, p, affine = make_case(24, 40, raw_dtype=np.float32, images=(2,))
    raw = jnp.where(jnp.isfinite(raw), raw, 500.0)  # finite frames: a derivative everywhere
    constants = with_residual(raw, p, affine, 64)

    def kernel(raw, p, constants, prepared=None):
        return gpu_kernel.pixel_outputs(raw, p, constants, saturation=SATURATION, kernel_mode=gpu_kernel.INTERPRET,
                                        prepared=prepared)

    def reference(raw, p, constants):
        return equations.pixel_outputs(raw, p, constants, saturation=SATURATION)

    want = reference(raw, p, constants)
    assert_agree(kernel(raw, p, constants), want)
    # The prepared constants are what the kernel reads (jit rounds their folds as it fuses them, so
    # the outputs agree to float32 rounding with those of constants made in the call).
    prepared = jax.jit(gpu_kernel.prepare)(constants)
    got = kernel(raw, p, constants, prepared)
    direct = pixel_outputs_pallas(raw, p, constants, saturation=SATURATION, interpret=True, prepared=prepared)
    for x, y in zip(got, direct):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert_agree(got, want)
    assert_agree(jax.vmap(kernel, in_axes=(0, 0, None, None))(raw, p, constants, prepared), want)

    tangent = jnp.ones_like(raw)
    _, got_tangents = jax.jvp(lambda r: kernel(r, p, constants, prepared)[:2], (raw,), (tangent,))
    _, want_tangents = jax.jvp(lambda r: reference(r, p, constants)[:2], (raw,), (tangent,))
    for got_t, want_t in zip(got_tangents, want_tangents):
        np.testing.assert_array_equal(np.asarray(got_t), np.asarray(want_t))

    def loss(function):
        # The first frame, whose patch is usable: a NaN p makes the jax.numpy path's derivative
        # with respect to the residual NaN (its k(v_tilde) is NaN on every pixel of that frame).
        def of(weights):
            c = residual_of(constants, dataclasses.replace(constants.wiener_residual, weights=weights))
            reflectance, lab, _ = function(raw[0], p[0], c)
            return jnp.nansum(reflectance) + 1e-3 * jnp.nansum(lab)
        return of

    weights = constants.wiener_residual.weights
    got_grad, want_grad = jax.grad(loss(kernel))(weights), jax.grad(loss(reference))(weights)
    assert np.all(np.isfinite(np.asarray(got_grad))) and np.count_nonzero(np.asarray(got_grad)) > weights.size // 2
    np.testing.assert_allclose(np.asarray(got_grad), np.asarray(want_grad), rtol=1e-5)


# -------------------------------------------------------------------------------------------------
# The kernel as a plan runs it (`gpu_kernel.pixel_outputs`, `steps`, `plan.Plan`): interpret mode
# stands in for the GPU, the plan's own choice of kernel on a device is tested with device stand-ins.


def plans(raw, calibration):
    """(a plan running the kernel in interpret mode, a plan running the jax.numpy path) of raw's
    shape and dtype."""
    kernel = Plan(calibration, raw.shape, raw.dtype, kernel_mode=gpu_kernel.INTERPRET)
    assert kernel.kernel_mode == gpu_kernel.INTERPRET
    return kernel, Plan(calibration, raw.shape, raw.dtype, kernel_mode=None)


def outputs(result):
    return result.reflectance, result.lab, result.quality


@pytest.mark.parametrize(("raw_dtype", "images"), [(np.uint16, (2,)), (np.float32, ())])
def test_a_plan_with_the_kernel_corrects_as_the_jax_numpy_path(raw_dtype, images):
    """Whole frames (p from the patch, traced into the same program), frames given with p (a
    strip's way) and under the caller's jit: the kernel's outputs are the jax.numpy path's."""
    raw, _, calibration = make_calibration_case(24, 40, raw_dtype=raw_dtype, images=images)
    kernel, reference = plans(raw, calibration)
    got, want = kernel(raw), reference(raw)
    np.testing.assert_array_equal(np.asarray(got.p), np.asarray(want.p))
    assert_agree(outputs(got), outputs(want))
    assert_agree(outputs(kernel(raw, p=want.p)), outputs(reference(raw, p=want.p)))
    assert_agree(outputs(jax.jit(lambda r: kernel(r))(raw)), outputs(want))


def test_intermediates_come_from_the_jax_numpy_path_and_the_main_outputs_from_the_kernel():
    raw, _, calibration = make_calibration_case(24, 40, raw_dtype=np.uint16)
    kernel, reference = plans(raw, calibration)
    got, want = kernel(raw, intermediates=True), reference(raw, intermediates=True)
    assert_agree(outputs(got), outputs(want))
    for name in ("v", "v_stage1", "v_stage2"):
        np.testing.assert_array_equal(np.asarray(getattr(got, name)), np.asarray(getattr(want, name)), err_msg=name)


def test_mapped_frames_are_images_of_one_kernel_call():
    """jax.vmap over frames and their p, over frames with one p, and over calibrations (a mapped
    calibration maps the jax.numpy path); a mapped axis in front of a batch axis of raw."""
    raw, p, calibration = make_calibration_case(24, 40, raw_dtype=np.uint16, images=(3,))
    constants = PixelConstants.of(calibration, np.float32)
    calls = []

    def kernel(raw, p, constants):
        return gpu_kernel.pixel_outputs(raw, p, constants, saturation=SATURATION, kernel_mode=gpu_kernel.INTERPRET)

    def reference(raw, p, constants):
        return equations.pixel_outputs(raw, p, constants, saturation=SATURATION)

    original = gpu_kernel.pixel_outputs_pallas

    def counted(raw, *args, **kwargs):
        calls.append(raw.shape)
        return original(raw, *args, **kwargs)

    gpu_kernel.pixel_outputs_pallas = counted
    try:
        got = jax.vmap(kernel, in_axes=(0, 0, None))(raw, p, constants)
        # Traced once per frame for the mapping's output types, then called once on all three.
        assert calls[-1] == (3, 24, 40, BANDS) and calls.count((3, 24, 40, BANDS)) == 1
        assert_agree(got, reference(raw, p, constants))
        # One p for every frame; a batch axis of two behind the mapped one.
        frames = jnp.stack([raw[:2], raw[1:]])
        assert_agree(jax.vmap(kernel, in_axes=(0, None, None))(frames, p[0], constants),
                     reference(frames, p[0], constants))
        assert calls[-1] == (2, 2, 24, 40, BANDS)
        # Two calibrations: the second's white 5 % higher.
        stacked = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), constants)
        stacked = eqx.tree_at(lambda c: c.white, stacked, stacked.white.at[1].multiply(1.05))
        got = jax.vmap(kernel, in_axes=(None, None, 0))(raw[0], p[0], stacked)
        want = jax.vmap(reference, in_axes=(None, None, 0))(raw[0], p[0], stacked)
        assert_agree(got, want)
    finally:
        gpu_kernel.pixel_outputs_pallas = original


def test_gradients_through_a_plan_with_the_kernel_are_the_jax_numpy_paths():
    """d(sum of good reflectance and Lab)/d raw through `correct`'s plan and through the kernel's
    own JVP: the jax.numpy path's derivatives, finite, and not all zero."""
    raw, p, calibration = make_calibration_case(24, 40, raw_dtype=np.float32)
    raw = jnp.where(jnp.isfinite(raw), raw, 500.0)  # finite frames: a derivative everywhere
    kernel, reference = plans(raw, calibration)

    def loss(plan):
        def of(r):
            result = plan(r)
            return jnp.nansum(result.reflectance) + 1e-3 * jnp.nansum(result.lab)
        return of

    got, want = jax.grad(loss(kernel))(raw), jax.grad(loss(reference))(raw)
    assert np.all(np.isfinite(np.asarray(got))) and np.count_nonzero(np.asarray(got)) > raw.size // 2
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-9)
    constants = PixelConstants.of(calibration, np.float32)
    tangent = jnp.ones_like(raw)
    (_, got_tangents) = jax.jvp(
        lambda r: gpu_kernel.pixel_outputs(
            r, p, constants, saturation=SATURATION, kernel_mode=gpu_kernel.INTERPRET
        )[:2],
        (raw,), (tangent,))
    (_, want_tangents) = jax.jvp(
        lambda r: equations.pixel_outputs(r, p, constants, saturation=SATURATION)[:2], (raw,), (tangent,))
    for got_t, want_t in zip(got_tangents, want_tangents):
        np.testing.assert_array_equal(np.asarray(got_t), np.asarray(want_t))


def test_a_plan_takes_the_kernel_for_a_kernel_estimator_calibration():
    """A calibration with a kernel residual of 64 points: the plan runs the kernel
    (`gpu_kernel.applies_residual`), whose outputs and derivatives with respect to raw are the
    jax.numpy path's; one of 1025 points it leaves to the jax.numpy path, saying why."""
    raw, p, affine = make_calibration_case(24, 40, raw_dtype=np.float32)
    raw = jnp.where(jnp.isfinite(raw), raw, 500.0)  # finite frames: a derivative everywhere
    residual = with_residual(raw, p, PixelConstants.of(affine, np.float32), 64).wiener_residual
    calibration = dataclasses.replace(affine, wiener_residual=residual)
    kernel, reference = plans(raw, calibration)
    # The kernel's constants are made once, by the plan, and are what every call reads.
    expected = jax.jit(gpu_kernel.prepare)(kernel.constants)
    assert reference.prepared is None and kernel.prepared is not None
    for mine, theirs in zip(jax.tree_util.tree_leaves(kernel.prepared), jax.tree_util.tree_leaves(expected), strict=True):
        np.testing.assert_array_equal(np.asarray(mine), np.asarray(theirs))
    got, want = kernel(raw), reference(raw)
    assert_agree(outputs(got), outputs(want))
    good = np.asarray(want.quality) == 0
    affine_reflectance = np.asarray(Plan(affine, raw.shape, raw.dtype, kernel_mode=None)(raw).reflectance)
    assert np.abs(np.asarray(want.reflectance) - affine_reflectance)[good].max() > 0.02

    def loss(plan):
        def of(r):
            result = plan(r)
            return jnp.nansum(result.reflectance) + 1e-3 * jnp.nansum(result.lab)
        return of

    got_grad, want_grad = jax.grad(loss(kernel))(raw), jax.grad(loss(reference))(raw)
    assert np.all(np.isfinite(np.asarray(got_grad))) and np.count_nonzero(np.asarray(got_grad)) > raw.size // 2
    np.testing.assert_allclose(np.asarray(got_grad), np.asarray(want_grad), rtol=1e-5, atol=1e-9)

    many = kernel_residual.KernelResidual(residual.centre, residual.whitening, jnp.zeros((1025, BANDS), jnp.float32),
                                          jnp.zeros((31, 1025), jnp.float32))
    # eqx.tree_at skips construction's checks: a Calibration built with more than
    # calibration.MAX_INDUCING_POINTS (1024) is refused; the kernel's own bound still guards a plan.
    plan = Plan(eqx.tree_at(lambda c: c.wiener_residual, calibration, many), raw.shape, raw.dtype, kernel_mode=gpu_kernel.INTERPRET)
    assert plan.kernel_mode is None and "applies_residual" in plan.kernel_refusal


class _Client:
    def __init__(self, platform_version):
        self.platform_version = platform_version


class _Device:
    """What `gpu_kernel.mode` reads of a jax device: its platform and its client's version text
    (as jax's own test_util tells CUDA from ROCm)."""

    def __init__(self, platform, platform_version):
        self.platform, self.client = platform, _Client(platform_version)


CUDA = _Device("gpu", "PJRT C API\ncuda 12080")


@pytest.mark.parametrize(
    ("device", "raw_dtype", "compute_dtype", "bands", "switch", "expected"),
    [
        (CUDA, np.uint16, np.float32, 16, None, gpu_kernel.GPU),
        (CUDA, np.float32, np.float32, 32, "1", gpu_kernel.GPU),
        (CUDA, np.uint16, np.float32, 16, "0", None),
        (CUDA, np.uint16, np.float64, 16, None, None),
        (CUDA, np.uint16, np.float32, 15, None, None),
        (CUDA, np.uint16, np.float32, 8, None, None),
        (CUDA, np.int32, np.float32, 16, None, None),
        (_Device("gpu", "PJRT C API\nrocm 60300"), np.uint16, np.float32, 16, None, None),
        (_Device("cpu", "cpu"), np.uint16, np.float32, 16, None, None),
        (None, np.uint16, np.float32, 16, None, None),
    ],
    ids=["cuda", "float32 raw, 32 bands, switched on", "switched off", "float64", "15 bands", "8 bands", "int32 raw",
         "rocm", "cpu", "no device"],
)
def test_which_plans_take_the_kernel(monkeypatch, device, raw_dtype, compute_dtype, bands, switch, expected):
    if switch is None:
        monkeypatch.delenv(gpu_kernel.SWITCH, raising=False)
    else:
        monkeypatch.setenv(gpu_kernel.SWITCH, switch)
    assert gpu_kernel.mode(raw_dtype, compute_dtype, bands, device) == expected


@pytest.mark.parametrize("value", ["off", "AVX2"])
def test_a_mistyped_cpu_kernel_switch_is_refused_on_a_gpu_too(monkeypatch, value):
    """SPHEREJAX_FUSED (the CPU kernel's switch) is refused on a GPU as on the CPU: a plan on an
    H100 took SPHEREJAX_FUSED=off silently, since only the CPU's plans read it."""
    monkeypatch.setenv(fused.SWITCH, value)
    with pytest.raises(ValueError, match=rf"SPHEREJAX_FUSED: expected one of .* or unset, got '{value}'"):
        kernels.choose(fused.AUTO, np.uint16, np.float32, 16, None, True, CUDA)
    monkeypatch.setenv(fused.SWITCH, "0")
    assert kernels.choose(fused.AUTO, np.uint16, np.float32, 16, None, True, CUDA) == (
        kernels.PallasGpu(gpu_kernel.GPU), None)


def test_a_mistyped_switch_is_refused(monkeypatch):
    monkeypatch.setenv(gpu_kernel.SWITCH, "off")
    with pytest.raises(ValueError, match="SPHEREJAX_GPU_KERNEL='off': expected one of 0, 1"):
        gpu_kernel.mode(np.uint16, np.float32, 16, CUDA)


@pytest.mark.parametrize("failure", ["pallas refuses", "lowering raises"])
def test_a_kernel_that_does_not_compile_leaves_the_plan_on_the_jax_numpy_path(caplog, monkeypatch, failure):
    """A plan asked for the compiled kernel where it cannot be compiled corrects by the jax.numpy
    path, with its flat-field mask, and says why at DEBUG: Pallas itself refusing (on the CPU,
    which Pallas runs in interpret mode only; on a GPU the same failure is injected), or the
    kernel's construction raising as a JAX without the Triton backend would."""
    raw, _, calibration = make_calibration_case(24, 40, raw_dtype=np.uint16)
    if failure == "lowering raises" or jax.default_backend() != "cpu":
        def unavailable(*args, **kwargs):
            raise NotImplementedError("no Triton backend in this JAX")

        monkeypatch.setattr(gpu_kernel, "pixel_outputs_pallas", unavailable)
        # jit keeps the traces of earlier tests: one of this signature (on a GPU, a plan of the
        # same frames) would be reused without tracing the failing kernel again (seen on an H100).
        jax.clear_caches()
    with caplog.at_level(logging.DEBUG, logger="spherejax._engine.plan"):
        plan = Plan(calibration, raw.shape, raw.dtype, kernel_mode=gpu_kernel.GPU)
    assert plan.kernel_mode is None and plan.no_flat_field is not None
    assert "the GPU kernel did not compile for (24, 40, 16) frames of uint16" in caplog.text
    reference = Plan(calibration, raw.shape, raw.dtype, kernel_mode=None)
    got, want = plan(raw), reference(raw)
    for name in ("reflectance", "lab", "quality", "p"):
        np.testing.assert_array_equal(np.asarray(getattr(got, name)), np.asarray(getattr(want, name)), err_msg=name)
