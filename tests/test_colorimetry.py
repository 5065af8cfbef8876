"""Reflectance -> XYZ -> Lab against colour-science as the oracle."""

import warnings

import colour
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spherejax as sj
from spherejax import spectra
from spherejax.grid import WAVELENGTHS_NM

ILLUMINANTS = ["D65", "A", "F2"]
COLOUR_NAME = {"D65": "D65", "A": "A", "F2": "FL2"}


def colour_sd_to_xyz(refl_31, illuminant, observer="CIE 1931 2 Degree Standard Observer"):
    """colour-science's sd_to_XYZ (ASTM E308, its default) for one 400..700/10 nm spectrum."""
    sd = colour.SpectralDistribution(refl_31, WAVELENGTHS_NM.astype(float))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "Trimming ..." notice for a 400-700 nm input
        return colour.sd_to_XYZ(
            sd, colour.MSDS_CMFS[observer], colour.SDS_ILLUMINANTS[COLOUR_NAME[illuminant]],
            method="ASTM E308",
        )


def colour_lab(refl, illuminant, observer="CIE 1931 2 Degree Standard Observer"):
    """colour-science's Lab of each spectrum, white = perfect diffuser under the illuminant."""
    white = colour_sd_to_xyz(np.ones(31), illuminant, observer)
    xyz = np.stack([colour_sd_to_xyz(r, illuminant, observer) for r in refl])
    return colour.XYZ_to_Lab(xyz / 100.0, colour.XYZ_to_xy(white / 100.0))


@pytest.fixture(scope="module")
def shipped():
    return spectra.all_reflectances()


class TestWeights:
    @pytest.mark.parametrize("illuminant", ILLUMINANTS)
    @pytest.mark.parametrize("observer", ["1931", "1964"])
    def test_perfect_diffuser_has_Y_100(self, illuminant, observer):
        white = sj.white_point_xyz(illuminant, observer=observer)
        np.testing.assert_allclose(white[1], 100.0, rtol=0, atol=1e-10)

    def test_d65_white_point_is_astm_e308(self):
        # ASTM E308 Table 6 white point of D65, 2° observer, 10 nm weights: (95.047, 100, 108.883).
        # The 1 nm CIE value differs in Z (108.906), which is how plain sampling would show.
        np.testing.assert_allclose(sj.white_point_xyz("D65"), (95.047, 100.000, 108.883), atol=1e-3)

    def test_weights_are_cached_and_read_only(self):
        first = sj.tristimulus_weights("A")
        assert sj.tristimulus_weights("A") is first
        assert sj.tristimulus_weights("FL2") is sj.tristimulus_weights("F2")
        assert not first.flags.writeable
        assert first.shape == (31, 3) and first.dtype == np.float64

    def test_astm_weights_differ_from_plain_sampling(self):
        # docs/design.md, "Conventions": multiplying 10 nm samples of CMFs and illuminant is not ASTM E308; make sure
        # the weights are really the folded E2022 ones (they differ, most at the range ends).
        cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
        plain = cmfs[WAVELENGTHS_NM.astype(float)] * colour.SDS_ILLUMINANTS["FL2"][WAVELENGTHS_NM.astype(float)][:, None]
        plain = plain * 100.0 / plain[:, 1].sum()
        assert np.max(np.abs(plain - sj.tristimulus_weights("F2"))) > 0.5


