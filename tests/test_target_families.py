"""Synthetic target families closer to real ones (spherejax/target_families.py): shade cards,
brighteners, gloss and texture, each tested against its physics and colour-science."""

import colour
import numpy as np
import pytest
from scipy.integrate import solve_bvp

from spherejax import kubelka_munk as km
from spherejax import target_families as tf
from spherejax.estimation import fit_wiener, wiener
from spherejax.grid import WAVELENGTHS_NM
from spherejax.simulate import FINE_WAVELENGTHS_NM
from spherejax.simulated_targets import render_targets, target_system

#: (171, 31) linear interpolation from the 31 samples to the simulator's fine grid, constant
#: outside 400-700 nm: the projection `target_system`'s M is made with.
INTERPOLATE_31_TO_FINE = np.stack(
    [np.interp(FINE_WAVELENGTHS_NM, WAVELENGTHS_NM, column) for column in np.eye(WAVELENGTHS_NM.size)], axis=1)

KINDS = list(tf.FAMILY_KINDS)
SHAPE = colour.SpectralShape(400, 700, 10)
OBSERVER = "CIE 1931 2 Degree Standard Observer"


def lab_d65(reflectances):
    """CIELAB under D65 (colour-science, 2° observer, integration) of reflectances (n, 31)."""
    cmfs = colour.MSDS_CMFS[OBSERVER].copy().align(SHAPE)
    illuminant = colour.SDS_ILLUMINANTS["D65"].copy().align(SHAPE)
    xyz = colour.msds_to_XYZ(np.asarray(reflectances), cmfs, illuminant, method="Integration", shape=SHAPE) / 100.0
    return colour.XYZ_to_Lab(xyz, colour.CCS_ILLUMINANTS[OBSERVER]["D65"])


def hue_chroma(lab):
    return np.degrees(np.arctan2(lab[..., 2], lab[..., 1])) % 360.0, np.hypot(lab[..., 1], lab[..., 2])


def largest_hue_gap(hues):
    """The widest arc (degrees) of the hue circle with no hue in it."""
    ordered = np.sort(hues)
    return float(np.max(np.diff(np.r_[ordered, ordered[0] + 360.0])))


def held_out_rms(kind, method="training"):
    """Spectral rms on seed 1 (n = 200) of fit_wiener trained on seed 0 (n = 200)."""
    estimator = fit_wiener(*tf.target_family(kind, 200, 0), method=method)
    V, R = tf.target_family(kind, 200, 1)
    return float(np.sqrt(np.mean((np.asarray(wiener(V, estimator)) - R) ** 2)))


class TestShapesAndSeeds:
    @pytest.mark.parametrize("kind", KINDS)
    def test_shapes_dtypes_and_seeds(self, kind):
        V, R = tf.target_family(kind, 20, 3)
        assert V.shape == (20, 16) and R.shape == (20, 31) and V.dtype == R.dtype == np.float64
        V_again, R_again = tf.target_family(kind, 20, 3)
        np.testing.assert_array_equal(V, V_again)
        np.testing.assert_array_equal(R, R_again)
        V_other, R_other = tf.target_family(kind, 20, 4)
        assert not np.allclose(R, R_other) and not np.allclose(V, V_other)

    def test_all_kinds_at_once(self):
        families = tf.family_kinds_responses(seed=2, n=12, noise=False)
        assert list(families) == KINDS
        for kind, (V, R) in families.items():
            np.testing.assert_array_equal(V, tf.target_family(kind, 12, 2, noise=False)[0])
            np.testing.assert_array_equal(R, tf.target_family(kind, 12, 2, noise=False)[1])

    @pytest.mark.parametrize("family", list(km.MATERIAL_FAMILIES))
    def test_km_mixing_is_the_kubelka_munk_family_unchanged(self, family):
        V, R = tf.target_family("km_mixing", 30, 5, family=family, patch_pixels=1225)
        expected = km.km_family_responses(5, 30, True, 1225)[family]
        np.testing.assert_array_equal(V, expected[0])
        np.testing.assert_array_equal(R, expected[1])
        assert tf.KM_DEFAULT_FAMILY in km.MATERIAL_FAMILIES

    @pytest.mark.parametrize("call, message", [
        ({"kind": "paint"}, "kind: expected one of"),
        ({"kind": None}, "kind: expected one of"),
        ({"kind": "shade_card", "n": 0}, "n: expected an integer >= 1"),
        ({"kind": "shade_card", "n": 2.5}, "n: expected an integer >= 1"),
        ({"kind": "shade_card", "n": True}, "n: expected an integer >= 1"),
        ({"kind": "mixed_real", "patch_pixels": 0}, "patch_pixels: expected an integer >= 1"),
        ({"kind": "km_mixing", "patch_pixels": "35"}, "patch_pixels: expected an integer >= 1"),
        ({"kind": "km_mixing", "family": "silk"}, "family: expected one of"),
    ])
    def test_bad_arguments_are_refused_in_one_line(self, call, message):
        with pytest.raises(ValueError, match=message) as raised:
            tf.target_family(**{"n": 5, **call})
        assert "\n" not in str(raised.value)


