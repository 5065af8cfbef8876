"""Trace-time argument checks shared by the kernels.

Every check raises ValueError naming the argument, what it got and what was expected, so that a
wrong shape fails before any computation (and at trace time under jit) instead of broadcasting
into a silently wrong answer. Value checks never live here: per-pixel paths do not raise on data.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def as_array(name: str, x) -> jax.Array:
    """`jnp.asarray(x)`, turning a conversion failure into a ValueError naming `name`, and
    refusing what the conversion would silently change: complex values (`require_real`) and
    float64 values beyond float32's range when JAX computes in float32 (`require_representable`)."""
    if isinstance(x, jax.Array):  # already one (a tracer too): nothing to convert
        require_real(name, x)
        return x
    if isinstance(x, np.ndarray):  # before the conversion, which casts or makes infinities
        require_real(name, x)
        require_representable(name, x)
    try:
        if isinstance(x, np.ndarray) and x.dtype == jax.dtypes.canonicalize_dtype(x.dtype):
            # What jnp.asarray does for such an array, at half the time: it measured 5.1 ms
            # against 2.4 ms for a 32 MB uint16 cube, the raw input of every correction.
            return jax.device_put(x)
        array = jnp.asarray(x)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{name}: expected an array, got {type(x).__name__} ({error})") from None
    require_real(name, array)
    return array


def require_real(name: str, x) -> None:
    """Raise if `x` holds complex numbers: every quantity of spherejax is real, and a cast to a
    real dtype would drop the imaginary part without a word."""
    if jnp.iscomplexobj(x):
        raise ValueError(f"{name}: expected real numbers, got {x.dtype} (complex: the imaginary part would be dropped)")


def require_representable(name: str, x: np.ndarray) -> None:
    """Raise if float64 values of `x` would become infinities in the float32 JAX computes in
    by default (float64 off): 1e300 is finite, its float32 is not."""
    if x.dtype != np.float64 or jax.dtypes.canonicalize_dtype(x.dtype) == np.float64 or x.size == 0:
        return
    limit = float(np.finfo(np.float32).max)
    # fmin/fmax skip NaN and make no temporary: one pass over the array, no copy.
    extreme = max(abs(float(np.fmin.reduce(x, axis=None))), abs(float(np.fmax.reduce(x, axis=None))))
    if not extreme > limit:
        return
    if not np.isfinite(extreme):  # infinities (not finite anyway): the largest finite value decides
        finite = np.abs(x[np.isfinite(x)])
        extreme = float(finite.max()) if finite.size else 0.0
    if extreme > limit:
        raise ValueError(
            f"{name}: values up to {extreme:.3g} overflow float32 (largest {limit:.3g}), the precision "
            "JAX computes in by default; rescale them, or enable float64 with "
            "jax.config.update('jax_enable_x64', True)"
        )


def band_array(name: str, x) -> jax.Array:
    """`as_array`, then raise unless `x` has a band axis (..., B)."""
    x = as_array(name, x)
    if x.ndim == 0:
        raise ValueError(f"{name}: expected shape (..., B) with B bands, got a scalar")
    return x


def response_and_ratio(v, p) -> tuple[jax.Array, jax.Array]:
    """Validate a response cube v (..., B) and its white-patch ratio p (broadcastable, (..., B))."""
    v = band_array("v", v)
    p = as_array("p", p)
    bands = v.shape[-1]
    require_last_axis("p", p, bands, f"one ratio per band of v, B = {bands}")
    require_broadcastable("p", p, "v", v.shape)
    return v, p


def float_dtype(*arrays) -> jnp.dtype:
    """The floating dtype a computation on `arrays` runs in.

    float32 unless a floating input is float64 (integer camera counts, e.g. uint16, do not vote):
    docs/design.md, "float32 by default, float64 when the caller passes float64".
    """
    floats = [a.dtype for a in arrays if jnp.issubdtype(a.dtype, jnp.floating)]
    if any(d == jnp.float64 for d in floats):
        return jnp.dtype(jnp.float64)
    return jnp.dtype(jnp.float32)


def require_last_axis(name: str, x, size: int, what: str) -> None:
    """Raise unless `x` has at least one axis and its last axis has `size` entries."""
    if x.ndim == 0 or x.shape[-1] != size:
        raise ValueError(f"{name}: expected shape (..., {size}) ({what}), got {tuple(x.shape)}")


