"""CIEDE2000: Sharma, Wu, Dalal (2005), colour-science as an oracle, gradients, properties."""

import colour
import hypothesis.extra.numpy as hnp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import spherejax as sj

from .helpers import sharma_pairs


class TestSharma2005:
    def test_all_34_pairs_float64(self):
        """Sharma et al. (2005) Table 1, published to 4 decimals: within 1e-4 in float64."""
        pairs, lab1, lab2, expected = sharma_pairs()
        assert len(pairs) == 34
        np.testing.assert_allclose(np.asarray(sj.delta_e_2000(lab1, lab2)), expected, rtol=0, atol=1e-4)

    def test_all_34_pairs_float32(self):
        """float32 also reproduces all 34 pairs to 1e-4, pairs 13-15 at the 180° hue
        discontinuity included.

        Why: in those pairs |h1' - h2'| differs from 180° by about 0.002-0.03°, while float32
        resolves hue angles between 256° and 512° to one ulp = 2**-15 ° = 3.05e-5°. Every branch
        of Sharma's Eq. 10 and 14 is therefore decided as in float64. Where |h1' - h2'| is within
        a few ulps of 180° float32 cannot decide the branch; see
        `test_float32_at_the_exact_discontinuity` for what happens there.
        """
        _, lab1, lab2, expected = sharma_pairs()
        de = sj.delta_e_2000(lab1.astype(np.float32), lab2.astype(np.float32))
        assert de.dtype == np.float32
        np.testing.assert_allclose(np.asarray(de), expected, rtol=0, atol=1e-4)

    def test_symmetric(self):
        _, lab1, lab2, _ = sharma_pairs()
        np.testing.assert_allclose(
            np.asarray(sj.delta_e_2000(lab1, lab2)), np.asarray(sj.delta_e_2000(lab2, lab1)), atol=1e-12
        )

    @pytest.mark.parametrize("chroma, jump", [(2.49, 0.042), (40.0, 2.57)])
    def test_float32_at_the_exact_discontinuity(self, chroma, jump):
        """ΔE00 is discontinuous where |h1' - h2'| = 180°: the mean hue h̄' jumps by 180° (Eq. 14),
        which changes T and Δθ. For complementary colours (chroma, ±0.01) vs (-chroma, ∓0.01 (1+d))
        float64 sees the side of the discontinuity that d puts it on; float32 rounds the hue
        difference to 180° ± 1 ulp and may pick either side. Its answer is always one of the two
        one-sided float64 limits, never something in between, and the two limits differ by
        `jump`. At d = 0 exactly the colours are opposite, which `delta_e_2000` decides from
        a', b rather than from the rounded hue angles: both dtypes take Eq. 14's first case.
        """
        def pair(d):
            return np.array([50.0, chroma, -0.01]), np.array([50.0, -chroma, 0.01 * (1.0 + d)])

        below = float(sj.delta_e_2000(*pair(-1e-9)))
        above = float(sj.delta_e_2000(*pair(+1e-9)))
        assert abs(above - below) == pytest.approx(jump, abs=0.01)
        for d in (-1e-9, 0.0, 1e-9):
            lab1, lab2 = pair(d)
            f32 = float(sj.delta_e_2000(lab1.astype(np.float32), lab2.astype(np.float32)))
            assert min(abs(f32 - below), abs(f32 - above)) < 1e-5 * above
        lab1, lab2 = pair(0.0)
        f64 = float(sj.delta_e_2000(lab1, lab2))
        assert float(sj.delta_e_2000(lab1.astype(np.float32), lab2.astype(np.float32))) == pytest.approx(f64, rel=1e-5)
        # Away from the discontinuity by 1e-4 relative (~0.0001° of hue) float32 agrees again.
        for d in (-1e-3, 1e-3):
            lab1, lab2 = pair(d)
            f64 = float(sj.delta_e_2000(lab1, lab2))
            f32 = float(sj.delta_e_2000(lab1.astype(np.float32), lab2.astype(np.float32)))
            assert f32 == pytest.approx(f64, rel=1e-6)


