"""Correcting through band maps (`spherejax.band_resampling`, `Calibration.band_transforms`): identity
maps give the unregistered numbers, known maps are undone (a scene rendered per band through its
map comes back in register, its edges without fringes), pixels outside a band's frame and next to
saturated ones are flagged, every kernel reads registered pixels, crops and strips match the whole
frame, bad maps are refused in one line, and derivatives through the resampling are finite and
match finite differences."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax import band_resampling as rs
from spherejax._engine import gpu_kernel, registered
from spherejax._engine.plan import Plan

H, W, B = 40, 56, 16
IDENTITY = np.broadcast_to(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), (B, 2, 3))


def shifted(dx, dy, scale=1.0, angle=0.0, shape=(H, W)):
    """(B, 2, 3) maps: about the frame's centre, scale and rotate, then shift by (dx, dy) (B,)."""
    height, width = shape
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    linear = scale * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    maps = np.zeros((B, 2, 3))
    maps[:, :, :2] = linear
    maps[:, :, 2] = centre - linear @ centre + np.stack([dx, dy], axis=1)
    return maps


def scene(x, y, band):
    """A smooth pattern of woven-looking stripes, different in every band: reflectance-like 0.2..0.8."""
    return 0.5 + 0.3 * np.sin(0.45 * x + 0.2 * band) * np.cos(0.3 * y - 0.1 * band)


def rendered(maps, white_level=20000.0, dark_level=100.0):
    """Raw frames whose band b shows `scene` through its map: native pixel n of band b holds the
    scene at the reference position A_b^-1 n, so that the registered pixel y (sampled at A_b y)
    holds the scene at y."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    raw = np.empty((H, W, B))
    for b in range(B):
        full = np.vstack([maps[b], [0, 0, 1]])
        inverse = np.linalg.inv(full)
        rx = inverse[0, 0] * x + inverse[0, 1] * y + inverse[0, 2]
        ry = inverse[1, 0] * x + inverse[1, 1] * y + inverse[1, 2]
        raw[..., b] = dark_level + (white_level - dark_level) * scene(rx, ry, b)
    return raw.astype(np.float32)


def calibration(maps=None, *, saturation=60000.0, seed=0):
    rng = np.random.default_rng(seed)
    dark = np.full((H, W, B), 100.0, np.float32)
    white = np.full((H, W, B), 20000.0, np.float32) * rng.uniform(0.98, 1.02, (1, 1, B)).astype(np.float32)
    patch = np.zeros((H, W), bool)
    patch[10:16, 20:28] = True
    wiener = (rng.uniform(0, 1, (31, B)) / B).astype(np.float32)
    return sj.Calibration(dark, white, patch, sj.identity_coeffs(B), wiener, saturation=saturation,
                          band_transforms=maps)


def test_identity_maps_give_the_unregistered_numbers():
    raw = np.random.default_rng(1).integers(2000, 19000, (2, H, W, B)).astype(np.uint16)
    plain, mapped = sj.correct(raw, calibration()), sj.correct(raw, calibration(IDENTITY))
    np.testing.assert_array_equal(np.asarray(mapped.quality), np.asarray(plain.quality))
    np.testing.assert_allclose(np.asarray(mapped.p), np.asarray(plain.p), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(mapped.reflectance), np.asarray(plain.reflectance), rtol=1e-5, atol=1e-6)


def test_known_maps_are_undone_and_their_fringes_with_them():
    """A scene rendered through sub-pixel maps (shift up to 1.5 px, scale 1e-3, rotation 1 mrad):
    registered, each band's response is the scene at the reference pixel to bilinear
    interpolation's own error, h^2 / 8 |f''| = (0.45^2 + 0.3^2) / 8 * 0.3 = 0.011 for this
    pattern; taken as in register, it is off by most of the pattern's swing over 1.5 px."""
    rng = np.random.default_rng(2)
    maps = shifted(rng.uniform(-1.5, 1.5, B), rng.uniform(-1.5, 1.5, B), scale=1.001, angle=1e-3)
    raw = rendered(maps)
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    truth = np.stack([scene(x, y, b) for b in range(B)], axis=-1)
    registered_v = np.asarray(sj.correct(raw, calibration(maps), intermediates=True).v, np.float64)
    unregistered_v = np.asarray(sj.correct(raw, calibration(), intermediates=True).v, np.float64)
    inside = np.s_[3:-3, 3:-3]
    # v is the flat field of the scene: white 20000 * band gain, scene * 19900 + 100 -> v ~ scene.
    scale = np.median(registered_v[inside] / truth[inside], axis=(0, 1))
    error_registered = np.abs(registered_v[inside] / scale - truth[inside]).max()
    error_unregistered = np.abs(unregistered_v[inside] / scale - truth[inside]).max()
    assert error_registered < 0.013 and error_unregistered > 0.1, (error_registered, error_unregistered)