class TestShadeCard:
    def test_the_ring_runs_around_the_hue_circle(self):
        """At 1 % owf each ring dye's CIELAB hue (D65) lies clockwise of the one before, and the
        twelve go once around the circle."""
        recipes = np.eye(len(tf.SHADE_CARD_DYES))[: len(tf.SHADE_CARD_RING)]
        hues, chroma = hue_chroma(lab_d65(km.on_reflectance_grid(
            km.saunderson(km.reflectance_from_ks(tf._layer_ks(recipes, np.zeros(12), FINE_WAVELENGTHS_NM)[0]),
                          tf.SHADE_CARD_K1, tf.SHADE_CARD_K2))))
        steps = (hues - np.roll(hues, -1)) % 360.0  # from each dye to the next, going down in hue
        assert np.all(steps > 5.0) and np.isclose(steps.sum(), 360.0), hues
        assert chroma.min() > 40.0  # measured 44.7 (navy) to 97.3 (rubine)

    def test_recipes_are_laid_out_as_a_shade_card(self):
        recipes = tf.shade_card_recipes(200, np.random.default_rng(0))
        used = np.count_nonzero(recipes, axis=1)
        assert recipes.shape == (200, 13) and used.max() == 3 and np.all(recipes >= 0.0)
        assert np.sum(used == 0) == 6  # 3 % whites
        greys = recipes[:, -1] > 0.0
        assert np.sum(greys & (recipes[:, :-1].sum(axis=1) <= 0.2 * recipes[:, -1] + 1e-12)) >= 30  # 15 % greys
        depth = recipes.sum(axis=1)[used > 0]
        assert depth.min() < 0.02 and depth.max() > 3.0

    def test_hues_chroma_and_depths_cover_the_card(self):
        """CIELAB under D65 (colour-science): chromatic targets all round the hue circle (no gap
        of 60°), lightness from pale (L* > 80) to deep (L* < 35), and near-neutrals."""
        _, R = tf.target_family("shade_card", 200, 0, noise=False)
        hues, chroma = hue_chroma(lab := lab_d65(R))
        assert largest_hue_gap(hues[chroma > 15.0]) < 60.0  # measured 21°: spread over more than 300°
        assert lab[:, 0].max() > 80.0 and lab[:, 0].min() < 35.0  # measured 94.9 and 15.7
        assert np.sum(chroma < 10.0) >= 20  # greys and whites: measured 41