def test_exactly_opposite_hues_take_the_unwrapped_branch():
    """|h1' - h2'| = 180° exactly (Sharma's pair 14 is one): Eq. 10 and 14 take their first
    case, whatever side of 180° the two separately rounded hue angles land on. Decided from the
    rounded angles, float32 and float64 would disagree, by the jump of the test above, on the
    pairs whose angles round to opposite sides; decided from a', b they agree on all 500."""
    rng = np.random.default_rng(5)
    L = rng.uniform(10, 90, 500)
    a, b = rng.uniform(-60, 60, 500), rng.uniform(-60, 60, 500)
    lab1 = np.stack([L, a, b], -1)
    lab2 = np.stack([L + rng.normal(0, 2, 500), -a, -b], -1)
    f64 = np.asarray(sj.delta_e_2000(lab1, lab2))
    f32 = np.asarray(sj.delta_e_2000(lab1.astype(np.float32), lab2.astype(np.float32)))
    np.testing.assert_allclose(f32, f64, rtol=2e-5)
    np.testing.assert_allclose(f64, np.asarray(sj.delta_e_2000(lab2, lab1)), rtol=1e-12)


class TestAgainstColourScience:
    def test_random_pairs(self, dtype):
        rng = np.random.default_rng(7)
        lab1 = np.column_stack([rng.uniform(0, 100, 2000), rng.uniform(-100, 100, (2000, 2))])
        lab2 = lab1 + rng.normal(0, rng.choice([0.5, 5, 50], (2000, 1)), (2000, 3))
        ours = np.asarray(sj.delta_e_2000(lab1.astype(dtype), lab2.astype(dtype)))
        theirs = colour.delta_E(lab1, lab2, method="CIE 2000")
        tolerance = {np.float32: 2e-4, np.float64: 1e-10}[dtype]
        # float32 may pick the other side of the 180° hue discontinuity for a pair whose hue
        # difference is within an ulp of 180° (see TestSharma2005); none of these pairs is.
        np.testing.assert_allclose(ours, theirs, rtol=tolerance, atol=tolerance)

    def test_neutral_and_black(self):
        lab1 = np.array([[0, 0, 0], [50, 0, 0], [50, 0, 0], [100, 0, 0], [0, 0, 0]], float)
        lab2 = np.array([[0, 0, 0], [60, 0, 0], [50, 3, 0], [100, 0, -4], [1, 1, 1]], float)
        np.testing.assert_allclose(
            np.asarray(sj.delta_e_2000(lab1, lab2)), colour.delta_E(lab1, lab2, method="CIE 2000"), atol=1e-10
        )

    def test_parametric_factors(self):
        lab1, lab2 = np.array([50.0, 20.0, -10.0]), np.array([55.0, 25.0, -5.0])
        ours = float(sj.delta_e_2000(lab1, lab2, k_L=2.0, k_C=1.0, k_H=1.0))
        theirs = float(colour.difference.delta_E_CIE2000(lab1, lab2, textiles=True))  # k_L = 2
        assert ours == pytest.approx(theirs, rel=1e-10)


class TestShapes:
    def test_broadcasting(self):
        rng = np.random.default_rng(2)
        lab1 = rng.uniform(0, 60, (5, 1, 3))
        lab2 = rng.uniform(0, 60, (4, 3))
        de = np.asarray(sj.delta_e_2000(lab1, lab2))
        assert de.shape == (5, 4)
        assert de[3, 2] == pytest.approx(float(sj.delta_e_2000(lab1[3, 0], lab2[2])), rel=1e-12)

    def test_jit_matches_eager(self, maybe_jit):
        _, lab1, lab2, expected = sharma_pairs()
        np.testing.assert_allclose(np.asarray(maybe_jit(sj.delta_e_2000)(lab1, lab2)), expected, atol=1e-4)

    def test_vmap(self):
        _, lab1, lab2, expected = sharma_pairs()
        np.testing.assert_allclose(np.asarray(jax.vmap(sj.delta_e_2000)(lab1, lab2)), expected, atol=1e-4)


class TestNonFinite:
    @pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
    @pytest.mark.parametrize("position", [0, 1, 2])
    def test_sweep(self, value, position):
        lab1 = np.array([[50.0, 10.0, 10.0], [50.0, 10.0, 10.0]])
        lab2 = np.array([[52.0, 12.0, 9.0], [52.0, 12.0, 9.0]])
        lab1[0, position] = value
        de = np.asarray(sj.delta_e_2000(lab1, lab2))
        assert np.isnan(de[0]) or np.isinf(de[0])  # never a plausible finite number
        assert np.isfinite(de[1])


