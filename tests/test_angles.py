"""spherejax.angles: sin, cos and atan2 in degrees against numpy, in float32 and float64."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spherejax import angles

from .helpers import ulp_bound

#: Largest error allowed, in units in the last place of the exact value's dtype (see the module).
ULP = {np.float32: 2.0, np.float64: 4.0}
#: atan2 rounds three more times (to degrees, + 45, mirrored into its octant) in float32. On a
#: GPU float32 measured 3.28 ulp (an H200, jax 0.11.2), the reduced ratio's division being a
#: reciprocal and a multiply there (XLA's GPU float32 division): 3.5 on any backend but the CPU.
ULP_ATAN2 = {np.float32: ulp_bound(cpu=3.0, gpu=3.5), np.float64: 4.0}


def ulp_error(got, exact, dtype):
    """|got - exact| in ulp of `exact` rounded to `dtype`, with exact computed in float64."""
    scale = np.spacing(np.maximum(np.abs(exact), np.finfo(dtype).tiny).astype(dtype)).astype(np.float64)
    return np.abs(np.asarray(got, np.float64) - exact) / scale


def exact_sincos(degrees):
    """sin and cos in float64 from an exact reduction to [-45, 45] degrees (numpy's own sin of
    radians(x) is off by ~1e-16 absolute at multiples of 180)."""
    x = np.asarray(degrees, np.float64)
    q = np.round(x / 90.0)
    r = np.radians(x - 90.0 * q)
    s, c = np.sin(r), np.cos(r)
    k = np.mod(q, 4)
    sin = np.select([k == 0, k == 1, k == 2, k == 3], [s, c, -s, -c])
    cos = np.select([k == 0, k == 1, k == 2, k == 3], [c, -s, -c, s])
    return sin, cos


class TestSinCos:
    def test_against_numpy(self, dtype):
        rng = np.random.default_rng(0)
        x = np.concatenate([
            rng.uniform(-720, 720, 200_000), np.arange(-720, 721, 15.0), rng.uniform(0, 60, 10_000),
        ]).astype(dtype)
        sin, cos = angles.sincos_degrees(jnp.asarray(x))
        assert sin.dtype == dtype and cos.dtype == dtype
        exact_sin, exact_cos = exact_sincos(x)
        # Near a zero the error is measured in the ulp of the value's scale, not of ~0.
        assert np.max(np.abs(np.asarray(sin, np.float64) - exact_sin)) <= ULP[dtype] * np.finfo(dtype).eps
        assert np.max(np.abs(np.asarray(cos, np.float64) - exact_cos)) <= ULP[dtype] * np.finfo(dtype).eps
        away = np.abs(exact_sin) > 0.01
        assert np.max(ulp_error(np.asarray(sin)[away], exact_sin[away], dtype)) <= ULP[dtype]

    def test_exact_at_right_angles(self, dtype):
        x = jnp.asarray([0.0, 90.0, 180.0, 270.0, 360.0, -90.0, -180.0], dtype)
        sin, cos = angles.sincos_degrees(x)
        np.testing.assert_array_equal(np.asarray(sin), [0, 1, 0, -1, 0, -1, 0])
        np.testing.assert_array_equal(np.asarray(cos), [1, 0, -1, 0, 1, 0, -1])

    def test_nan_propagates(self, dtype):
        sin, cos = angles.sincos_degrees(jnp.asarray([np.nan], dtype))
        assert np.isnan(np.asarray(sin)).all() and np.isnan(np.asarray(cos)).all()

    def test_gradient_is_cos(self):
        x = jnp.linspace(-400.0, 400.0, 1601)
        grad = jax.vmap(jax.grad(angles.sin_degrees))(x)
        np.testing.assert_allclose(np.asarray(grad), np.pi / 180 * np.cos(np.radians(np.asarray(x))), atol=1e-15)


class TestAtan2:
    def test_against_numpy(self, dtype):
        rng = np.random.default_rng(1)
        y = rng.normal(0, 50, 200_000).astype(dtype)
        x = rng.normal(0, 50, 200_000).astype(dtype)
        # the octant and axis boundaries, both signs, and very unequal magnitudes
        edges = np.array([1.0, -1.0, 0.0, 2.0, -3.0, 1e-6, -1e-6, 1e4], dtype)
        y = np.concatenate([y, np.repeat(edges, edges.size)])
        x = np.concatenate([x, np.tile(edges, edges.size)])
        got = np.asarray(angles.atan2_degrees(jnp.asarray(y), jnp.asarray(x)))
        assert got.dtype == dtype
        exact = np.degrees(np.arctan2(y.astype(np.float64), x.astype(np.float64)))
        at_origin = (x == 0) & (y == 0)
        assert np.all(got[at_origin] == 0)
        exact, got = exact[~at_origin], got[~at_origin]
        assert np.max(np.abs(got - exact)) <= ULP_ATAN2[dtype] * np.spacing(np.asarray(180.0, dtype))
        away = np.abs(exact) > 1.0
        assert np.max(ulp_error(got[away], exact[away], dtype)) <= ULP_ATAN2[dtype]

    @pytest.mark.parametrize("y, x, expected", [
        (0.0, 1.0, 0.0), (1.0, 1.0, 45.0), (1.0, 0.0, 90.0), (1.0, -1.0, 135.0), (0.0, -1.0, 180.0),
        (-1.0, -1.0, -135.0), (-1.0, 0.0, -90.0), (-1.0, 1.0, -45.0),
    ])
    def test_exact_on_the_octant_boundaries(self, dtype, y, x, expected):
        got = angles.atan2_degrees(jnp.asarray(y, dtype), jnp.asarray(x, dtype))
        assert float(got) == expected

    def test_nan_propagates(self, dtype):
        got = angles.atan2_degrees(jnp.asarray([np.nan, 1.0], dtype), jnp.asarray([1.0, np.nan], dtype))
        assert np.isnan(np.asarray(got)).all()

    def test_gradient(self):
        rng = np.random.default_rng(2)
        y, x = jnp.asarray(rng.normal(size=500)), jnp.asarray(rng.normal(size=500))
        dy, dx = jax.vmap(jax.grad(angles.atan2_degrees, argnums=(0, 1)))(y, x)
        r2 = np.asarray(x) ** 2 + np.asarray(y) ** 2
        np.testing.assert_allclose(np.asarray(dy), np.degrees(np.asarray(x) / r2), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(dx), np.degrees(-np.asarray(y) / r2), rtol=1e-12)


def test_value_and_gradient_at_the_origin_are_finite(dtype):
    """0 at the origin, with a finite gradient (one-sided: the origin has no derivative), where
    jnp.arctan2's gradient is 0/0; CIEDE2000 relies on it for colours of zero chroma."""
    zero = jnp.asarray(0.0, dtype)
    assert float(angles.atan2_degrees(zero, zero)) == 0.0
    grad = jax.grad(angles.atan2_degrees, argnums=(0, 1))(zero, zero)
    assert all(np.isfinite(float(g)) for g in grad)