class TestFluorescence:
    @pytest.mark.parametrize("ks, decay", [(0.01, 0.3), (0.5, 0.3), (0.5, 2.0), (5.0, 1.0)])
    def test_escape_fraction_solves_the_two_flux_equations(self, ks, decay):
        """η (F4) against a numerical solution of the Kubelka-Munk equations with a source
        exp(-σ_μ z) shared equally up and down, no flux entering at the top (S = 1)."""
        depth = 60.0 / min(decay, np.sqrt(ks * (ks + 2.0)))

        def flux(z, y):
            source = 0.5 * np.exp(-decay * z)
            i, j = y
            return np.vstack([-(ks + 1.0) * i + j + source, (ks + 1.0) * j - i - source])

        z = np.linspace(0.0, depth, 2000)
        solution = solve_bvp(flux, lambda top, bottom: np.array([top[0], bottom[1]]), z, np.zeros((2, z.size)),
                             tol=1e-8, max_nodes=200000)
        assert solution.success
        emitted = 1.0 / decay  # the source integrated over depth
        np.testing.assert_allclose(solution.sol(0.0)[1] / emitted, tf.escape_fraction(ks, decay), rtol=1e-5)

    def test_photons_out_are_the_yield_times_photons_absorbed(self):
        """Where nothing absorbs at the emission wavelengths (η = 1 and the surface passes all),
        the fluorescent photons leaving equal Φ times those the brightener absorbs, which by
        Saunderson's correction are (1 - k1) (1 - R_∞) / (1 - k2 R_∞) of the incident ones."""
        ks = 2.0 * tf.BRIGHTENER.unit_ks(tf.EXCITATION_WAVELENGTHS_NM)[None] / tf.BRIGHTENER.unit_ks(np.array([350.0]))
        irradiance_excitation = tf.d65_photon_irradiance(tf.EXCITATION_WAVELENGTHS_NM)
        irradiance_emission = tf.d65_photon_irradiance(FINE_WAVELENGTHS_NM)
        k1, k2, yield_ = 0.04, 0.6, 0.6
        beta = tf.luminescent_radiance_factor(
            ks, ks, np.zeros((1, FINE_WAVELENGTHS_NM.size)), irradiance_excitation, irradiance_emission,
            tf.BRIGHTENER.emission(FINE_WAVELENGTHS_NM), quantum_yield=yield_, k1=k1, k2=k2)
        reflectance = km.reflectance_from_ks(ks[0])
        absorbed = np.sum((1.0 - k1) * (1.0 - reflectance) / (1.0 - k2 * reflectance) * irradiance_excitation) * 2.0
        np.testing.assert_allclose(np.sum(beta[0] * irradiance_emission) * 2.0, yield_ * absorbed, rtol=1e-12)

    def test_emission_fades_with_depth(self):
        """Each ring dye and the black, deeper and deeper on the brightened white: the
        fluorescence (D65) falls at every step, to under half of the white's at 4 % owf (dyes absorb
        the ultraviolet and the blue: measured 0.02 (yellow) to 0.39 (royal blue))."""
        depths = np.array([0.0, 0.01, 0.1, 1.0, 4.0])
        for index in range(len(tf.SHADE_CARD_DYES)):
            recipes = np.zeros((depths.size, len(tf.SHADE_CARD_DYES)))
            recipes[:, index] = depths
            beta = tf.brightener_fluorescence(recipes, np.full(depths.size, tf.BRIGHTENER_CONCENTRATION),
                                              tf.SHADE_CARD_K1, tf.d65_photon_irradiance)
            peak = beta.max(axis=1)
            assert np.all(np.diff(peak) < 0.0) and peak[-1] < 0.5 * peak[0], (tf.SHADE_CARD_DYES[index].name, peak)

    def test_whites_exceed_one_only_in_the_emission_band(self):
        """The brightened whites' total radiance factor under D65 exceeds 1 at 420-470 nm (peak
        1.05-1.15, as brightened papers and cottons measure) and nowhere else; deep shades and the
        kinds without a brightener stay below 1."""
        targets = tf.sample_targets("fluorescent", 200, 0)
        _, R = tf.target_family("fluorescent", 200, 0, noise=False)
        np.testing.assert_array_equal(R, km.on_reflectance_grid(targets.reference()))
        depth = targets.recipes.sum(axis=1)
        whites = R[depth == 0.0]
        assert len(whites) == 6 and np.all(whites.max(axis=1) > 1.0)
        assert 1.05 < whites.max() < 1.15  # measured 1.059
        band = (WAVELENGTHS_NM >= 420) & (WAVELENGTHS_NM <= 470)
        assert R[:, ~band].max() < 1.0 and R[depth >= 0.5].max() < 1.0
        for kind in ("shade_card", "gloss_texture"):
            assert tf.target_family(kind, 200, 0, noise=False)[1].max() < 1.0

    def test_camera_and_reference_see_different_fluorescence(self):
        """The sphere's xenon light and D65 differ in the ultraviolet: the camera's β_L differs
        from the reference's by more than 10 % for a brightened white, and the responses miss
        the camera's linear system through the reference by far more than the projection does."""
        white = np.zeros((1, len(tf.SHADE_CARD_DYES)))
        brightened = np.array([tf.BRIGHTENER_CONCENTRATION])
        camera = tf.brightener_fluorescence(white, brightened, tf.SHADE_CARD_K1, tf.sphere_photon_irradiance)
        reference = tf.brightener_fluorescence(white, brightened, tf.SHADE_CARD_K1, tf.d65_photon_irradiance)
        assert abs(camera.max() / reference.max() - 1.0) > 0.1  # measured 1.21
        system = target_system()
        violet_blue = slice(1, 3)  # the 420 and 440 nm bands, in the emission band
        misses = {}
        for kind in ("shade_card", "fluorescent"):
            V, R = tf.target_family(kind, 200, 0, noise=False)
            misses[kind] = np.sqrt(np.mean((V - (R @ system.sensitivity.T + system.offset))[:, violet_blue] ** 2))
        assert misses["fluorescent"] > 10.0 * misses["shade_card"], misses  # measured 0.039 and 0.0011


