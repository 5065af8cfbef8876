"""`correct()` and `Calibration`: the whole per-pixel path for an image."""

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax import spectra

from .helpers import ON_CPU, TABLE_2, gaussian_sensitivity, lambertian_sphere_frames

H, W, B = 20, 28, 16

#: Every XLA compilation in this process (JAX reports each through jax.monitoring).
COMPILATIONS = []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, seconds, **kwargs: COMPILATIONS.append(event)
    if event == "/jax/core/compile/backend_compile_duration"
    else None
)


@pytest.fixture(scope="module")
def scene():
    """A Lambertian sphere imaging a mosaic of measured spectra, with dark current, vignetting,
    a lamp change and an affine Wiener estimator (matrix and offset) trained on other spectra.
    Frames are float64 counts."""
    rng = np.random.default_rng(11)
    sets = spectra.reflectance_sets()
    M = gaussian_sensitivity()
    train = np.concatenate([v for k, v in sets.items() if k.startswith(("ColorChecker", "TCS"))])
    estimator = sj.fit_wiener(train @ M.T, train, noise_variance=1e-7)
    wiener_matrix, wiener_offset = np.asarray(estimator.matrix), np.asarray(estimator.offset)
    mosaic = sets["CES (TM-30)"][rng.integers(0, 99, (H // 4, W // 4))]
    truth = np.repeat(np.repeat(mosaic, 4, axis=0), 4, axis=1)  # (H, W, 31)
    patch = np.zeros((H, W), bool)
    patch[1:5, 1:5] = True
    yy, xx = np.mgrid[0:H, 0:W]
    beta = 1.0 - 0.5 * (((yy - H / 2) / H) ** 2 + ((xx - W / 2) / W) ** 2)
    dark = rng.uniform(95, 105, (H, W, B))
    white, raw = lambertian_sphere_frames(
        truth @ M.T, 1.0, np.ones(B), patch, beta, np.full(B, 1.02),
        rho_wall=np.full(B, 0.97), alpha_ww=0.955, alpha_wsp=0.03, alpha_spw=0.97,
        gamma_phi0=np.full(B, 400.0), dark=dark,
    )
    calibration = sj.Calibration(
        dark=dark, white=white, patch=patch, coeffs=np.asarray(sj.identity_coeffs(B, np.float64)),
        wiener=wiener_matrix, illuminant="D65", saturation=16383.0, wiener_offset=wiener_offset,
    )
    return dict(raw=raw, truth=truth, calibration=calibration, patch=patch)


def with_dtype(calibration, dtype):
    return sj.Calibration(
        dark=np.asarray(calibration.dark, dtype), white=np.asarray(calibration.white, dtype),
        patch=calibration.patch, coeffs=np.asarray(calibration.coeffs, dtype),
        wiener=np.asarray(calibration.wiener, dtype), illuminant=calibration.illuminant,
        saturation=calibration.saturation, wiener_offset=np.asarray(calibration.wiener_offset, dtype),
    )


def kernel_composition(raw, calibration):
    """The path written out with the public kernels, for comparison with the fused `correct`."""
    v = sj.flat_field(raw, calibration.dark, calibration.white)
    p = sj.white_patch_ratio(raw, calibration.dark, calibration.white, calibration.patch)
    v_tilde = sj.stage2(v, p, calibration.coeffs)
    reflectance = sj.wiener(v_tilde, calibration.wiener) + calibration.wiener_offset  # r = W v + r0
    return v, p, v_tilde, reflectance, sj.reflectance_to_lab(reflectance, calibration.illuminant)


class TestCorrect:
    def test_equals_the_kernels_composed(self, scene, dtype):
        calibration = with_dtype(scene["calibration"], dtype)
        raw = scene["raw"].astype(dtype)
        result = sj.correct(raw, calibration, intermediates=True)
        v, p, v_tilde, reflectance, lab = kernel_composition(raw, calibration)
        tolerance = {np.float32: 2e-4, np.float64: 1e-10}[dtype]
        assert result.reflectance.dtype == dtype and result.lab.dtype == dtype
        assert result.reflectance.shape == (H, W, 31) and result.lab.shape == (H, W, 3)
        np.testing.assert_allclose(np.asarray(result.p), np.asarray(p), rtol=tolerance)
        np.testing.assert_allclose(np.asarray(result.v), np.asarray(v), rtol=tolerance, atol=tolerance)
        np.testing.assert_allclose(np.asarray(result.v_stage1), np.asarray(sj.stage1(v, p)), rtol=tolerance, atol=tolerance)
        np.testing.assert_allclose(np.asarray(result.v_stage2), np.asarray(v_tilde), rtol=tolerance, atol=tolerance)
        np.testing.assert_allclose(np.asarray(result.reflectance), np.asarray(reflectance), atol=tolerance)
        # Lab goes through the folded (B, 3) matrix; it must equal Lab of the reflectance.
        np.testing.assert_allclose(np.asarray(result.lab), np.asarray(lab), atol=100 * tolerance)
        assert np.all(np.asarray(result.quality) == 0) and bool(jnp.all(result.valid))

    def test_recovers_the_scene(self, scene):
        """Lambertian sphere + Stage I: reflectance within Wiener accuracy of the truth, whatever
        the lamp change and the sample's effect on the sphere."""
        result = sj.correct(scene["raw"], scene["calibration"])
        outside = ~scene["patch"]
        error = np.asarray(result.reflectance)[outside] - scene["truth"][outside]
        assert np.sqrt(np.mean(error**2)) < 0.01
        de = np.asarray(result.delta_e_map(sj.reflectance_to_lab(scene["truth"])))[outside]
        assert np.mean(de) < 0.5

    def test_uint16_equals_float_counts(self, scene):
        raw16 = np.round(scene["raw"]).astype(np.uint16)
        calibration = with_dtype(scene["calibration"], np.float32)
        from_uint16 = sj.correct(raw16, calibration)
        from_float = sj.correct(raw16.astype(np.float32), calibration)
        assert from_uint16.reflectance.dtype == np.float32
        np.testing.assert_array_equal(np.asarray(from_uint16.reflectance), np.asarray(from_float.reflectance))
        # Bit for bit on the CPU (one kernel, the same arithmetic after the exact conversion). On
        # an H100 (jax 0.11.2) the GPU kernel's two compilations (uint16 and float32 raw) round
        # Lab's sums differently: 187 of 1680 values, at most 6.1e-5 apart, reflectance equal.
        lab_atol = 0.0 if ON_CPU else 2e-4
        np.testing.assert_allclose(np.asarray(from_uint16.lab), np.asarray(from_float.lab), rtol=0, atol=lab_atol)

    def test_table_2_coefficients_apply(self, scene):
        calibration = scene["calibration"]
        with_table = sj.Calibration(
            dark=calibration.dark, white=calibration.white, patch=calibration.patch,
            coeffs=TABLE_2, wiener=calibration.wiener,
        )
        result = sj.correct(scene["raw"], with_table, intermediates=True)
        np.testing.assert_allclose(
            np.asarray(result.v_stage2), np.asarray(sj.stage2(result.v, result.p, TABLE_2)), rtol=1e-12
        )

    def test_leading_dimensions(self, scene):
        raw = scene["raw"]
        darker = scene["calibration"].dark + 0.5 * (raw - scene["calibration"].dark)
        batch = sj.correct(np.stack([raw, darker]), scene["calibration"])
        assert batch.reflectance.shape == (2, H, W, 31) and batch.p.shape == (2, B)
        single = sj.correct(darker, scene["calibration"])
        np.testing.assert_allclose(np.asarray(batch.reflectance[1]), np.asarray(single.reflectance), atol=1e-12)

    def test_no_recompilation_for_a_second_image(self, scene):
        calibration = scene["calibration"]
        sj.correct(scene["raw"], calibration)
        before = len(COMPILATIONS)
        second = sj.correct(scene["raw"] * 0.9 + 10.0, calibration)
        jax.block_until_ready(second)
        assert len(COMPILATIONS) == before
        sj.correct(np.stack([scene["raw"]] * 3), calibration)  # a new shape: a new program
        assert len(COMPILATIONS) > before  # the counter does see compilations

    def test_calibration_traced_under_jit(self, scene):
        """With the calibration itself a jit argument the patch is a tracer: the ratio is then
        taken over the whole image instead of the patch's bounding box, with the same result."""
        traced = jax.jit(lambda raw, calibration: sj.correct(raw, calibration))(scene["raw"], scene["calibration"])
        direct = sj.correct(scene["raw"], scene["calibration"])
        np.testing.assert_allclose(np.asarray(traced.p), np.asarray(direct.p), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(traced.lab), np.asarray(direct.lab), atol=1e-10)

    def test_intermediates_off_by_default(self, scene):
        result = sj.correct(scene["raw"], scene["calibration"])
        assert result.v is None and result.v_stage1 is None and result.v_stage2 is None


class TestQualityMask:
    def test_bad_pixels_become_nan_and_are_flagged(self, scene):
        calibration = scene["calibration"]
        raw = scene["raw"].copy()
        white = np.asarray(calibration.white).copy()
        raw[10, 10, 3] = 16383.0  # saturated in one band
        raw[11, 12, 0] = np.nan
        raw[12, 14, 15] = np.inf
        white[13, 16, 7] = np.asarray(calibration.dark)[13, 16, 7] - 1.0  # white below dark
        bad_white = sj.Calibration(
            dark=calibration.dark, white=white, patch=calibration.patch, coeffs=calibration.coeffs,
            wiener=calibration.wiener, saturation=16383.0,
        )
        result = sj.correct(raw, bad_white)
        quality = np.asarray(result.quality)
        assert quality[10, 10] == sj.QUALITY_SATURATED
        assert quality[11, 12] == sj.QUALITY_NONFINITE
        assert quality[12, 14] == sj.QUALITY_NONFINITE
        assert quality[13, 16] == sj.QUALITY_WHITE_NOT_ABOVE_DARK
        bad = quality != 0
        assert bad.sum() == 4
        assert np.isnan(np.asarray(result.reflectance)[bad]).all() and np.isnan(np.asarray(result.lab)[bad]).all()
        assert np.isfinite(np.asarray(result.reflectance)[~bad]).all()
        np.testing.assert_array_equal(np.asarray(result.valid), ~bad)

    def test_default_saturation_is_the_integer_full_scale(self, scene):
        calibration = sj.Calibration(
            dark=scene["calibration"].dark, white=scene["calibration"].white, patch=scene["patch"],
            coeffs=scene["calibration"].coeffs, wiener=scene["calibration"].wiener,
        )
        raw16 = np.round(scene["raw"]).astype(np.uint16)
        raw16[5, 20, 2] = 65535
        quality = np.asarray(sj.correct(raw16, calibration).quality)
        assert quality[5, 20] == sj.QUALITY_SATURATED and (quality != 0).sum() == 1
        # Float counts have no implicit full scale.
        assert np.all(np.asarray(sj.correct(raw16.astype(np.float32), calibration).quality) == 0)

    def test_bad_pixel_in_the_patch_does_not_shift_p(self, scene):
        raw = scene["raw"].copy()
        clean = sj.correct(raw, scene["calibration"])
        raw[2, 2, :] = 16383.0  # inside the patch
        dirty = sj.correct(raw, scene["calibration"])
        reduced = scene["patch"].copy()
        reduced[2, 2] = False
        expected = sj.white_patch_ratio(scene["raw"], scene["calibration"].dark, scene["calibration"].white, reduced)
        np.testing.assert_allclose(np.asarray(dirty.p), np.asarray(expected), rtol=1e-12)
        # On a Lambertian sphere every patch pixel gives the same ratio 1/q_s, so dropping one
        # leaves p unchanged; averaging the saturated pixel in would not.
        np.testing.assert_allclose(np.asarray(dirty.p), np.asarray(clean.p), rtol=1e-12)
        polluted = sj.white_patch_ratio(raw, scene["calibration"].dark, scene["calibration"].white, scene["patch"])
        assert np.max(np.abs(np.asarray(polluted) / np.asarray(clean.p) - 1.0)) > 0.01

    def test_unusable_patch_flags_the_whole_image_without_raising(self, scene):
        raw = scene["raw"].copy()
        raw[scene["patch"], 4] = np.nan
        result = sj.correct(raw, scene["calibration"])
        assert np.all(np.asarray(result.quality) & sj.QUALITY_PATCH_UNUSABLE)
        assert np.isnan(np.asarray(result.reflectance)).all()

    @pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf, 0.0, 1e38])
    def test_value_sweep_never_raises(self, scene, value):
        raw = np.full((H, W, B), value, dtype=np.float32)
        result = sj.correct(raw, with_dtype(scene["calibration"], np.float32))
        assert result.reflectance.shape == (H, W, 31)


class TestGradients:
    def test_finite_gradients_of_a_delta_e_loss(self, scene):
        """d(mean ΔE00 to the truth)/d(coeffs, W), with a few bad pixels in the image."""
        raw = scene["raw"].copy()
        raw[3, 20, 5] = np.nan
        raw[15, 7, 0] = 16383.0
        reference = sj.reflectance_to_lab(scene["truth"])
        calibration = scene["calibration"]

        def loss(coeffs, wiener_matrix):
            cal = sj.Calibration(
                dark=calibration.dark, white=calibration.white, patch=calibration.patch,
                coeffs=coeffs, wiener=wiener_matrix, saturation=16383.0,
                wiener_offset=calibration.wiener_offset,
            )
            result = sj.correct(raw, cal)
            de = sj.delta_e_2000(result.lab, reference)
            return jnp.sum(jnp.where(result.valid, de, 0.0)) / jnp.sum(result.valid).astype(de.dtype)

        coeffs, wiener_matrix = jnp.asarray(calibration.coeffs), jnp.asarray(calibration.wiener)
        g_coeffs, g_wiener = jax.grad(loss, argnums=(0, 1))(coeffs, wiener_matrix)
        assert g_coeffs.shape == (B, 4) and g_wiener.shape == (31, B)
        assert np.isfinite(np.asarray(g_coeffs)).all() and np.isfinite(np.asarray(g_wiener)).all()
        assert np.abs(np.asarray(g_coeffs)).max() > 0
        # Central differences on one coefficient (float64).
        eps = 1e-6
        step = jnp.zeros_like(coeffs).at[5, 1].set(eps)
        fd = (loss(coeffs + step, wiener_matrix) - loss(coeffs - step, wiener_matrix)) / (2 * eps)
        assert float(g_coeffs[5, 1]) == pytest.approx(float(fd), rel=1e-5)


def with_offset(calibration, offset):
    """`calibration` with the Wiener offset r0 replaced (every other field as it was)."""
    return dataclasses.replace(calibration, wiener_offset=np.asarray(offset, np.asarray(calibration.wiener).dtype))


#: A reflectance offset of the size an affine fit gives (a few hundredths), with both signs.
OFFSET = 0.03 * np.sin(np.linspace(0.0, 3.0 * np.pi, 31)) + 0.01


class TestWienerOffset:
    """The affine estimator r = W v_tilde + r0 through `correct`, on both CPU paths (the fused
    kernel in float32 by default, the jax.numpy path with SPHEREJAX_FUSED=0) and float64."""

    @pytest.fixture
    def dirty(self, scene):
        """The scene's raw frames with bad pixels of every per-pixel kind."""
        raw = scene["raw"].copy()
        raw[10, 10, 3] = 16383.0
        raw[11, 12, 0] = np.nan
        raw[12, 14, 15] = -np.inf
        return raw

    @pytest.mark.parametrize("path", ["default", "jax.numpy"])
    def test_offset_adds_to_the_reflectance_of_good_pixels(self, scene, dirty, dtype, path, monkeypatch):
        if path == "jax.numpy":
            monkeypatch.setenv("SPHEREJAX_FUSED", "0")
        base = with_offset(with_dtype(scene["calibration"], dtype), np.zeros(31))
        shifted = with_offset(base, OFFSET)
        raw = dirty.astype(dtype)
        without, with_r0 = sj.correct(raw, base), sj.correct(raw, shifted)
        quality = np.asarray(with_r0.quality)
        np.testing.assert_array_equal(quality, np.asarray(without.quality))
        good = quality == 0
        assert (~good).sum() == 3
        refl0, refl = np.asarray(without.reflectance), np.asarray(with_r0.reflectance)
        tolerance = {np.float32: 2e-6, np.float64: 1e-13}[dtype]
        np.testing.assert_allclose(refl[good], refl0[good] + OFFSET.astype(dtype), rtol=0, atol=tolerance)
        # Colour oracle: Lab of the shifted spectra through the public colorimetry (ASTM E308
        # weights, colour-science's convention), not through the folded (B, 3) matrix.
        lab_oracle = np.asarray(sj.reflectance_to_lab(jnp.asarray(refl0[good] + OFFSET.astype(dtype)), base.illuminant))
        np.testing.assert_allclose(np.asarray(with_r0.lab)[good], lab_oracle, rtol=0, atol={np.float32: 2e-2, np.float64: 1e-8}[dtype])
        assert np.abs(np.asarray(with_r0.lab)[good] - np.asarray(without.lab)[good]).max() > 0.5  # r0 shows in Lab
        # Bad pixels stay NaN in every channel, whatever the offset.
        for name in ("reflectance", "lab"):
            out = np.asarray(getattr(with_r0, name))
            assert np.isnan(out[~good]).all() and np.isfinite(out[good]).all(), name

    def test_zero_offset_is_the_default(self, scene, dirty):
        """A calibration built without an offset has r0 = 0 and gives the same bits."""
        calibration = scene["calibration"]
        plain = sj.Calibration(
            dark=calibration.dark, white=calibration.white, patch=calibration.patch,
            coeffs=calibration.coeffs, wiener=calibration.wiener, saturation=16383.0,
        )
        np.testing.assert_array_equal(np.asarray(plain.wiener_offset), np.zeros(31))
        zero = with_offset(calibration, np.zeros(31))
        for a, b in zip(jax.tree.leaves(sj.correct(dirty, plain)), jax.tree.leaves(sj.correct(dirty, zero))):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

    def test_rows_carry_the_offset(self, scene):
        rows = with_offset(scene["calibration"], OFFSET).rows(3, 9)
        np.testing.assert_array_equal(np.asarray(rows.wiener_offset), OFFSET)
        assert rows.patch is None and rows.dark.shape == (6, W, B)

    @pytest.mark.parametrize("path", ["default", "jax.numpy"])
    def test_gradient_with_respect_to_the_offset(self, scene, dirty, dtype, path, monkeypatch):
        """d(mean ΔE00 to the truth)/d r0 with bad pixels in the image: finite, and equal to
        central differences."""
        if path == "jax.numpy":
            monkeypatch.setenv("SPHEREJAX_FUSED", "0")
        calibration = with_dtype(scene["calibration"], dtype)
        reference = sj.reflectance_to_lab(scene["truth"].astype(dtype))
        raw = dirty.astype(dtype)

        def loss(offset):
            result = sj.correct(raw, dataclasses.replace(calibration, wiener_offset=offset))
            de = sj.delta_e_2000(result.lab, reference)
            return jnp.sum(jnp.where(result.valid, de, 0.0)) / jnp.sum(result.valid).astype(de.dtype)

        offset = jnp.asarray(OFFSET, dtype)
        grad = np.asarray(jax.grad(loss)(offset))
        assert grad.shape == (31,) and grad.dtype == dtype
        assert np.isfinite(grad).all() and np.abs(grad).max() > 0
        eps, rel = {np.float32: (1e-3, 2e-2), np.float64: (1e-6, 1e-5)}[dtype]
        for k in (0, 12, 30):
            step = jnp.zeros_like(offset).at[k].set(eps)
            fd = (float(loss(offset + step)) - float(loss(offset - step))) / (2 * eps)
            assert float(grad[k]) == pytest.approx(fd, rel=rel, abs=rel * float(np.abs(grad).max())), k


class TestDeltaEMap:
    def test_against_one_colour_and_an_image(self, scene):
        result = sj.correct(scene["raw"], scene["calibration"])
        colour_ref = np.array([50.0, 10.0, -20.0])
        one = np.asarray(result.delta_e_map(colour_ref))
        assert one.shape == (H, W)
        np.testing.assert_allclose(one[3, 4], float(sj.delta_e_2000(result.lab[3, 4], colour_ref)))
        image = np.asarray(sj.delta_e_map(result.lab, result.lab))
        np.testing.assert_array_equal(image, 0.0)

    def test_wrong_reference_shape(self, scene):
        result = sj.correct(scene["raw"], scene["calibration"])
        with pytest.raises(ValueError, match=r"reference: expected shape \(20, 28, 3\).*got \(5, 3\)"):
            result.delta_e_map(np.zeros((5, 3)))


class TestBadInput:
    def make(self, scene, **changes):
        calibration = scene["calibration"]
        fields = dict(
            dark=calibration.dark, white=calibration.white, patch=calibration.patch,
            coeffs=calibration.coeffs, wiener=calibration.wiener,
        )
        fields.update(changes)
        return sj.Calibration(**fields)

    def test_raw_band_count(self, scene):
        with pytest.raises(ValueError, match=r"raw: expected frames of shape \(20, 28, 16\).*got \(20, 28, 15\)"):
            sj.correct(scene["raw"][..., :15], scene["calibration"])

    def test_raw_image_size(self, scene):
        with pytest.raises(ValueError, match=r"raw: expected frames of shape \(20, 28, 16\).*got \(28, 20, 16\)"):
            sj.correct(np.swapaxes(scene["raw"], 0, 1), scene["calibration"])

    def test_raw_rank(self, scene):
        with pytest.raises(ValueError, match=r"raw: expected shape \(H, W, B\)"):
            sj.correct(scene["raw"][0], scene["calibration"])

    def test_raw_dtype(self, scene):
        with pytest.raises(ValueError, match="raw: expected integer counts or floats, got dtype bool"):
            sj.correct(scene["raw"] > 0, scene["calibration"])

    def test_not_a_calibration(self, scene):
        with pytest.raises(ValueError, match="calibration: expected a spherejax.Calibration, got dict"):
            sj.correct(scene["raw"], {"dark": 0})

    def test_dark_rank(self, scene):
        with pytest.raises(ValueError, match=r"dark: expected shape \(H, W, B\), got \(20, 28\)"):
            self.make(scene, dark=np.zeros((H, W)))

    def test_white_shape(self, scene):
        with pytest.raises(ValueError, match=r"white: expected shape \(20, 28, 16\).*got \(20, 28, 15\)"):
            self.make(scene, white=np.ones((H, W, 15)))

    def test_patch_shape(self, scene):
        with pytest.raises(ValueError, match=r"patch: expected shape \(20, 28\).*got \(20, 27\)"):
            self.make(scene, patch=np.ones((H, W - 1), bool))

    def test_patch_not_boolean(self, scene):
        with pytest.raises(ValueError, match="patch: expected a boolean mask, got dtype int64"):
            self.make(scene, patch=scene["patch"].astype(np.int64))

    def test_patch_empty(self, scene):
        with pytest.raises(ValueError, match="patch: the mask selects no pixel"):
            self.make(scene, patch=np.zeros((H, W), bool))

    def test_coeffs_shape(self, scene):
        with pytest.raises(ValueError, match=r"coeffs: expected shape \(16, 4\).*got \(16, 3\)"):
            self.make(scene, coeffs=np.ones((B, 3)))

    def test_wiener_shape(self, scene):
        with pytest.raises(ValueError, match=r"wiener: expected shape \(31, 16\).*got \(16, 31\)"):
            self.make(scene, wiener=np.ones((B, 31)))

    @pytest.mark.parametrize("shape", [(30,), (31, 1), (16,), ()])
    def test_wiener_offset_shape(self, scene, shape):
        expected = r"wiener_offset: expected shape \(31,\) \(one reflectance offset r0 per wavelength.*got " + re.escape(str(shape))
        with pytest.raises(ValueError, match=expected):
            self.make(scene, wiener_offset=np.zeros(shape))

    def test_unknown_illuminant(self, scene):
        with pytest.raises(ValueError, match="illuminant: unknown illuminant 'D50'"):
            self.make(scene, illuminant="D50")

    def test_unknown_observer(self, scene):
        with pytest.raises(ValueError, match="observer: unknown observer 'CIE 2015'"):
            self.make(scene, observer="CIE 2015")

    def test_bad_saturation(self, scene):
        with pytest.raises(ValueError, match="saturation: expected a level > 0 or None, got -5"):
            self.make(scene, saturation=-5)


def test_patch_bounding_box_follows_the_mask():
    """`patch_bounding_box` reads the mask it is given each time: a NumPy mask changed in place
    gets its new box; an empty mask has none."""
    from spherejax import pipeline

    mask = np.zeros((6, 8), bool)
    mask[1:3, 2:5] = True
    assert pipeline.patch_bounding_box(jnp.asarray(mask)) == (1, 3, 2, 5)
    mask[4, 7] = True
    assert pipeline.patch_bounding_box(mask) == (1, 5, 2, 8)
    assert pipeline.patch_bounding_box(jnp.asarray(mask)) == (1, 5, 2, 8)
    assert pipeline.patch_bounding_box(np.zeros((6, 8), bool)) is None


def test_a_calibration_works_its_patch_box_out_once(scene):
    """`Calibration.patch_box` is worked out once per calibration (the patch is an immutable
    jax.Array), and a calibration made from it by `dataclasses.replace` works out its own."""
    calibration = scene["calibration"]
    first = calibration.patch_box
    assert calibration.patch_box is first and first == pipeline_box(calibration)
    moved = np.zeros(calibration.image_shape, bool)
    moved[:2, :3] = True
    other = dataclasses.replace(calibration, patch=moved)
    assert other.patch_box == (0, 2, 0, 3) and calibration.patch_box == first


def pipeline_box(calibration):
    from spherejax import pipeline

    return pipeline.patch_bounding_box(np.asarray(calibration.patch))


BENCHMARK_SIZE = 96  # three 32-pixel tiles a side; the 35 x 35 patch sits 8 px in


@pytest.fixture(scope="module")
def benchmark_frames():
    """benchmarks/reference.py's frames and calibration, and its outputs for them."""
    from benchmarks import reference

    inputs = reference.make_inputs(BENCHMARK_SIZE, seed=7)
    # Saturated pixels, one inside the patch (the frames have about one at this size by chance).
    for row, col, band in ((50, 60, 4), (81, 20, 15), (20, 20, 0)):
        inputs["raw"][row, col, band] = reference.SATURATION
    wiener, offset = reference.wiener_estimator()
    xyz_weights, whitepoint_xy = reference.reference_constants()
    coeffs = reference.stage2_coeffs()
    expected = reference.reference_correct(
        inputs["raw"], inputs["dark"], inputs["white"], inputs["patch"], coeffs, wiener,
        xyz_weights, whitepoint_xy, wiener_offset=offset,
    )
    calibration = reference.make_calibration(inputs, coeffs, wiener, wiener_offset=offset)
    return reference, inputs["raw"], calibration, expected


class TestAgainstTheBenchmarkReference:
    """`correct` against the numpy + colour-science reference every speed figure is a ratio to
    (benchmarks/reference.py), on the same synthetic frames the benchmarks time: measured
    spectra in tiles under vignetting, a sample darkening the sphere (p near 1 / 0.97), a few
    saturated pixels, the paper's Table 2 and an affine Wiener estimator. One oracle for the
    benchmarks' agreement check and for the tests."""

    @pytest.mark.parametrize("path", ["default", "jax.numpy"])
    def test_agrees_with_the_reference(self, benchmark_frames, path, monkeypatch):
        if path == "jax.numpy":
            monkeypatch.setenv("SPHEREJAX_FUSED", "0")
        reference, raw, calibration, expected = benchmark_frames
        assert 3 <= (~expected["valid"]).sum() <= 5  # the saturated pixels, and only they
        agreement = reference.compare(sj.correct(raw, calibration), expected)
        assert agreement["valid_pixels"] == BENCHMARK_SIZE**2 - (~expected["valid"]).sum()

    def test_the_agreement_check_can_fail(self, benchmark_frames):
        """A Table 2 coefficient off by 1 % must be caught by the tolerance the benchmarks use."""
        reference, raw, calibration, expected = benchmark_frames
        coeffs = np.asarray(calibration.coeffs).copy()
        coeffs[5, 0] *= 1.01
        wrong = dataclasses.replace(calibration, coeffs=coeffs)
        with pytest.raises(AssertionError, match="disagree"):
            reference.compare(sj.correct(raw, wrong), expected)
