"""Test configuration: float64 available, strict dtype promotion, shared fixtures.

x64 is switched on so every kernel can be tested in float32 and float64 side by side (float32
inputs stay float32 under x64). Strict promotion turns any implicit uint16 -> float or
float32 -> float64 mixing inside spherejax into an error, so dtype handling is explicit.
"""

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

import numpy as np  # noqa: E402
import pytest  # noqa: E402


@pytest.fixture(params=[np.float32, np.float64], ids=["float32", "float64"])
def dtype(request):
    """Each test using it runs in float32 and float64."""
    return request.param


@pytest.fixture(params=[False, True], ids=["eager", "jit"])
def maybe_jit(request):
    """Wrap a function in jax.jit (static keyword arguments allowed) or leave it as is."""
    if not request.param:
        return lambda fn, **static: fn

    def wrap(fn, static_argnames=()):
        return jax.jit(fn, static_argnames=static_argnames)

    return wrap