class TestSurfaceAndTexture:
    def test_cavity_is_the_sum_of_its_interreflections(self):
        reflectance, a = np.linspace(0.0, 1.0, 11), 0.5
        series = sum(reflectance * (1.0 - a) * (a * reflectance) ** m for m in range(200))
        np.testing.assert_allclose(tf.cavity_reflectance(reflectance, a), series, rtol=1e-12, atol=1e-15)
        assert np.all(tf.cavity_reflectance(reflectance[1:-1], a) < reflectance[1:-1])  # texture deepens colour

    def test_sci_minus_camera_is_the_specular_part(self):
        """R_SCI - R_cam = (1 - f) g k1 (Eqs. S2-S3) for every target and wavelength; g = 0 (all
        surface reflection diffuse) the camera sees as SCI; and the body is Saunderson's SCE."""
        targets = tf.sample_targets("gloss_texture", 100, 0)
        difference = targets.reference() - targets.camera()
        expected = (1.0 - targets.cavity_fraction) * targets.gloss * targets.k1
        np.testing.assert_allclose(difference, np.broadcast_to(expected[:, None], difference.shape), rtol=1e-10, atol=1e-15)
        assert 0.005 < expected.min() and expected.max() < 0.045
        matte = tf.surface_view(targets.body_camera, targets.k1, 0.0, targets.cavity_fraction, 0.5, specular_included=False)
        np.testing.assert_allclose(matte, targets.reference(), rtol=1e-12)
        internal = km.reflectance_from_ks(tf._layer_ks(targets.recipes, targets.brightener, FINE_WAVELENGTHS_NM)[0])
        for index in (0, 50):
            sce = km.saunderson(internal[index], targets.k1[index], tf.SHADE_CARD_K2, specular_included=False)
            sci = km.saunderson(internal[index], targets.k1[index], tf.SHADE_CARD_K2, specular_included=True)
            np.testing.assert_allclose(targets.body_camera[index], sce, rtol=1e-12)
            flat = tf.surface_view(targets.body_reference[index:index + 1], targets.k1[index], 1.0, 0.0, 0.5,
                                   specular_included=True)
            np.testing.assert_allclose(flat[0], sci, rtol=1e-12)

    def test_responses_follow_the_camera_system(self):
        """Noise-free, the responses are the camera's linear system (simulated_targets.target_system)
        applied to what the camera sees: for the shade card the reference itself, for gloss and
        texture the reference less (1 - f) g k1; to the 31-sample projection's precision."""
        system = target_system()
        targets = tf.sample_targets("shade_card", 200, 0)
        V, R = tf.target_family("shade_card", 200, 0, noise=False)
        np.testing.assert_array_equal(targets.camera(), targets.reference())
        np.testing.assert_array_equal(V, render_targets(targets.camera(), noise=False))
        np.testing.assert_array_equal(R, km.on_reflectance_grid(targets.reference()))
        # The 31 samples determine the fine spectrum through linear interpolation (M's projection):
        # what the camera integrates between them is the projection's error, ~1e-3 as for km_mixing.
        misfit = V - (R @ system.sensitivity.T + system.offset)
        projection = V - render_targets(km.on_reflectance_grid(targets.camera()) @ INTERPOLATE_31_TO_FINE.T, noise=False)
        np.testing.assert_allclose(misfit, projection, atol=1e-12)
        assert np.sqrt(np.mean(misfit**2)) < 2.5e-3  # measured 1.9e-3 (km_mixing's 3.4e-3)
        targets = tf.sample_targets("gloss_texture", 200, 0)
        V, R = tf.target_family("gloss_texture", 200, 0, noise=False)
        np.testing.assert_array_equal(V, render_targets(targets.camera(), noise=False))
        seen = R - ((1.0 - targets.cavity_fraction) * targets.gloss * targets.k1)[:, None]
        misfit_gloss = V - (seen @ system.sensitivity.T + system.offset)
        projection = V - render_targets(seen @ INTERPOLATE_31_TO_FINE.T, noise=False)
        np.testing.assert_allclose(misfit_gloss, projection, atol=1e-12)
        naive = V - (R @ system.sensitivity.T + system.offset)  # the reference's SCI is not what the camera saw
        assert np.sqrt(np.mean(naive**2)) > 5.0 * np.sqrt(np.mean(misfit_gloss**2))