GRADIENT_CASES = {
    "identical pair (ΔE00 = 0)": ([50.0, 20.0, -30.0], [50.0, 20.0, -30.0]),
    "identical neutrals": ([50.0, 0.0, 0.0], [50.0, 0.0, 0.0]),
    "zero chroma vs chromatic": ([50.0, 0.0, 0.0], [55.0, 3.0, -2.0]),
    "both zero chroma": ([40.0, 0.0, 0.0], [60.0, 0.0, 0.0]),
    "black vs black": ([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
    "black vs grey": ([0.0, 0.0, 0.0], [10.0, 0.0, 0.0]),
    "hue at +180°": ([50.0, -20.0, 0.0], [50.0, -25.0, 1.0]),
    "hue at -180°": ([50.0, -20.0, -0.0], [50.0, -25.0, -1.0]),
    "hue difference of 180°": ([50.0, 20.0, 0.0], [50.0, -20.0, 0.0]),
    "Sharma pair 13": ([50.0, 2.49, -0.001], [50.0, -2.49, 0.0009]),
}


#: Jitted once at module level, so that all cases of one dtype share one compilation (a jax.jit
#: made inside the test would be a new function, compiled again, for every case).
_grad_delta_e = jax.jit(jax.grad(sj.delta_e_2000, argnums=(0, 1)))
_jacrev_delta_e = jax.jit(jax.jacrev(sj.delta_e_2000))


class TestGradients:
    @pytest.mark.parametrize("case", list(GRADIENT_CASES))
    def test_grad_and_jacrev_finite(self, case, dtype):
        lab1, lab2 = (jnp.asarray(x, dtype=dtype) for x in GRADIENT_CASES[case])
        g1, g2 = _grad_delta_e(lab1, lab2)
        assert np.all(np.isfinite(np.asarray(g1))) and np.all(np.isfinite(np.asarray(g2)))
        batch1, batch2 = jnp.stack([lab1, lab2]), jnp.stack([lab2, lab1])
        jac = _jacrev_delta_e(batch1, batch2)
        assert jac.shape == (2, 2, 3) and np.all(np.isfinite(np.asarray(jac)))

    def test_gradient_matches_finite_differences(self):
        lab1, lab2 = np.array([45.0, 12.0, -33.0]), np.array([47.0, 18.0, -29.0])
        grad = np.asarray(jax.grad(sj.delta_e_2000)(jnp.asarray(lab1), jnp.asarray(lab2)))
        eps = 1e-6
        for i in range(3):
            e = np.zeros(3)
            e[i] = eps
            fd = (float(sj.delta_e_2000(lab1 + e, lab2)) - float(sj.delta_e_2000(lab1 - e, lab2))) / (2 * eps)
            assert grad[i] == pytest.approx(fd, rel=1e-6, abs=1e-9)


lab_values = hnp.arrays(
    np.float64,
    (3,),
    elements=st.floats(-128, 128, allow_nan=False).map(float),
).map(lambda x: np.array([abs(x[0]) % 100.0, x[1], x[2]]))


class TestProperties:
    @settings(max_examples=200, deadline=None)
    @given(lab1=lab_values, lab2=lab_values)
    def test_symmetric_non_negative_zero_on_identity(self, lab1, lab2):
        d12 = float(sj.delta_e_2000(lab1, lab2))
        d21 = float(sj.delta_e_2000(lab2, lab1))
        assert d12 >= 0.0
        assert d12 == pytest.approx(d21, rel=1e-9, abs=1e-9)
        assert float(sj.delta_e_2000(lab1, lab1)) == 0.0


class TestBadInput:
    def test_wrong_last_axis(self):
        with pytest.raises(ValueError, match=r"lab1: expected shape \(\.\.\., 3\).*got \(4,\)"):
            sj.delta_e_2000(np.zeros(4), np.zeros(3))

    def test_not_broadcastable(self):
        with pytest.raises(ValueError, match=r"lab1, lab2: shapes \(2, 3\) and \(5, 3\) do not broadcast"):
            sj.delta_e_2000(np.zeros((2, 3)), np.zeros((5, 3)))
