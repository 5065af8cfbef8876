"""Outputs that are not finite are flagged on every kernel (docs/reliability.md, section 2):
a pixel whose inputs the flags call good but whose reflectance or Lab comes out infinite or
NaN (a float raw of 1e38 over a white signal of one count, or an estimator whose product
overflows float32, such as residual weights of 3e38 in a calibration made without its checks) gets
`Quality.NONFINITE` and NaN in every output, so that every output is NaN exactly where quality says
so. The rule is `equations.flag_nonfinite_outputs`; the fused CPU kernel (every variant this CPU
runs), the Pallas GPU kernel (in interpret mode on CPU) and the jax.numpy definition all apply it
and agree on the bits.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax import estimation
from spherejax._engine import fused, gpu_kernel
from spherejax._engine.plan import Plan

H, W, B = 12, 10, 16
#: The kernels: None (the jax.numpy definition), each fused variant this CPU runs, and the
#: Pallas kernel interpreted on CPU.
KERNELS = [None, *fused.supported_variants(), gpu_kernel.INTERPRET]


def calibration() -> sj.Calibration:
    """Float raw, no saturation level; a region (rows 6-10, columns 6-9) whose white signal is one
    count, away from the white patch (rows 2-4, columns 2-4), where a large raw value overflows."""
    rng = np.random.default_rng(0)
    patch = np.zeros((H, W), bool)
    patch[2:5, 2:5] = True
    dark = rng.uniform(50, 60, (H, W, B)).astype(np.float32)
    white = rng.uniform(9000, 12000, (H, W, B)).astype(np.float32)
    white[6:11, 6:10] = dark[6:11, 6:10] + 1
    return sj.Calibration(dark=dark, white=white, patch=patch, coeffs=np.tile([1.0, 0, 0, 0], (B, 1)).astype(np.float32),
                          wiener=rng.uniform(0, 0.1, (31, B)).astype(np.float32), saturation=None)


def frames(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    raw = rng.uniform(3000, 6000, (H, W, B)).astype(np.float32)
    pixels = [(r, c) for r in range(6, 11) for c in range(6, 10)]
    for index in rng.choice(len(pixels), 8, replace=False):
        r, c = pixels[index]
        bands = rng.choice(B, rng.integers(1, B + 1), replace=False)
        raw[r, c, bands] = rng.choice([3e38, 1e38, 1e37, 1e35, 1e30, -1e38, 2e4])
    return raw


def outputs(calibration, raw, kernel, monkeypatch):
    """(reflectance, lab, quality) as NumPy of `kernel` (None, a fused variant or the interpreted
    GPU kernel), checking that the plan really took it."""
    if kernel == gpu_kernel.INTERPRET:
        plan = Plan(calibration, raw.shape, raw.dtype, kernel_mode=gpu_kernel.INTERPRET)
    else:
        monkeypatch.setenv(fused.SWITCH, kernel or "0")
        plan = sj.plan(calibration, raw.shape, dtype=raw.dtype)
    assert plan.kernel_mode == kernel, plan.kernel_refusal
    result = plan(raw)
    return tuple(np.asarray(x) for x in (result.reflectance, result.lab, result.quality))


def check_nan_exactly_where_flagged(reflectance, lab, quality) -> None:
    bad = quality != 0
    for out in (reflectance, lab):
        np.testing.assert_array_equal(np.isnan(out), np.broadcast_to(bad[..., None], out.shape))
        assert np.isfinite(out[~bad]).all()


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("kernel", KERNELS, ids=str)
def test_overflowing_outputs_are_flagged_and_nan_on_every_kernel_alike(kernel, seed, monkeypatch):
    cal, raw = calibration(), frames(seed)
    reflectance, lab, quality = outputs(cal, raw, kernel, monkeypatch)
    check_nan_exactly_where_flagged(reflectance, lab, quality)
    # Raw of 3e38 over one count overflows: flagged bit 2 though the raw value is finite.
    huge = np.any(np.abs(raw) >= 1e38, axis=-1) & ~np.any(raw < 0, axis=-1)
    assert huge.any() and np.all(quality[huge] & sj.QUALITY_NONFINITE)
    # The same bits as the definition's.
    _, _, expected = outputs(cal, raw, None, monkeypatch)
    np.testing.assert_array_equal(quality, expected)


def test_the_definition_flags_what_overflowed_and_only_that(monkeypatch):
    """The definition: bit 2 exactly on pixels whose finite raw gave outputs that are not finite
    before the flag (computed here from the unflagged projection), and intermediates NaN there too."""
    cal, raw = calibration(), frames(1)
    monkeypatch.setenv(fused.SWITCH, "0")
    result = sj.correct(raw, cal, intermediates=True)
    quality = np.asarray(result.quality)
    raw_nonfinite = ~np.isfinite(raw).all(axis=-1)
    v_tilde = np.asarray(sj.stage2(np.where(np.isfinite(raw), (raw - np.asarray(cal.dark)) / (np.asarray(cal.white) - np.asarray(cal.dark)), 0),
                                   np.asarray(result.p), cal.coeffs), np.float32)
    weights = np.asarray(sj.colorimetry.tristimulus_weights(cal.illuminant), np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        estimate = v_tilde @ np.asarray(cal.wiener).T  # reflectance
        xyz = v_tilde @ (np.asarray(cal.wiener).T @ weights)  # XYZ as the definition folds it; Lab follows
    overflowed = ~(np.isfinite(estimate).all(axis=-1) & np.isfinite(xyz).all(axis=-1)) & ~raw_nonfinite & ((quality & ~np.uint8(sj.QUALITY_NONFINITE)) == 0)
    assert overflowed.sum() >= 1
    np.testing.assert_array_equal((quality & sj.QUALITY_NONFINITE) != 0, overflowed | raw_nonfinite)
    for name in ("v", "v_stage1", "v_stage2"):
        assert np.isnan(np.asarray(getattr(result, name))[quality != 0]).all(), name


@pytest.mark.parametrize("kernel", KERNELS, ids=str)
def test_residual_weights_of_3e38_give_no_infinite_good_pixel(kernel, monkeypatch):
    """Weights of 3e38 (refused when a calibration is built, saved or opened: here put in by
    tree_map, which skips the checks) overflow near the inducing points: those pixels are flagged
    and NaN, no infinity comes out with quality 0."""
    cal = calibration()
    white = np.asarray(cal.white).copy()
    white[6:11, 6:10] = np.asarray(cal.dark)[6:11, 6:10] + 9000
    cal = dataclasses.replace(cal, white=white)
    raw = np.random.default_rng(2).uniform(3000, 6000, (H, W, B)).astype(np.float32)
    reference = sj.correct(raw, cal, intermediates=True)
    v = np.asarray(reference.v_stage2).reshape(-1, B)
    mu, S = estimation.kernel_residual.whitening_of(v)
    Z = (v[:8] - mu) @ S.T
    residual = estimation.KernelResidual(*(jnp.asarray(x, jnp.float32) for x in (mu, S, Z, np.zeros((31, 8)))))
    cal = dataclasses.replace(cal, wiener_residual=residual)
    big = jnp.full((31, 8), 3e38, jnp.float32)
    unchecked = jax.tree_util.tree_map(lambda x: big if x is residual.weights else x, cal)
    reflectance, lab, quality = outputs(unchecked, raw, kernel, monkeypatch)
    check_nan_exactly_where_flagged(reflectance, lab, quality)
    assert (quality & sj.QUALITY_NONFINITE).sum() >= 8  # at least the inducing points' own pixels


def test_finite_outputs_are_unchanged_by_the_flag(monkeypatch):
    """An ordinary frame: no pixel flagged, and the definition's numbers are the fused kernel's as
    before (the flag changes nothing where outputs are finite)."""
    cal = calibration()
    raw = np.random.default_rng(4).uniform(3000, 6000, (H, W, B)).astype(np.float32)
    definition = outputs(cal, raw, None, monkeypatch)
    assert not definition[2].any()
    for kernel in KERNELS[1:]:
        got = outputs(cal, raw, kernel, monkeypatch)
        np.testing.assert_array_equal(got[2], definition[2])
        np.testing.assert_allclose(got[0], definition[0], rtol=2e-6, atol=2e-6)
        np.testing.assert_allclose(got[1], definition[1], rtol=2e-5, atol=2e-3)
