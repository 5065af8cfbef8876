"""Kubelka-Munk dyed-material families: the equations and their inverses, K/S additivity against
the non-additivity of reflectance, dye bands and substrates, recipe sampling (1 to 3 of each
family's 6 dyes), the families' distinctness, responses as patch means, the curved manifold that
a linear map from camera responses cannot follow, and the nonlinear structure that an estimator
can learn from patch-mean responses but not from single pixels (why the families exist)."""

import collections
import dataclasses

import numpy as np
import pytest
from scipy.optimize import nnls

from spherejax import kubelka_munk as km
from spherejax.grid import WAVELENGTHS_NM
from spherejax.simulate import FINE_WAVELENGTHS_NM, InstrumentModel
from spherejax.simulated_targets import render_targets

FAMILY_NAMES = list(km.MATERIAL_FAMILIES)
DYES = 6  # dyes per shipped family


def rms(a, b):
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


def affine_held_out_rms(V_train, R_train, V_test, R_test):
    """rms of the affine least-squares map responses -> reflectance, fitted on one set, on another."""
    def with_ones(V):
        return np.concatenate([V, np.ones((len(V), 1))], axis=1)

    X = np.linalg.lstsq(with_ones(V_train), R_train, rcond=None)[0]
    return rms(with_ones(V_test) @ X, R_test)


@pytest.fixture(scope="module")
def noiseless():
    """Two draws (targets and samples) of every family, exact responses."""
    return km.km_family_responses(seed=0, n=150, noise=False), km.km_family_responses(seed=1, n=150, noise=False)


class TestKubelkaMunk:
    KS = np.geomspace(1e-4, 1e3, 400)

    def test_known_values(self):
        assert km.reflectance_from_ks(0.0) == 1.0
        assert km.reflectance_from_ks(0.5) == pytest.approx(1.5 - np.sqrt(1.25), rel=1e-15)
        assert km.reflectance_from_ks(0.5) == pytest.approx(0.381966, abs=5e-7)
        assert km.ks_from_reflectance(1.0) == 0.0
        assert km.ks_from_reflectance(0.5) == pytest.approx(0.25, rel=1e-15)  # (0.5)^2 / 1

    def test_round_trip_over_seven_decades(self):
        R = km.reflectance_from_ks(self.KS)
        np.testing.assert_allclose(km.ks_from_reflectance(R), self.KS, rtol=1e-12)
        R_grid = np.linspace(1e-3, 0.999, 500)
        np.testing.assert_allclose(km.reflectance_from_ks(km.ks_from_reflectance(R_grid)), R_grid, rtol=1e-12)

    def test_reflectance_lies_in_the_unit_interval_and_falls_with_ks(self):
        R = km.reflectance_from_ks(self.KS)
        assert np.all((R > 0.0) & (R < 1.0))
        assert np.all(np.diff(R) < 0.0)
        assert R[0] > 0.98 and R[-1] < 6e-4  # nearly white at K/S = 1e-4, black at 1e3

    def test_the_stable_form_equals_the_textbook_form(self):
        """1 / (1 + x + sqrt(x^2 + 2x)) == 1 + x - sqrt(x^2 + 2x) where the latter does not cancel."""
        x = np.geomspace(1e-4, 10.0, 100)
        np.testing.assert_allclose(km.reflectance_from_ks(x), 1.0 + x - np.sqrt(x * x + 2.0 * x), rtol=1e-12)

    def test_shapes_are_kept(self):
        ks = np.full((2, 3, 5), 0.3)
        assert km.reflectance_from_ks(ks).shape == (2, 3, 5)
        assert km.ks_from_reflectance(km.reflectance_from_ks(ks)).shape == (2, 3, 5)


