"""Stage I: flat field (Eq. 10), white-patch ratio (Eq. 14-15), Stage I (Eq. 16-17)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj

from .helpers import lambertian_sphere_frames

H, W, B = 24, 32, 16


def patch_mask(h=H, w=W):
    mask = np.zeros((h, w), bool)
    mask[2:7, 3:8] = True
    return mask


def random_frames(dtype=np.float64, seed=0):
    rng = np.random.default_rng(seed)
    dark = rng.uniform(90, 110, (H, W, B))
    white = dark + rng.uniform(8000, 12000, (H, W, B))
    raw = dark + (white - dark) * rng.uniform(0.05, 0.95, (H, W, B))
    return raw.astype(dtype), dark.astype(dtype), white.astype(dtype)


@pytest.fixture(scope="module")
def sphere():
    rng = np.random.default_rng(42)
    wall = rng.uniform(0.95, 0.99, B)  # spectral sphere wall reflectance (docs/design.md)
    yy, xx = np.mgrid[0:H, 0:W]
    r2 = ((yy - H / 2) ** 2 + (xx - W / 2) ** 2) / (H**2 + W**2)
    beta = (1.0 - 0.6 * r2) * (1.0 + 0.05 * xx / W)  # vignetting and a gradient
    return dict(
        rho_wall=wall,
        # Port fractions: ports take 1.63 % of the sphere (Section 5), the holder a few %.
        alpha_ww=0.955,
        alpha_wsp=0.03,
        alpha_spw=0.97,
        gamma_phi0=rng.uniform(0.5, 2.0, B) * 40.0,
        dark=rng.uniform(95, 105, (H, W, B)),
        beta=beta,
    )


class TestLambertianSphere:
    """Zou et al. Eq. 16: on a Lambertian sphere Stage I returns rho_s / rho_r exactly, whatever
    the background (through k_s, Eq. 9) and the lamp (Delta Phi_0)."""

    @pytest.mark.parametrize("background", [0.03, 0.2, 0.5, 0.8, 0.97])
    @pytest.mark.parametrize("lamp", [0.97, 1.0, 1.03])
    def test_stage1_returns_reflectance_ratio(self, sphere, background, lamp):
        rng = np.random.default_rng(int(background * 100) + int(lamp * 1000))
        patch = patch_mask()
        rho_standard = 0.985
        rho_patch = rng.uniform(0.96, 0.99, B)
        # A textured sample on a uniform background: the mean reflectance sets k_s.
        rho_sample = np.full((H, W, B), background) * rng.uniform(0.9, 1.1, (1, 1, B))
        rho_sample[10:20, 12:28] = rng.uniform(0.02, 0.9, (10, 16, B))
        lamp_change = lamp * rng.uniform(0.99, 1.01, B)  # band-to-band fluctuation too
        beta, other = sphere["beta"], {k: v for k, v in sphere.items() if k != "beta"}
        white, raw = lambertian_sphere_frames(
            rho_sample, rho_standard, rho_patch, patch, beta, lamp_change, **other
        )
        v = sj.flat_field(raw, sphere["dark"], white)
        p = sj.white_patch_ratio(raw, sphere["dark"], white, patch)
        v_check = np.asarray(sj.stage1(v, p))
        outside = ~patch
        np.testing.assert_allclose(v_check[outside], (rho_sample / rho_standard)[outside], rtol=1e-6, atol=0)
        # The flat field alone does not remove q_s (Eq. 10-11) except by accident:
        q_s = np.asarray(v)[outside] / (rho_sample / rho_standard)[outside]
        if background < 0.9 or lamp != 1.0:
            assert np.max(np.abs(q_s - 1.0)) > 1e-3

    def test_p_is_inverse_q(self, sphere):
        """Eq. 14-15: p_s = 1 / q_s, with q_s from Eq. 11."""
        patch = patch_mask()
        rho_sample = np.full((H, W, B), 0.1)
        lamp_change = np.full(B, 1.02)
        other = {k: v for k, v in sphere.items() if k != "beta"}
        white, raw = lambertian_sphere_frames(
            rho_sample, 0.985, np.full(B, 0.98), patch, sphere["beta"], lamp_change, **other
        )
        p = np.asarray(sj.white_patch_ratio(raw, sphere["dark"], white, patch))
        holder_r = np.where(patch, 0.98, 0.985).mean()
        holder_s = np.where(patch, 0.98, 0.1).mean()
        k_r = 0.955 + 0.03 * 0.97 * holder_r
        k_s = 0.955 + 0.03 * 0.97 * holder_s
        q_s = (1 - k_r * sphere["rho_wall"]) / (1 - k_s * sphere["rho_wall"]) * lamp_change
        np.testing.assert_allclose(p, 1.0 / q_s, rtol=1e-12)
        assert np.all(p > 1.0)  # a dark sample darkens the sphere


class TestFlatField:
    def test_white_is_one_dark_is_zero(self, dtype):
        _, dark, white = random_frames(dtype)
        np.testing.assert_allclose(np.asarray(sj.flat_field(white, dark, white)), 1.0, rtol=1e-6)
        np.testing.assert_allclose(np.asarray(sj.flat_field(dark, dark, white)), 0.0, atol=1e-12)
        assert sj.flat_field(white, dark, white).dtype == dtype

    def test_value(self, dtype, maybe_jit):
        raw, dark, white = random_frames(dtype)
        v = np.asarray(maybe_jit(sj.flat_field)(raw, dark, white))
        tolerance = {np.float32: 1e-5, np.float64: 1e-12}[dtype]
        np.testing.assert_allclose(v, (raw - dark) / (white - dark), rtol=tolerance)

    def test_uint16_raw_is_float32_and_exact(self):
        raw, dark, white = random_frames(np.float64)
        raw16 = np.round(raw).astype(np.uint16)
        v = sj.flat_field(raw16, dark.astype(np.float32), white.astype(np.float32))
        assert v.dtype == np.float32
        np.testing.assert_allclose(np.asarray(v), (raw16 - dark) / (white - dark), rtol=1e-5)

    def test_uint16_below_dark_does_not_wrap(self):
        # A uint16 subtraction would wrap 90 - 100 to 65526.
        v = sj.flat_field(np.array([90], np.uint16), np.array([100], np.uint16), np.array([1100], np.uint16))
        assert float(v[0]) == pytest.approx(-0.01)

    def test_leading_dimensions(self):
        raw, dark, white = random_frames()
        stack = np.stack([raw, raw * 0.5 + dark * 0.5])
        v = np.asarray(sj.flat_field(stack, dark, white))
        np.testing.assert_allclose(v[0], np.asarray(sj.flat_field(raw, dark, white)))
        np.testing.assert_allclose(v[1], 0.5 * v[0], rtol=1e-12)

    def test_white_not_above_dark_is_nan_with_finite_gradient(self):
        raw = jnp.array([500.0, 500.0, 500.0])
        dark = jnp.array([100.0, 100.0, 100.0])
        white = jnp.array([1100.0, 100.0, 50.0])
        v = np.asarray(sj.flat_field(raw, dark, white))
        assert v[0] == pytest.approx(0.4) and np.isnan(v[1]) and np.isnan(v[2])
        grad = jax.grad(lambda w: jnp.nansum(sj.flat_field(raw, dark, w)))(white)
        assert np.all(np.isfinite(np.asarray(grad)))

    @pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
    def test_nan_inf_sweep(self, value):
        raw, dark, white = random_frames()
        raw[0, 0, 0] = value
        dark[1, 1, 1] = value
        white[2, 2, 2] = value
        v = np.asarray(sj.flat_field(raw, dark, white))
        assert not np.isfinite(v[0, 0, 0]) and np.isnan(v[1, 1, 1]) and np.isnan(v[2, 2, 2])
        assert np.isfinite(v[3:]).all()


class TestWhitePatchRatio:
    def test_value(self, dtype, maybe_jit):
        raw, dark, white = random_frames(dtype)
        mask = patch_mask()
        p = np.asarray(maybe_jit(sj.white_patch_ratio)(raw, dark, white, mask))
        expected = (white - dark)[mask].sum(0) / (raw - dark)[mask].sum(0)
        assert p.shape == (B,) and p.dtype == dtype
        np.testing.assert_allclose(p, expected, rtol={np.float32: 1e-5, np.float64: 1e-12}[dtype])

    def test_unusable_patch_pixels_are_left_out(self):
        raw, dark, white = random_frames()
        mask = patch_mask()
        clean = np.asarray(sj.white_patch_ratio(raw, dark, white, mask))
        raw_bad, white_bad = raw.copy(), white.copy()
        raw_bad[3, 4, :] = np.nan
        white_bad[4, 5, :] = dark[4, 5, :]
        reduced = mask.copy()
        reduced[3, 4] = reduced[4, 5] = False
        np.testing.assert_allclose(
            np.asarray(sj.white_patch_ratio(raw_bad, dark, white_bad, mask)),
            np.asarray(sj.white_patch_ratio(raw, dark, white, reduced)),
            rtol=1e-12,
        )
        assert not np.allclose(clean, np.asarray(sj.white_patch_ratio(raw, dark, white, reduced)))

    def test_whole_patch_unusable_gives_nan(self):
        raw, dark, white = random_frames()
        mask = patch_mask()
        raw[mask, 5] = np.nan
        p = np.asarray(sj.white_patch_ratio(raw, dark, white, mask))
        assert np.isnan(p[5]) and np.isfinite(np.delete(p, 5)).all()

    def test_leading_dimensions(self):
        raw, dark, white = random_frames()
        other = dark + 0.5 * (raw - dark)
        p = np.asarray(sj.white_patch_ratio(np.stack([raw, other]), dark, white, patch_mask()))
        assert p.shape == (2, B)
        np.testing.assert_allclose(p[1], 2.0 * p[0], rtol=1e-12)


class TestStage1:
    def test_broadcast_per_image(self):
        v = np.ones((2, 3, 4, B))
        p = np.arange(2 * B, dtype=float).reshape(2, 1, 1, B)
        np.testing.assert_allclose(np.asarray(sj.stage1(v, p))[:, 1, 2], p[:, 0, 0])

    def test_dtype(self, dtype):
        assert sj.stage1(np.ones((3, B), dtype), np.ones(B, dtype)).dtype == dtype


class TestBadInput:
    def test_band_count_mismatch(self):
        raw, dark, white = random_frames()
        with pytest.raises(ValueError, match=r"dark: expected shape \(\.\.\., 16\).*got \(24, 32, 15\)"):
            sj.flat_field(raw, dark[..., :15], white)

    def test_dark_white_mismatch(self):
        raw, dark, white = random_frames()
        with pytest.raises(ValueError, match=r"dark, white: .* got \(24, 32, 16\) and \(24, 31, 16\)"):
            sj.flat_field(raw, dark, white[:, :31])

    def test_frames_do_not_match_raw(self):
        raw, dark, white = random_frames()
        with pytest.raises(ValueError, match=r"dark: shape \(20, 32, 16\) does not broadcast to raw's shape \(24, 32, 16\)"):
            sj.flat_field(raw, dark[:20], white[:20])

    def test_empty_patch(self):
        raw, dark, white = random_frames()
        with pytest.raises(ValueError, match="patch: the mask selects no pixel"):
            sj.white_patch_ratio(raw, dark, white, np.zeros((H, W), bool))

    def test_patch_wrong_shape(self):
        raw, dark, white = random_frames()
        with pytest.raises(ValueError, match=r"patch: expected shape \(24, 32\).*got \(32, 24\)"):
            sj.white_patch_ratio(raw, dark, white, np.ones((W, H), bool))

    def test_patch_not_boolean(self):
        raw, dark, white = random_frames()
        with pytest.raises(ValueError, match="patch: expected a boolean mask, got dtype float64"):
            sj.white_patch_ratio(raw, dark, white, patch_mask().astype(float))

    def test_raw_without_image_axes(self):
        with pytest.raises(ValueError, match=r"raw: expected shape \(\.\.\., H, W, B\), got \(16,\)"):
            sj.white_patch_ratio(np.ones(B), np.zeros(B), np.ones(B), np.ones((1,), bool))

    def test_scalar_frames(self):
        with pytest.raises(ValueError, match=r"raw: expected shape \(\.\.\., B\) with B bands, got a scalar"):
            sj.flat_field(1.0, 0.0, 2.0)

    def test_stage1_scalar_v(self):
        with pytest.raises(ValueError, match=r"v: expected shape \(\.\.\., B\) with B bands, got a scalar"):
            sj.stage1(0.5, np.ones(B))

    def test_stage1_p_band_count(self):
        with pytest.raises(ValueError, match=r"p: expected shape \(\.\.\., 16\).*got \(15,\)"):
            sj.stage1(np.ones((3, B)), np.ones(15))