class TestReflectanceToXYZ:
    @pytest.mark.parametrize("illuminant", ILLUMINANTS)
    def test_matches_sd_to_xyz(self, illuminant, shipped):
        rng = np.random.default_rng(0)
        sample = shipped[rng.choice(len(shipped), 25, replace=False)]
        ours = np.asarray(sj.reflectance_to_xyz(sample, illuminant))
        theirs = np.stack([colour_sd_to_xyz(r, illuminant) for r in sample])
        np.testing.assert_allclose(ours, theirs, rtol=1e-12, atol=1e-12)

    def test_ten_degree_observer(self, shipped):
        observer = "CIE 1964 10 Degree Standard Observer"
        sample = shipped[:10]
        ours = np.asarray(sj.reflectance_to_xyz(sample, "D65", observer=observer))
        theirs = np.stack([colour_sd_to_xyz(r, "D65", observer) for r in sample])
        np.testing.assert_allclose(ours, theirs, rtol=1e-12, atol=1e-12)
        assert not np.allclose(ours, np.asarray(sj.reflectance_to_xyz(sample, "D65")), atol=1e-3)

    def test_dtypes(self, dtype):
        xyz = sj.reflectance_to_xyz(np.full((2, 31), 0.5, dtype=dtype))
        assert xyz.dtype == dtype
        np.testing.assert_allclose(np.asarray(xyz)[:, 1], 50.0, rtol=1e-6)

    def test_n_dimensional(self, shipped):
        flat = shipped[:24]
        cube = flat.reshape(2, 3, 4, 31)
        np.testing.assert_allclose(
            np.asarray(sj.reflectance_to_xyz(cube, "A")).reshape(24, 3),
            np.asarray(sj.reflectance_to_xyz(flat, "A")),
            rtol=1e-14,
        )

    def test_jit_matches_eager(self, maybe_jit, shipped):
        fn = maybe_jit(sj.reflectance_to_lab, static_argnames=("illuminant",))
        np.testing.assert_allclose(
            np.asarray(fn(shipped[:5], illuminant="F2")),
            np.asarray(sj.reflectance_to_lab(shipped[:5], "F2")),
            rtol=1e-12,
        )


class TestLab:
    @pytest.mark.parametrize("illuminant", ILLUMINANTS)
    def test_every_shipped_reflectance_float64(self, illuminant, shipped):
        """docs/design.md, "Conventions": every reflectance colour-science ships, 1e-6 ΔE00 in float64."""
        ours = np.asarray(sj.reflectance_to_lab(shipped, illuminant))
        theirs = colour_lab(shipped, illuminant)
        de = colour.delta_E(ours, theirs, method="CIE 2000")
        assert len(shipped) > 400
        assert np.max(de) < 1e-6, np.max(de)

    @pytest.mark.parametrize("illuminant", ILLUMINANTS)
    def test_every_shipped_reflectance_float32(self, illuminant, shipped):
        ours = np.asarray(sj.reflectance_to_lab(shipped.astype(np.float32), illuminant))
        assert ours.dtype == np.float32
        theirs = colour_lab(shipped, illuminant)
        de = colour.delta_E(ours.astype(np.float64), theirs, method="CIE 2000")
        assert np.max(de) < 1e-3, np.max(de)

    def test_ten_degree_observer_every_shipped_reflectance(self, shipped):
        observer = "CIE 1964 10 Degree Standard Observer"
        ours = np.asarray(sj.reflectance_to_lab(shipped, "D65", observer=observer))
        de = colour.delta_E(ours, colour_lab(shipped, "D65", observer), method="CIE 2000")
        assert np.max(de) < 1e-6

    def test_xyz_to_lab_matches_colour_including_dark_colours(self, dtype):
        rng = np.random.default_rng(1)
        white = sj.white_point_xyz("D65")
        # Spread Y over 6 decades so both the cube-root and the linear segment are exercised.
        xyz = white * 10.0 ** rng.uniform(-5, 0, size=(500, 1)) * rng.uniform(0.6, 1.2, size=(500, 3))
        ours = np.asarray(sj.xyz_to_lab(xyz.astype(dtype), white.astype(dtype)))
        theirs = colour.XYZ_to_Lab(xyz / 100.0, colour.XYZ_to_xy(white / 100.0))
        tolerance = {np.float32: 2e-3, np.float64: 1e-9}[dtype]
        np.testing.assert_allclose(ours, theirs, atol=tolerance)

    def test_perfect_diffuser_is_L_100(self):
        np.testing.assert_allclose(np.asarray(sj.reflectance_to_lab(np.ones(31), "A")), [100, 0, 0], atol=1e-10)

    def test_black_is_L_0(self):
        np.testing.assert_allclose(np.asarray(sj.reflectance_to_lab(np.zeros(31))), [0, 0, 0], atol=1e-12)

    def test_white_broadcasts_per_pixel(self):
        xyz = np.array([[20.0, 30.0, 40.0], [20.0, 30.0, 40.0]])
        whites = np.array([[95.0, 100.0, 108.0], [109.8, 100.0, 35.6]])
        lab = np.asarray(sj.xyz_to_lab(xyz, whites))
        np.testing.assert_allclose(lab[1], np.asarray(sj.xyz_to_lab(xyz[1], whites[1])))
        assert not np.allclose(lab[0], lab[1])