class TestSaunderson:
    R_INF = np.linspace(0.0, 1.0, 201)

    @pytest.mark.parametrize("specular_included", [False, True])
    @pytest.mark.parametrize("k1, k2", [(0.04, 0.6), (0.059, 0.4), (0.04, 0.45)])
    def test_round_trip(self, k1, k2, specular_included):
        R_m = km.saunderson(self.R_INF, k1, k2, specular_included=specular_included)
        back = km.inverse_saunderson(R_m, k1, k2, specular_included=specular_included)
        np.testing.assert_allclose(back, self.R_INF, rtol=1e-13, atol=1e-15)
        assert np.all(np.diff(R_m) > 0.0)

    @pytest.mark.parametrize("specular_included", [False, True])
    def test_no_surface_is_the_identity(self, specular_included):
        np.testing.assert_array_equal(km.saunderson(self.R_INF, 0.0, 0.0, specular_included=specular_included), self.R_INF)
        back = km.inverse_saunderson(self.R_INF, 0.0, 0.0, specular_included=specular_included)
        np.testing.assert_array_equal(back, self.R_INF)

    def test_values_and_the_two_geometries(self):
        # (1 - 0.04)(1 - 0.6) 0.5 / (1 - 0.6 * 0.5) = 0.192 / 0.7
        assert km.saunderson(0.5, 0.04, 0.6) == pytest.approx(0.192 / 0.7, rel=1e-15)
        sce = km.saunderson(self.R_INF, 0.04, 0.6, specular_included=False)
        sci = km.saunderson(self.R_INF, 0.04, 0.6, specular_included=True)
        np.testing.assert_allclose(sci - sce, 0.04, rtol=1e-12)
        # A black body reflects only its surface; a perfect white loses the light its surface sends away.
        assert sce[0] == 0.0 and sci[0] == pytest.approx(0.04)
        assert sce[-1] == pytest.approx(0.96, rel=1e-14) and sci[-1] == pytest.approx(1.0, rel=1e-14)
        assert km.SPECULAR_INCLUDED is False  # the d:0° sphere excludes the specular component