def test_pixels_a_band_does_not_cover_are_flagged_and_nan():
    maps = shifted(np.full(B, 2.5), np.zeros(B))  # every band lies 2.5 px to the right
    result = sj.correct(rendered(IDENTITY), calibration(maps))
    quality = np.asarray(result.quality)
    # Reference columns x with x + 2.5 > W - 1 have no band pixel: the last 3 columns.
    assert np.all(quality[:, -3:] & sj.QUALITY_NOT_COVERED) and not np.any(quality[:, :-3])
    assert np.isnan(np.asarray(result.reflectance)[:, -3:]).all()
    assert np.isfinite(np.asarray(result.reflectance)[:, :-3]).all()


def test_a_saturated_pixel_flags_the_registered_pixels_it_reaches():
    maps = shifted(np.full(B, 0.5), np.zeros(B))  # half a pixel: each registered pixel reads two
    raw = rendered(IDENTITY).astype(np.uint16)
    raw[20, 30, 4] = 65535
    quality = np.asarray(sj.correct(raw, calibration(maps, saturation=65535.0)).quality)
    assert np.all(quality[:, -1] == sj.QUALITY_NOT_COVERED)  # x + 0.5 > W - 1 there
    flagged = np.argwhere(quality[:, :-1] != 0)
    # x + 0.5 interpolates native x and x + 1: reference pixels 29 and 30 of row 20 read native 30.
    np.testing.assert_array_equal(flagged, [[20, 29], [20, 30]])
    assert np.all(quality[20, 29:31] == sj.QUALITY_SATURATED)


def test_the_white_patch_ratio_reads_registered_pixels():
    """A bright square on the patch, shifted in band 3 only: registered, band 3's p is the other
    bands' (the square sits where the patch is in every band); taken as in register, it is not."""
    maps = shifted(np.where(np.arange(B) == 3, 2.0, 0.0), np.zeros(B))
    raw = rendered(IDENTITY)
    raw[10:16, 20:28] = 12000.0
    shifted_raw = raw.copy()
    shifted_raw[..., 3] = np.roll(raw[..., 3], 2, axis=1)  # band 3's image lies 2 px to the right
    p_registered = np.asarray(sj.patch_ratio(shifted_raw, calibration(maps)))
    p_plain = np.asarray(sj.patch_ratio(shifted_raw, calibration()))
    gains = np.asarray(calibration().white[0, 0] - 100.0)
    expected = (gains - 0) / (12000.0 - 100.0)
    np.testing.assert_allclose(p_registered, expected, rtol=1e-5)
    assert abs(p_plain[3] / expected[3] - 1) > 0.05


def _plans(raw, cal, mode):
    return registered.RegisteredPlan(cal, raw.shape, raw.dtype,
                                     make_plan=lambda c, s, d: Plan(c, s, d, kernel_mode=mode))