class TestNonFinite:
    def test_nan_inf_sweep_does_not_raise(self):
        values = np.array([np.nan, np.inf, -np.inf, 0.0, -1.0, 1e30])
        for value in values:
            refl = np.full((3, 31), 0.4)
            refl[1, 7] = value
            lab = np.asarray(sj.reflectance_to_lab(refl))
            np.testing.assert_allclose(lab[0], lab[2])  # neighbours untouched
            if not np.isfinite(value):
                assert np.isnan(lab[1]).any()

    def test_nan_in_xyz_stays_nan(self):
        lab = np.asarray(sj.xyz_to_lab(np.array([np.nan, 10.0, 10.0]), sj.white_point_xyz()))
        assert np.isnan(lab[0]) == False  # noqa: E712  L* depends on Y alone
        assert np.isnan(lab[1]) and not np.isnan(lab[2])


class TestGradients:
    @pytest.mark.parametrize("level", [0.0, 1e-6, 0.00885, 0.5, 1.0])
    def test_lab_jacobian_finite(self, level):
        refl = jnp.full((31,), level)
        jac = jax.jacrev(sj.reflectance_to_lab)(refl)
        assert jac.shape == (3, 31)
        assert np.all(np.isfinite(np.asarray(jac)))

    def test_lab_gradient_matches_finite_differences(self, shipped):
        refl = jnp.asarray(shipped[3])
        loss = lambda r: jnp.sum(sj.reflectance_to_lab(r, "F2") ** 2)  # noqa: E731
        grad = np.asarray(jax.grad(loss)(refl))
        eps = 1e-4  # central differences: truncation error ~eps², rounding ~1e-16 * |loss| / eps
        for i in (0, 15, 30):
            e = np.zeros(31)
            e[i] = eps
            fd = (loss(refl + e) - loss(refl - e)) / (2 * eps)
            np.testing.assert_allclose(grad[i], fd, rtol=1e-6)


class TestBadInput:
    def test_wrong_band_count(self):
        with pytest.raises(ValueError, match=r"refl: expected shape \(\.\.\., 31\).*got \(4, 16\)"):
            sj.reflectance_to_xyz(np.zeros((4, 16)))

    def test_scalar(self):
        with pytest.raises(ValueError, match="refl"):
            sj.reflectance_to_lab(0.5)

    def test_unknown_illuminant(self):
        with pytest.raises(ValueError, match=r"illuminant: unknown illuminant 'D50'; expected one of"):
            sj.reflectance_to_xyz(np.zeros(31), "D50")

    def test_unknown_observer(self):
        with pytest.raises(ValueError, match=r"observer: unknown observer '2 degree'"):
            sj.reflectance_to_lab(np.zeros(31), observer="2 degree")

    def test_xyz_wrong_last_axis(self):
        with pytest.raises(ValueError, match=r"xyz: expected shape \(\.\.\., 3\)"):
            sj.xyz_to_lab(np.zeros((5, 4)), np.ones(3))

    def test_white_wrong_shape(self):
        with pytest.raises(ValueError, match=r"white_xyz: expected shape \(\.\.\., 3\).*got \(2,\)"):
            sj.xyz_to_lab(np.zeros((5, 3)), np.ones(2))

    def test_white_not_broadcastable(self):
        with pytest.raises(ValueError, match=r"white_xyz: shape \(4, 3\) does not broadcast to xyz's shape \(5, 3\)"):
            sj.xyz_to_lab(np.zeros((5, 3)), np.ones((4, 3)))

    def test_not_an_array(self):
        with pytest.raises(ValueError, match="refl: expected an array"):
            sj.reflectance_to_xyz({"a": 1})