class TestNoise:
    def test_camera_noise_is_the_simulators_region_mean(self):
        """Without texture, a response's noise falls as 1 / sqrt(patch_pixels) (the simulator's
        pixel noise over the region's pixels); texture adds a region-to-reference difference that
        falls the same way and, at 35 x 35 px, dominates."""
        clean = {kind: tf.target_family(kind, 200, 0, noise=False)[0] for kind in ("shade_card", "gloss_texture")}
        std = {(kind, pixels): np.std(tf.target_family(kind, 200, 0, patch_pixels=pixels)[0] - clean[kind])
               for kind in clean for pixels in (100, 1600)}
        assert 3.6 < std["shade_card", 100] / std["shade_card", 1600] < 4.4
        assert 3.0 < std["gloss_texture", 100] / std["gloss_texture", 1600] < 4.4
        assert std["gloss_texture", 1600] > 3.0 * std["shade_card", 1600]

    def test_reference_noise_has_the_spectrophotometers_size(self):
        """Reference minus the noise-free reference: per-wavelength, gain and offset noise of
        `REFERENCE_NOISE` (total std within 15 % of its prediction); km_mixing's stays exact."""
        _, noisy = tf.target_family("shade_card", 200, 0)
        _, clean = tf.target_family("shade_card", 200, 0, noise=False)
        noise = tf.REFERENCE_NOISE
        predicted = np.sqrt(noise.per_wavelength**2 + noise.offset_per_target**2
                            + noise.relative_per_target**2 * np.mean(clean**2))
        assert abs(np.std(noisy - clean) / predicted - 1.0) < 0.15
        np.testing.assert_array_equal(tf.target_family("km_mixing", 50, 0)[1], tf.target_family("km_mixing", 50, 0, noise=False)[1])


def test_shade_cards_and_real_mechanisms_are_harder_than_mixing():
    """The affine estimator (fit_wiener, method="training") trained on seed 0 and tested on seed
    1 (200 targets each) misses the shade card by more than the Kubelka-Munk mixing family and
    all mechanisms together by far more (measured: 8.7e-4, 1.75e-3, 7.8e-3)."""
    rms = {kind: held_out_rms(kind) for kind in ("km_mixing", "shade_card", "mixed_real")}
    assert rms["shade_card"] > 1.5 * rms["km_mixing"], rms
    assert rms["mixed_real"] > 4.0 * rms["km_mixing"] and rms["mixed_real"] > 2.0 * rms["shade_card"], rms