@pytest.mark.parametrize("mode", [gpu_kernel.INTERPRET, "auto"])
def test_every_kernel_reads_registered_pixels(mode):
    """The Pallas kernel (interpreted) and the fused CPU kernel (where built) correct registered
    frames as the jax.numpy definition does."""
    rng = np.random.default_rng(3)
    maps = shifted(rng.uniform(-1, 1, B), rng.uniform(-1, 1, B), scale=0.9995)
    raw = rendered(maps).astype(np.uint16)
    raw[5, 5, 2] = 65535
    cal = calibration(maps, saturation=65535.0)
    plan = _plans(raw, cal, mode)
    reference = _plans(raw, cal, None)
    assert reference.kernel_mode is None
    got, want = plan(raw), reference(raw)
    np.testing.assert_array_equal(np.asarray(got.quality), np.asarray(want.quality))
    np.testing.assert_allclose(np.asarray(got.reflectance), np.asarray(want.reflectance), rtol=2e-5, atol=2e-6)
    np.testing.assert_allclose(np.asarray(got.lab), np.asarray(want.lab), rtol=1e-4, atol=1e-3)


def test_crops_and_strips_with_their_halo_give_the_whole_frames_rows():
    rng = np.random.default_rng(4)
    maps = shifted(rng.uniform(-1.5, 1.5, B), rng.uniform(-1.5, 1.5, B), scale=1.0005)
    cal = calibration(maps)
    raw = rendered(maps)
    whole = sj.correct(raw, cal)
    p = sj.patch_ratio(raw, cal)
    n0, n1, _, _ = rs.read_box((12, 24, 0, W), maps, (H, W))
    assert n0 < 12 and n1 > 24
    strip = sj.correct(raw[n0:n1], cal.rows(n0, n1), p=p)
    keep = np.s_[12 - n0:24 - n0]
    np.testing.assert_array_equal(np.asarray(strip.quality)[keep], np.asarray(whole.quality)[12:24])
    np.testing.assert_allclose(np.asarray(strip.reflectance)[keep], np.asarray(whole.reflectance)[12:24],
                               rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(
    ("maps", "message"),
    [
        (np.zeros((B, 3, 3)), r"band_transforms: expected shape \(16, 2, 3\)"),
        (np.where(np.arange(6).reshape(1, 2, 3) == 0, -1.0, IDENTITY), r"band 0's linear part differs from the identity by 2"),
        (shifted(np.full(B, 80.0), np.zeros(B)), r"a band is displaced by 80 px in the frame, expected at most 50 px"),
        (np.full((B, 2, 3), np.nan), r"expected finite numbers"),
    ],
)
def test_bad_maps_are_refused_in_one_line(maps, message):
    with pytest.raises(ValueError, match=message) as raised:
        calibration(maps)
    assert "\n" not in str(raised.value)


def test_derivatives_through_the_resampling_are_finite_and_match_finite_differences():
    rng = np.random.default_rng(5)
    maps = shifted(rng.uniform(-1, 1, B), rng.uniform(-1, 1, B))
    raw = jnp.asarray(rendered(maps))
    base = calibration(maps)

    def loss(translation):
        moved = jnp.asarray(maps, jnp.float32).at[:, :, 2].set(translation)
        result = sj.correct(raw, dataclasses.replace(base, band_transforms=moved))
        good = result.quality == 0
        return jnp.sum(jnp.where(good[..., None], result.reflectance, 0.0))

    translation = jnp.asarray(maps[:, :, 2], jnp.float32)
    gradient = np.asarray(jax.grad(loss)(translation))
    assert np.isfinite(gradient).all() and np.count_nonzero(gradient) > B
    # Central differences along one direction (piecewise-linear interpolation: a step well inside
    # one cell of the sampling grid).
    direction = jnp.asarray(rng.normal(size=translation.shape), jnp.float32)
    step = 1e-3
    with jax.enable_x64(False):
        numeric = (loss(translation + step * direction) - loss(translation - step * direction)) / (2 * step)
    np.testing.assert_allclose(float(np.sum(gradient * np.asarray(direction))), float(numeric), rtol=0.05)
    raw_gradient = np.asarray(jax.grad(lambda r: jnp.nansum(sj.correct(r, base).reflectance))(raw))
    assert np.isfinite(raw_gradient).all()


def test_halo_and_read_box_cover_the_reach_of_the_maps():
    maps = shifted(np.array([2.3] + [0.0] * (B - 1)), np.array([-1.2] + [0.0] * (B - 1)), scale=1.001)
    halo = rs.halo_px(maps, (H, W))
    reach = np.abs(rs.displacements(maps, (H, W))).max()
    assert reach <= halo - 1 < reach + 1
    assert rs.read_box((0, 10, 5, 20), maps, (H, W)) == (0, 10 + halo, 5 - halo, 20 + halo)
    local = np.asarray(rs.local_transforms(maps, 7, 3))
    point = np.array([4.0, 5.0, 1.0])
    np.testing.assert_allclose(local[0] @ point, maps[0] @ (point + [3, 7, 0]) - [3, 7], atol=1e-9)


@pytest.mark.skipif(not registered.fused_registration.applies(np.uint16, np.float32, B),
                    reason="the compiled registration is not built here (no C++ compiler at install)")
@pytest.mark.parametrize("raw_dtype", [np.uint16, np.float32])
def test_the_compiled_registration_is_the_definition(raw_dtype):
    """The CPU loop (kernel/register_bands.cc) against `band_resampling.registered_frames`: the
    same bits on every pixel (saturated, not finite, no flat field, not covered, and a whole-pixel
    shift whose zero-weight taps fall on flagged pixels), the same values to float rounding, for
    two images at once."""
    rng = np.random.default_rng(6)
    maps = shifted(rng.uniform(-1.5, 1.5, B), rng.uniform(-1.5, 1.5, B), scale=1.0007, angle=4e-4)
    maps[5, :, 2] = np.round(maps[5, :, 2])  # whole pixels: the right and lower taps weigh 0
    maps[5, :, :2] = np.eye(2)
    cal = calibration(maps, saturation=60000.0)
    dark, white = jnp.asarray(cal.dark), jnp.asarray(cal.white)
    white = white.at[7, 9, 3].set(50.0)  # no flat field there
    raw = rendered(maps)[None].repeat(2, axis=0)
    raw[0, 20, 30, 5] = 60000.0
    raw[1, 12, 40, 2] = 65000.0
    if raw_dtype == np.float32:
        raw[1, 3, 3, 0] = np.nan
    raw = jnp.asarray(raw.astype(raw_dtype))
    transforms = jnp.asarray(maps, jnp.float32)
    signal = rs.registered_white(dark, white, transforms)
    inverse = registered.fused_registration.inverse_signal(dark, white)
    got = jax.jit(functools.partial(registered.fused_registration.registered_frames, saturation=60000.0))(
        raw, dark, white, inverse, transforms, signal)
    want = rs.registered_frames(raw, dark, white, transforms, signal, saturation=60000.0)
    np.testing.assert_array_equal(np.asarray(got[1]), np.asarray(want[1]))
    bits = np.asarray(want[1])
    expected = [sj.QUALITY_SATURATED, sj.QUALITY_WHITE_NOT_ABOVE_DARK, sj.QUALITY_NOT_COVERED]
    expected += [sj.QUALITY_NONFINITE] if raw_dtype == np.float32 else []
    assert all(np.any(bits & bit) for bit in expected)
    np.testing.assert_allclose(np.asarray(got[0]), np.asarray(want[0]), rtol=2e-6, atol=2e-3)


def test_a_region_is_measured_on_registered_pixels():
    """`spherejax.measure` with band maps: the region's mean reflectance is the mean of what
    `correct` gives its pixels, registered."""
    rng = np.random.default_rng(7)
    maps = shifted(rng.uniform(-1.5, 1.5, B), rng.uniform(-1.5, 1.5, B))
    cal = calibration(maps)
    raw = rendered(maps)
    mask = np.zeros((H, W), bool)
    mask[20:30, 30:44] = True
    measured = sj.measure(raw, cal, mask)
    corrected = np.asarray(sj.correct(raw, cal).reflectance, np.float64)[mask]
    assert measured.pixels == mask.sum() and measured.excluded == 0
    np.testing.assert_allclose(measured.reflectance, corrected.mean(axis=0), rtol=1e-5, atol=1e-6)
