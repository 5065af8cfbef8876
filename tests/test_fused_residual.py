"""The fused CPU kernel's kernel residual (kernel/fused_correct.h, residual_of: E8-E10 of
`spherejax.estimation.kernel_residual`) on each instruction-set variant, AVX2 above all: one
template whose variants differ only in their lane policy.

Called directly (`fused.correct_arrays`, with `kernel_mode` naming the variant) and through XLA
(`fused._kernel_call`), against the jax.numpy definition (`SPHEREJAX_FUSED=0`) and float64 numpy
(E9-E10 written out): uint16 and float32 raw with every kind of bad pixel, several images (one
whose patch ratio is not finite), a partial last block, inducing counts that fill whole chunks
of the template, part of one and need padding, and weights of rank 8 and below. Also what the
extension declares it supports (`capabilities`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax import estimation, pixel_constants
from spherejax._engine import fused

from .helpers import numpy_kernel_estimate
from .helpers import make_fused_case as make_case

pytestmark = pytest.mark.skipif(not fused.built(), reason="the fused kernel was not built")

#: The variants this CPU runs, each of which applies the residual with its own code.
VARIANTS = [name for name in (fused.AVX512, fused.AVX2, fused.GENERIC) if name in fused.supported_variants()]
needs_avx2 = pytest.mark.skipif(fused.AVX2 not in fused.supported_variants(), reason="this CPU does not run AVX2")

# 37 x 45 pixels: 1665 = 52 blocks of 32 and one pixel, so every call ends on a partial block.
HEIGHT, WIDTH, BANDS = 37, 45, 16


def _with_residual(raw, calibration, inducing: int, rank: int, seed: int):
    """The calibration with a kernel residual that matters on `raw`: whitened on its own Stage II
    responses (halved, so that k(v) spans 1 down to nothing), `inducing` inducing points at its
    pixels and weights of rank `rank` (31, inducing), entries of about 0.015."""
    rng = np.random.default_rng(seed)
    result = sj.correct(raw, calibration, intermediates=True)
    good = np.asarray(result.quality) == 0
    v = np.asarray(result.v_stage2, np.float64)[good]
    mu, S = estimation.kernel_residual.whitening_of(v)
    S = S / 2.0
    Z = (v[rng.choice(len(v), inducing, replace=False)] - mu) @ S.T
    A = rng.normal(scale=0.015, size=(31, rank)) @ rng.normal(size=(rank, inducing)) / np.sqrt(rank)
    residual = estimation.KernelResidual(*(jnp.asarray(x, jnp.float32) for x in (mu, S, Z, A)))
    return dataclasses.replace(calibration, wiener_residual=residual)


def _arrays(raw, calibration, p):
    """What the kernel reads for frames raw (N, H, W, B) with patch ratios p (N, B)."""
    c = pixel_constants.PixelConstants.of(calibration, jnp.float32)
    projection, bias, white_xyz = fused.kernel_constants(c.wiener, c.wiener_offset, c.tristimulus_weights)
    residual = fused.residual_constants(c.wiener_residual, c.tristimulus_weights, BANDS)
    images, pixels = raw.shape[0], raw.shape[1] * raw.shape[2]
    inputs = (np.ascontiguousarray(raw.reshape(images, pixels, BANDS)), np.asarray(c.dark).reshape(pixels, BANDS),
              np.asarray(c.white).reshape(pixels, BANDS), np.asarray(p, np.float32), np.asarray(c.coeffs),
              *(np.asarray(x) for x in (projection, bias, white_xyz)))
    return inputs, tuple(np.asarray(x) for x in residual)


def _direct(raw, calibration, p, variant, threads=2):
    """(reflectance, lab, quality) of the direct call, shaped as raw's frames."""
    inputs, residual = _arrays(raw, calibration, p)
    images, pixels = inputs[0].shape[:2]
    out = (np.empty((images, pixels, 31), np.float32), np.empty((images, pixels, 3), np.float32),
           np.empty((images, pixels), np.uint8))
    fused.correct_arrays(*inputs, calibration.saturation, variant, out, threads, residual=residual)
    return tuple(x.reshape(raw.shape[:-1] + x.shape[2:]) for x in out)


@pytest.fixture(scope="module", params=[np.uint16, np.float32], ids=["uint16", "float32"])
def frames(request):
    """Two frames of every kind of bad pixel (`make_case`) with a non-zero Wiener offset, their
    patch ratios, the second made not finite in one band (quality 8 on all its pixels)."""
    raw, calibration = make_case(HEIGHT, WIDTH, BANDS, raw_dtype=request.param, images=(2,), offset=True)
    # Reflectances of 0 to about 1.5, as a real estimator gives (make_case's reach 11).
    calibration = dataclasses.replace(calibration, wiener=calibration.wiener / 8)
    p = np.asarray(sj.patch_ratio(raw, calibration), np.float32).copy()
    p[1, 5] = np.nan
    return raw, calibration, p


def _definition(raw, calibration, p, monkeypatch):
    """The jax.numpy path's result (the definition), with its v_tilde."""
    with monkeypatch.context() as patched:
        patched.setenv(fused.SWITCH, "0")
        return sj.correct(raw, calibration, p=jnp.asarray(p), intermediates=True)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize(("inducing", "rank"), [(8, 8), (64, 8), (197, 8), (40, 3)])