def require_shape(name: str, x, shape: tuple[int, ...], what: str) -> None:
    """Raise unless `x.shape == shape`."""
    if tuple(x.shape) != tuple(shape):
        raise ValueError(f"{name}: expected shape {tuple(shape)} ({what}), got {tuple(x.shape)}")


def require_broadcastable(name: str, x, target_name: str, target_shape: tuple[int, ...]) -> None:
    """Raise unless `x` broadcasts to `target_shape` without enlarging it."""
    try:
        out = np.broadcast_shapes(tuple(x.shape), tuple(target_shape))
    except ValueError:
        out = None
    if out != tuple(target_shape):
        raise ValueError(
            f"{name}: shape {tuple(x.shape)} does not broadcast to {target_name}'s shape "
            f"{tuple(target_shape)}"
        )


def require_bool_mask(name: str, mask, shape: tuple[int, ...]) -> None:
    """Raise unless `mask` is a boolean array of `shape`."""
    if mask.dtype != jnp.bool_:
        raise ValueError(f"{name}: expected a boolean mask, got dtype {mask.dtype}")
    require_shape(name, mask, shape, "one entry per image pixel")


def require_nonempty_mask(name: str, mask) -> None:
    """Raise if a concrete boolean mask selects no pixel; tracers (under jit) pass unchecked."""
    if isinstance(mask, jax.core.Tracer):
        return
    if not bool(np.any(np.asarray(mask))):
        raise ValueError(f"{name}: the mask selects no pixel; expected at least one True entry")


def require_mask_or_weights(name: str, mask, shape: tuple[int, ...]) -> None:
    """Raise unless `mask` is a boolean mask or an array of floating weights >= 0, of `shape`,
    selecting at least one pixel (a nonzero weight).

    Weights make a mask differentiable. Their values are checked only when concrete: under jit,
    grad or vmap they are tracers and pass unchecked, like every value in the per-pixel path.
    """
    if mask.dtype != jnp.bool_ and not jnp.issubdtype(mask.dtype, jnp.floating):
        # Integer masks are refused rather than read as weights: a 0/255 image is a likely
        # mistake, and `mask.astype(bool)` says what was meant.
        raise ValueError(
            f"{name}: expected a boolean mask, got dtype {mask.dtype} (floating weights >= 0 "
            f"are accepted too)"
        )
    require_shape(name, mask, shape, "one entry per image pixel")
    if mask.dtype == jnp.bool_:
        require_nonempty_mask(name, mask)
        return
    if isinstance(mask, jax.core.Tracer):
        return
    weights = np.asarray(mask)
    if not np.all(np.isfinite(weights) & (weights >= 0)):
        bad = weights[~(np.isfinite(weights) & (weights >= 0))]
        raise ValueError(
            f"{name}: expected weights that are finite and >= 0, got {bad.size} that are not "
            f"(first: {bad.flat[0]})"
        )
    if not np.any(weights > 0):
        raise ValueError(f"{name}: the weights select no pixel; expected at least one weight > 0")


def require_finite(name: str, x) -> None:
    """Raise if a concrete `x` holds a NaN or an infinity (tracers, under jit, grad or vmap, pass
    unchecked). For parameters, not per-pixel data: data with NaN is flagged pixel by pixel."""
    if isinstance(x, jax.core.Tracer):
        return
    values = np.asarray(x)
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        index = np.unravel_index(int(bad[0]), values.shape)
        raise ValueError(
            f"{name}: {bad.size} entries are not finite (the first, {values[index]}, at {tuple(int(i) for i in index)}); "
            "expected finite numbers"
        )


def require_plan_frames(raw, shape: tuple[int, ...], dtype) -> None:
    """Raise ValueError, one line, unless raw has a prepared correction's frame shape and dtype
    (`spherejax._engine.plan.Plan`, `spherejax._engine.registered.RegisteredPlan`)."""
    found_shape, found_dtype = tuple(getattr(raw, "shape", ())), getattr(raw, "dtype", None)
    if found_shape != shape or found_dtype != dtype:
        found = f"shape {found_shape} and dtype {found_dtype}" if found_dtype is not None else type(raw).__name__
        raise ValueError(f"raw: expected frames of this plan's shape {shape} and dtype {dtype}, got {found}")


def is_concrete(x) -> bool:
    """True when `x` holds values now (not a tracer inside jit, grad or vmap)."""
    return not isinstance(x, jax.core.Tracer)