class TestMixtures:
    def test_mixture_ks_is_the_substrate_plus_concentration_weighted_dyes(self):
        family = km.MATERIAL_FAMILIES["cotton reactive"]
        c = np.zeros((3, DYES))
        c[1, 0] = 1.0
        c[2, [0, 2, 5]] = 0.5, 2.0, 0.1
        ks = km.mixture_ks(family.substrate_ks, family.dye_ks, c)
        assert ks.shape == (3, FINE_WAVELENGTHS_NM.size)
        np.testing.assert_array_equal(ks[0], family.substrate_ks)
        np.testing.assert_allclose(ks[1], family.substrate_ks + family.dye_ks[0], rtol=1e-15)
        expected = family.substrate_ks + 0.5 * family.dye_ks[0] + 2.0 * family.dye_ks[2] + 0.1 * family.dye_ks[5]
        np.testing.assert_allclose(ks[2], expected, rtol=1e-14)

    @pytest.mark.parametrize("name", FAMILY_NAMES)
    def test_ks_from_measured_reflectance_is_additive_and_reflectance_is_not(self, name):
        """The colorist's K/S (Saunderson-inverted, Eq. 5, then Eq. 1) adds over recipes; the
        measured reflectance of the sum is far from the sum of the reflectance changes."""
        family = km.MATERIAL_FAMILIES[name]
        high = family.concentration_range[1]
        c_a, c_b, none = np.zeros(DYES), np.zeros(DYES), np.zeros(DYES)
        c_a[0], c_b[1], c_b[2] = high / 2, high / 2, high / 4
        R = {key: family.reflectance(c) for key, c in (("a", c_a), ("b", c_b), ("a+b", c_a + c_b), ("0", none))}
        ks = {key: family.ks_from_measured(value) for key, value in R.items()}
        np.testing.assert_allclose(ks["a+b"] - ks["0"], (ks["a"] - ks["0"]) + (ks["b"] - ks["0"]), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(ks["a+b"], km.mixture_ks(family.substrate_ks, family.dye_ks, c_a + c_b), rtol=1e-9)
        deviation = np.abs((R["a+b"] - R["0"]) - ((R["a"] - R["0"]) + (R["b"] - R["0"])))
        assert deviation.max() > 0.3  # measured 0.53 (wool acid) to 0.80 (cotton reactive)

    @pytest.mark.parametrize("name", FAMILY_NAMES)
    def test_a_family_is_flat_in_ks_and_curved_in_reflectance(self, name):
        """Minus the substrate, a family's K/S span exactly its D = 6 dyes (recipes of 1 to 3 dyes
        each, all 6 used across the family); its reflectances lie near no D-dimensional affine
        subspace (the union of 3-dimensional pieces is curved)."""
        family = km.MATERIAL_FAMILIES[name]
        _, fine = km.sample_family(family, 150, seed=0)
        R = km.on_reflectance_grid(fine)
        ks = family.ks_from_measured(R) - km.on_reflectance_grid(family.substrate_ks)
        dyes = len(family.dyes)
        assert dyes == DYES
        singular = np.linalg.svd(ks, compute_uv=False)
        assert singular[dyes] < 1e-10 * singular[0]  # measured < 2e-16
        assert singular[dyes - 1] > 1e-3 * singular[0]  # rank exactly D: measured 0.026 (polyester) to 0.072 (wool)
        singular = np.linalg.svd(R - R.mean(axis=0), compute_uv=False)
        residual_of_best_affine_subspace = np.sqrt(np.sum(singular[dyes:] ** 2) / R.size)
        assert residual_of_best_affine_subspace > 0.005  # measured 0.010 (paper) to 0.015 (wool)


class TestDyesAndSubstrates:
    def test_a_band_has_its_strength_at_the_peak_and_half_at_its_width(self):
        band = km.AbsorptionBand(peak_nm=520.0, fwhm_nm=80.0, strength=3.0)
        # Gaussian in wavenumber: half maximum at 1/λ = 1/λ0 ± (w / λ0^2) / 2.
        half = 1.0 / (1.0 / 520.0 + np.array([1.0, -1.0]) * 80.0 / 520.0**2 / 2.0)
        np.testing.assert_allclose(km.absorption_bands_ks(np.array([520.0, *half]), (band,)), [3.0, 1.5, 1.5], rtol=1e-14)
        assert half[1] - half[0] == pytest.approx(80.0, rel=0.01)  # ≈ the width in nm at the peak
        assert half[1] - 520.0 > 520.0 - half[0]  # the longer tail is to the red

    def test_dye_peaks_lie_where_their_hue_class_absorbs(self):
        expected_nm = {"yellow": (400, 460), "orange": (470, 500), "red": (480, 520), "rubine": (520, 550), "magenta": (530, 560),
                       "violet": (530, 560), "navy": (575, 620), "blue": (580, 640), "turquoise": (600, 680)}
        checked = 0
        for family in km.MATERIAL_FAMILIES.values():
            visible = (FINE_WAVELENGTHS_NM >= 400) & (FINE_WAVELENGTHS_NM <= 700)
            for dye, ks in zip(family.dyes, family.dye_ks):
                peak = FINE_WAVELENGTHS_NM[visible][np.argmax(ks[visible])]
                (low, high), = [span for hue, span in expected_nm.items() if hue in dye.name]
                assert low <= peak <= high, (family.name, dye.name, peak)
                checked += 1
        assert checked == DYES * len(km.MATERIAL_FAMILIES)

    def test_undyed_substrates_measure_as_their_kind(self):
        undyed = {name: km.on_reflectance_grid(family.reflectance(np.zeros(len(family.dyes))))
                  for name, family in km.MATERIAL_FAMILIES.items()}
        at = {int(nm): index for index, nm in enumerate(WAVELENGTHS_NM)}.__getitem__
        for R in undyed.values():
            assert np.all(np.diff(R) >= 0.0)  # they absorb most in the blue
        assert undyed["cotton reactive"][at(400)] == pytest.approx(0.80, abs=0.02)
        assert undyed["cotton reactive"][at(700)] == pytest.approx(0.88, abs=0.02)
        assert undyed["wool acid"][at(400)] < 0.5 and undyed["wool acid"][at(700)] > 0.7  # yellowish
        assert all(undyed[name].min() > 0.75 for name in ("cotton reactive", "polyester disperse", "paper direct"))

    def test_on_reflectance_grid_takes_the_31_samples(self):
        family = km.MATERIAL_FAMILIES["wool acid"]
        fine = family.reflectance(np.array([[0.3, 0.1, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.5, 0.0, 2.0]]))
        coarse = km.on_reflectance_grid(fine)
        assert coarse.shape == (2, WAVELENGTHS_NM.size)
        for row, values in zip(fine, coarse):
            np.testing.assert_array_equal(values, np.interp(WAVELENGTHS_NM, FINE_WAVELENGTHS_NM, row))
        with pytest.raises(ValueError, match="FINE_WAVELENGTHS_NM"):
            km.on_reflectance_grid(coarse)

    def test_families_are_read_only_and_checked(self):
        family = km.MATERIAL_FAMILIES["cotton reactive"]
        with pytest.raises(TypeError):
            km.MATERIAL_FAMILIES["other"] = family
        with pytest.raises(dataclasses.FrozenInstanceError):
            family.k2 = 0.5
        with pytest.raises(ValueError):
            family.dye_ks[0, 0] = 1.0
        with pytest.raises(ValueError, match="concentration_range"):
            dataclasses.replace(family, concentration_range=(1.0, 0.1))
        with pytest.raises(ValueError, match="k1 and k2"):
            dataclasses.replace(family, k2=1.0)
        for bad in (0, DYES + 1, 2.5, True):
            with pytest.raises(ValueError, match="max_dyes_per_recipe"):
                dataclasses.replace(family, max_dyes_per_recipe=bad)
        assert family.dye_ks.shape == (DYES, FINE_WAVELENGTHS_NM.size) and family.substrate_ks.shape == (FINE_WAVELENGTHS_NM.size,)
        assert all(family.max_dyes_per_recipe == 3 for family in km.MATERIAL_FAMILIES.values())


class TestSampling:
    @pytest.mark.parametrize("name", FAMILY_NAMES)
    def test_recipes_and_reflectances(self, name):
        family = km.MATERIAL_FAMILIES[name]
        c, fine = km.sample_family(name, 600, seed=3)
        assert c.shape == (600, DYES) and fine.shape == (600, FINE_WAVELENGTHS_NM.size)
        assert np.all((fine > 0.0) & (fine < 1.0))
        np.testing.assert_array_equal(fine, family.reflectance(c))
        dyes_used = np.count_nonzero(c, axis=1)
        assert set(dyes_used) == {1, 2, 3}  # 1 to max_dyes_per_recipe = 3 of the 6
        assert np.min(np.bincount(dyes_used)[1:]) > 150  # each count about a third of 600: measured 188-215
        # a random subset: each dye in about 2/6 of the recipes (mean count 2 of 6 dyes), 200 of 600:
        # measured 174-210
        recipes_per_dye = np.count_nonzero(c, axis=0)
        assert np.all((recipes_per_dye > 150) & (recipes_per_dye < 250)), recipes_per_dye
        low, high = family.concentration_range
        used = c[c > 0]
        assert used.min() >= low and used.max() <= high
        # log-uniform: as many below the geometric middle of the range as above it
        assert 0.42 < np.mean(used < np.sqrt(low * high)) < 0.58
        R = km.on_reflectance_grid(fine)
        assert R.max() > 0.6  # pale shades ...
        assert R.mean(axis=1).min() < 0.15  # ... and deep ones

    @pytest.mark.parametrize("max_dyes", [1, 2, 6])
    def test_max_dyes_per_recipe(self, max_dyes):
        family = dataclasses.replace(km.MATERIAL_FAMILIES["wool acid"], max_dyes_per_recipe=max_dyes)
        c = km.sample_recipes(family, 600, np.random.default_rng(0))
        dyes_used = np.count_nonzero(c, axis=1)
        assert set(dyes_used) == set(range(1, max_dyes + 1))
        assert np.all(np.count_nonzero(c, axis=0) > 0)  # every dye in some recipe

    def test_a_seed_fixes_the_draw(self):
        family = km.MATERIAL_FAMILIES["paper direct"]
        first, second, other = (km.sample_family(family, 50, seed=s) for s in (7, 7, 8))
        np.testing.assert_array_equal(first[0], second[0])
        np.testing.assert_array_equal(first[1], second[1])
        assert not np.array_equal(first[0], other[0])

    def test_specular_included_adds_k1(self):
        family = km.MATERIAL_FAMILIES["polyester disperse"]
        _, sce = km.sample_family(family, 20, seed=0)
        _, sci = km.sample_family(family, 20, seed=0, specular_included=True)
        np.testing.assert_allclose(sci - sce, family.k1, rtol=1e-12)


class TestFamilies:
    def test_four_families_of_different_substrates_and_dyes(self):
        families = list(km.MATERIAL_FAMILIES.values())
        assert len(families) >= 4
        assert len({family.substrate.name for family in families}) == len(families)
        dye_names = [name for family in families for name in family.dye_names]
        assert len(set(dye_names)) == len(dye_names) == DYES * len(families)

    def test_no_family_dyes_can_be_mixed_from_another_family_dyes(self):
        """For every ordered pair, some dye of the first family is far (relative rms) from every
        non-negative combination of the second family's dyes: the dye sets differ."""
        for a in FAMILY_NAMES:
            for b in FAMILY_NAMES:
                if a == b:
                    continue
                basis = km.on_reflectance_grid(km.MATERIAL_FAMILIES[b].dye_ks).T
                dyes = km.on_reflectance_grid(km.MATERIAL_FAMILIES[a].dye_ks)
                misfits = [nnls(basis, ks)[1] / np.linalg.norm(ks) for ks in dyes]
                assert max(misfits) > 0.25, (a, b, misfits)  # measured 0.33 (polyester by paper) to 0.65 (wool by polyester)

    def test_mean_spectra_differ(self, noiseless):
        targets, _ = noiseless
        means = {name: R.mean(axis=0) for name, (_, R, _) in targets.items()}
        for i, a in enumerate(FAMILY_NAMES):
            for b in FAMILY_NAMES[i + 1:]:
                assert rms(means[a], means[b]) > 0.03, (a, b)  # measured 0.064 (cotton, wool) to 0.16 (polyester, paper)

    def test_responses_are_the_rendered_recipes(self, noiseless):
        targets, samples = noiseless
        assert list(targets) == FAMILY_NAMES
        for name, (V, R, c) in targets.items():
            family = km.MATERIAL_FAMILIES[name]
            assert V.shape == (150, 16) and R.shape == (150, 31) and c.shape == (150, DYES)
            fine = family.reflectance(c)
            np.testing.assert_array_equal(R, km.on_reflectance_grid(fine))
            np.testing.assert_array_equal(V, render_targets(fine, noise=False))
            assert not np.array_equal(c, samples[name][2])  # targets and samples: two draws
        again = km.km_family_responses(seed=0, n=150, noise=False)
        for name in FAMILY_NAMES:
            np.testing.assert_array_equal(again[name][2], targets[name][2])
        recipes = [c for _, _, c in targets.values()]
        assert not np.array_equal(recipes[0], recipes[1])  # each family its own draw

    def test_noise_is_small_and_seeded(self, noiseless):
        targets, _ = noiseless
        noisy, noisy_again = (km.km_family_responses(seed=0, n=150) for _ in range(2))
        for name in FAMILY_NAMES:
            np.testing.assert_array_equal(noisy[name][0], noisy_again[name][0])
            np.testing.assert_array_equal(noisy[name][1], targets[name][1])  # same recipes as without noise
            difference = noisy[name][0] - targets[name][0]
            assert 0.0 < np.std(difference) < 5e-4  # 20 x 20 px means: measured 1.4e-4 to 1.7e-4 (a pixel's 0.0027-0.0034)

    def test_a_linear_map_from_responses_cannot_follow_a_family(self, noiseless):
        """The affine least-squares map from 16 exact responses to 31-sample reflectance, fitted on
        one draw and applied to another, misses a Kubelka-Munk family by far more than it misses
        random linear mixtures of 49 of that family's own spectra (the substrate and each of its 6
        dyes alone at 8 concentrations): the responses are linear in reflectance, the family is
        curved."""
        targets, samples = noiseless
        for index, (name, family) in enumerate(km.MATERIAL_FAMILIES.items()):
            curved = affine_held_out_rms(*targets[name][:2], *samples[name][:2])
            levels = np.geomspace(*family.concentration_range, 8)
            basis = family.reflectance(np.vstack([np.zeros(DYES), *(np.eye(DYES) * level for level in levels)]))
            rng = np.random.default_rng(index)
            train, test = (rng.dirichlet(np.ones(len(basis)), 150) @ basis for _ in range(2))
            linear = affine_held_out_rms(render_targets(train, noise=False), km.on_reflectance_grid(train),
                                         render_targets(test, noise=False), km.on_reflectance_grid(test))
            # measured: curved 4.9e-4 (paper) to 9.3e-4 (cotton), 15x (wool) to 36x (cotton) the linear mixtures'
            assert curved > 2e-4 and curved > 10.0 * linear, (name, curved, linear)


class TestPatchMeans:
    def test_noise_falls_as_one_over_the_root_of_the_pixels(self, noiseless):
        """A response is the mean over `patch_pixels` pixels: its noise std is a pixel's / sqrt(pixels)."""
        targets, _ = noiseless
        pixel, patch = (km.km_family_responses(seed=0, n=150, patch_pixels=p) for p in (1, 100))
        for name in FAMILY_NAMES:
            std_pixel = np.std(pixel[name][0] - targets[name][0])
            std_patch = np.std(patch[name][0] - targets[name][0])
            assert 0.002 < std_pixel < 0.005  # a pixel's noise at 4 frames: measured 0.0027-0.0034
            assert 9.0 < std_pixel / std_patch < 11.0, (name, std_pixel, std_patch)  # measured 10.00-10.01
            np.testing.assert_array_equal(patch[name][1], pixel[name][1])  # the same recipes

    def test_patch_pixels_scale_the_given_instruments_frames(self):
        """patch_pixels multiplies the sample's and the white's frame counts of the instrument given."""
        instrument = InstrumentModel(frames_averaged_sample=2, frames_averaged_white=3)
        scaled = km.km_family_responses(seed=4, n=20, instrument=instrument, patch_pixels=25)
        frames = km.km_family_responses(
            seed=4, n=20, instrument=dataclasses.replace(instrument, frames_averaged_sample=50, frames_averaged_white=75),
            patch_pixels=1)
        default = km.km_family_responses(seed=4, n=20, instrument=InstrumentModel(), patch_pixels=400)
        default_too = km.km_family_responses(seed=4, n=20)
        for name in FAMILY_NAMES:
            np.testing.assert_array_equal(scaled[name][0], frames[name][0])
            np.testing.assert_array_equal(default[name][0], default_too[name][0])
        assert instrument.frames_averaged_sample == 2  # the given instrument is left as it was

    @pytest.mark.parametrize("bad", [0, -4, 2.5, "400", True, None])
    def test_bad_patch_pixels_are_refused(self, bad):
        with pytest.raises(ValueError, match="patch_pixels must be an integer >= 1"):
            km.km_family_responses(n=2, patch_pixels=bad)


def with_ones(V):
    return np.concatenate([V, np.ones((len(V), 1))], axis=1)


def affine_map(V, R, ridge=1e-10):
    """Least squares [V 1] X ≈ R with a tiny ridge (numpy lstsq on the stacked system)."""
    X = with_ones(V)
    A = np.vstack([X, np.sqrt(ridge) * np.eye(X.shape[1])])
    B = np.vstack([R, np.zeros((X.shape[1], R.shape[1]))])
    return np.linalg.lstsq(A, B, rcond=None)[0]


LENGTHSCALES = (2.0, 4.0, 8.0, 16.0)
RIDGES = (1e-4, 1e-3, 1e-2)


def affine_plus_kernel_ridge(V_train, R_train, V_test, lengthscales=LENGTHSCALES, ridges=RIDGES):
    """The affine map plus kernel ridge regression of its residuals, RBF kernel on PCA-whitened
    responses: {(lengthscale, ridge): predictions (n_test, 31)} for every pair, from one
    eigendecomposition of the kernel per lengthscale (few LAPACK calls: the suite runs two
    workers on two cores, where each multithreaded LAPACK call can wait on a busy core)."""
    X = affine_map(V_train, R_train)
    affine_test = with_ones(V_test) @ X
    residuals = R_train - with_ones(V_train) @ X
    mean = V_train.mean(axis=0)
    _, s, Vt = np.linalg.svd(V_train - mean, full_matrices=False)
    whiten = Vt.T / (s / np.sqrt(len(V_train)))
    Z_train, Z_test = (V_train - mean) @ whiten, (V_test - mean) @ whiten

    def squared_distances(A, B):
        return np.maximum(np.sum(A * A, axis=1)[:, None] + np.sum(B * B, axis=1)[None] - 2.0 * A @ B.T, 0.0)

    train_train, test_train = squared_distances(Z_train, Z_train), squared_distances(Z_test, Z_train)
    out = {}
    for lengthscale in lengthscales:
        eigenvalues, Q = np.linalg.eigh(np.exp(-train_train / (2.0 * lengthscale**2)))
        projected = Q.T @ residuals
        K_test = np.exp(-test_train / (2.0 * lengthscale**2))
        for ridge in ridges:
            alpha = Q @ (projected / (eigenvalues + ridge)[:, None])  # (K + ridge I)^-1 residuals
            out[lengthscale, ridge] = affine_test + K_test @ alpha
    return out


def kernel_ridge_by_cross_validation(V_train, R_train, V_test, folds=5):
    """affine_plus_kernel_ridge with lengthscale and ridge chosen by k-fold CV on the training set."""
    index = np.arange(len(V_train))
    errors = collections.Counter()
    for held_out in np.array_split(index, folds):
        fit = np.setdiff1d(index, held_out)
        for key, predicted in affine_plus_kernel_ridge(V_train[fit], R_train[fit], V_train[held_out]).items():
            errors[key] += np.sum((predicted - R_train[held_out]) ** 2)
    lengthscale, ridge = min(errors, key=errors.__getitem__)
    return affine_plus_kernel_ridge(V_train, R_train, V_test, (lengthscale,), (ridge,))[lengthscale, ridge]


def affine_and_nonlinear_held_out_rms(patch_pixels):
    """Family -> (affine rms, affine + kernel ridge rms) on seed 1, both fitted on seed 0 (n = 200)."""
    train, test = (km.km_family_responses(seed=seed, n=200, patch_pixels=patch_pixels) for seed in (0, 1))
    out = {}
    for name in FAMILY_NAMES:
        (V_train, R_train, _), (V_test, R_test, _) = train[name], test[name]
        affine = rms(with_ones(V_test) @ affine_map(V_train, R_train), R_test)
        out[name] = affine, rms(kernel_ridge_by_cross_validation(V_train, R_train, V_test), R_test)
    return out


class TestWhatAnEstimatorCanLearn:
    """Why the families exist: their nonlinear structure is there for an estimator to learn.

    An affine least-squares map from the 16 responses (+ a constant) to the 31 reflectances, fitted
    on one draw (seed 0, 200 recipes per family) and applied to another (seed 1), leaves a held-out
    error; kernel ridge regression on its residuals (RBF on PCA-whitened responses, lengthscale and
    ridge by 5-fold cross-validation on the training draw only) removes much of it from patch-mean
    responses, and next to nothing from single pixels, whose noise buries the structure."""

    def test_a_nonlinear_regression_beats_the_affine_map_on_patch_means(self):
        result = affine_and_nonlinear_held_out_rms(patch_pixels=400)
        gains = {name: 1.0 - nonlinear / affine for name, (affine, nonlinear) in result.items()}
        # measured: affine 4.7e-4 (paper) to 9.0e-4 (wool); gain 34 % (paper), 51 % (wool, polyester), 57 % (cotton)
        # (34-62 % on every family for seed pairs (2, 3), (4, 5), (6, 7), (1, 0))
        assert sum(gain >= 0.2 for gain in gains.values()) >= 3, gains
        assert all(2e-4 < affine < 2e-3 for affine, _ in result.values()), result

    def test_single_pixel_noise_buries_the_structure(self):
        result = affine_and_nonlinear_held_out_rms(patch_pixels=1)
        gains = {name: 1.0 - nonlinear / affine for name, (affine, nonlinear) in result.items()}
        # measured: affine 2.8e-3 to 3.2e-3 (the noise), gain 2.0 % (paper) to 4.2 % (wool)
        assert all(gain < 0.1 for gain in gains.values()), gains
        assert all(affine > 2e-3 for affine, _ in result.values()), result


# --- a layer over a background (Kubelka 1948) ------------------------------------------------------


@pytest.mark.parametrize("r_inf", [0.03, 0.2, 0.5, 0.9, 0.999])
def test_layer_over_background_limits(r_inf):
    """Thick layers hide the background, vanishing ones are the background, and a background
    equal to R_inf cannot be told from more of the layer."""
    backgrounds = np.linspace(0.0, 1.0, 11)
    assert np.allclose(km.layer_over_background(r_inf, 1e6, backgrounds), r_inf, atol=1e-9)
    assert np.allclose(km.layer_over_background(r_inf, 1e-7, backgrounds), backgrounds, atol=1e-5)
    for sx in (0.1, 1.0, 5.0):
        assert km.layer_over_background(r_inf, sx, r_inf) == pytest.approx(r_inf, rel=1e-9)


def test_two_layers_are_one_layer_twice_as_thick():
    """Kubelka's layers compose: S X over (S X over R_g) equals 2 S X over R_g, for absorbing and
    non-absorbing layers alike (b -> 0 takes the 1 / (S X) limit of b coth)."""
    rng = np.random.default_rng(3)
    r_inf = rng.uniform(0.02, 0.999, 200)
    r_g = rng.uniform(0.0, 1.0, 200)
    sx = rng.uniform(0.2, 6.0, 200)
    once = km.layer_over_background(r_inf, sx, km.layer_over_background(r_inf, sx, r_g))
    assert np.allclose(once, km.layer_over_background(r_inf, 2 * sx, r_g), rtol=1e-9, atol=1e-12)


def test_a_white_layer_over_black_follows_its_transmittance():
    """A layer that does not absorb (R_inf = 1) over black reflects S X / (1 + S X) and
    transmits the rest (Kubelka 1948, K = 0), and over any background lies between it and 1."""
    for sx in (0.5, 2.0, 8.0):
        assert km.layer_over_background(1.0, sx, 0.0) == pytest.approx(sx / (1.0 + sx), rel=1e-6)
        over = km.layer_over_background(1.0, sx, np.linspace(0, 1, 5))
        assert np.all(np.diff(over) > 0) and np.all(over <= 1.0 + 1e-12)