def test_the_residual_on_each_variant_is_the_definitions(frames, monkeypatch, variant, inducing, rank):
    """Inducing counts: one step (8), two whole chunks of 32 (64), 197 padded to 200 (six chunks
    and part of one), 40 (a chunk and part of one) with weights of rank 3, below the kernel's 8
    (its factor and basis padded with zeros)."""
    raw, affine, p = frames
    calibration = _with_residual(raw[0], affine, inducing, rank, seed=inducing + rank)
    want = _definition(raw, calibration, p, monkeypatch)
    reflectance, lab, quality = _direct(raw, calibration, p, variant)

    expected_quality = np.asarray(want.quality)
    np.testing.assert_array_equal(quality, expected_quality)
    assert (expected_quality[1] & 8).all() and ((expected_quality[0] & 0b11110111) != 0).sum() >= 4
    bad = expected_quality != 0
    for got in (reflectance, lab):  # NaN exactly where a quality bit is set
        np.testing.assert_array_equal(np.isnan(got), np.broadcast_to(bad[..., None], got.shape))
    good = ~bad
    # The residual is no small part of the estimate here ...
    affine_reflectance = np.asarray(sj.correct(raw, affine, p=jnp.asarray(p)).reflectance)
    assert np.abs(np.asarray(want.reflectance) - affine_reflectance)[good].max() > 0.02
    # ... and the kernel gives it as the definition and as float64 numpy do. The generic code's
    # e^x clips x at -87 as (x - 87) + |x + 87|, rounded to the ulp of 87 (7.6e-6): up to 4e-6
    # relative in k(v), about 2e-6 in these estimates.
    atol = 4e-6 if variant == fused.GENERIC else 2e-6
    np.testing.assert_allclose(reflectance[good], np.asarray(want.reflectance)[good], rtol=0, atol=atol)
    np.testing.assert_allclose(lab[good], np.asarray(want.lab)[good], rtol=0, atol=5e-4)
    expected = numpy_kernel_estimate(np.asarray(want.v_stage2, np.float64), calibration)
    np.testing.assert_allclose(reflectance[good].astype(np.float64), expected[good], rtol=0, atol=atol + 1e-6)


@needs_avx2
def test_avx2_runs_its_own_residual_code(frames):
    """AVX2 asked with a residual runs the AVX2 block (Avx2Lanes: 16 pixels as two ymm registers,
    its own exponential), not the generic code: its bits differ from the generic code's in the
    last places (each within its tolerance of the definition above)."""
    raw, affine, p = frames
    calibration = _with_residual(raw[0], affine, 64, 8, seed=3)
    avx2 = _direct(raw, calibration, p, fused.AVX2)
    generic = _direct(raw, calibration, p, fused.GENERIC)
    np.testing.assert_array_equal(avx2[2], generic[2])
    good = generic[2] == 0
    assert not np.array_equal(avx2[0][good], generic[0][good])
    np.testing.assert_allclose(avx2[0][good], generic[0][good], rtol=0, atol=6e-6)


@pytest.mark.parametrize("variant", VARIANTS)
def test_strips_and_threads_give_the_whole_frames_bits(frames, variant):
    """Each pixel's lane does the same sums whatever its neighbours or place in a block: rows of
    the frames (their first pixels at other places in a block) and other thread counts give the
    bits of the whole call."""
    raw, affine, p = frames
    calibration = _with_residual(raw[0], affine, 64, 8, seed=4)
    whole = _direct(raw, calibration, p, variant, threads=2)
    for row0, row1 in ((0, 5), (5, 37), (13, 14)):
        part = _direct(raw[:, row0:row1], calibration.rows(row0, row1), p, variant, threads=1)
        for got, want in zip(part, whole):
            np.testing.assert_array_equal(got, want[:, row0:row1])


@pytest.mark.parametrize("variant", VARIANTS)
def test_the_xla_route_gives_the_direct_routes_bits(frames, variant):
    """The custom call (`fused._kernel_call`, as jitted programs run it) with a residual gives the
    direct call's bits: the same code behind both entries."""
    raw, affine, p = frames
    calibration = _with_residual(raw[0], affine, 64, 8, seed=5)
    inputs, residual = _arrays(raw, calibration, p)
    call = jax.jit(fused._kernel_call, static_argnames=("saturation", "kernel_mode"))
    through_xla = call(*inputs, saturation=calibration.saturation, kernel_mode=variant, residual=residual)
    direct = _direct(raw, calibration, p, variant)
    for got, want in zip(through_xla, direct):
        np.testing.assert_array_equal(np.asarray(got).reshape(want.shape), want)


def test_the_extension_declares_what_it_supports():
    """`capabilities()` (module.cc) against the constants the Python side uses and what the kernel
    does: every variant applies the residual, at rank 8, rows in eights (residual_constants pads to
    that), up to 64 bands, uint16 and float32 raw."""
    caps = fused._fused_correct.capabilities()
    assert caps == {
        "max_bands": fused.MAX_BANDS, "variant_bands": fused.VARIANT_BANDS,
        "raw_dtypes": tuple(np.dtype(d).name for d in fused.RAW_DTYPES), "residual_rank": fused.RESIDUAL_RANK,
        "residual_rows": 8, "residual_variants": (fused.AVX512, fused.AVX2, fused.GENERIC),
    }
    residual = estimation.KernelResidual(jnp.zeros(BANDS), jnp.eye(BANDS), jnp.zeros((13, BANDS)), jnp.zeros((31, 13)))
    whitening, inducing, factor, basis = fused.residual_constants(residual, jnp.zeros((31, 3)), BANDS)
    assert whitening.shape[0] % caps["residual_rows"] == 0 and inducing.shape[0] % caps["residual_rows"] == 0
    assert factor.shape[1] == basis.shape[0] == caps["residual_rank"]
