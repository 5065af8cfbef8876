"""The colour targets every fit takes, responses V (n, B) and reflectances R (n, 31): the checks
of the fitting functions' arguments, and the weighted moments through which each fit sees them.

Every fit takes per-target weights w (n,) in {0, 1}, so that the folds of a cross-validation are
the same computation with other weights (vmapped, one compilation); `_weighted_centre` is that
weighting of the targets' means.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .. import _checks
from ..grid import N_WAVELENGTHS

def _check_training(responses, reflectances):
    responses = _checks.as_array("responses", responses)
    reflectances = _checks.as_array("reflectances", reflectances)
    if responses.ndim != 2:
        raise ValueError(
            f"responses: expected shape (n, B) (targets, bands), got {tuple(responses.shape)}"
        )
    _checks.require_shape(
        "reflectances",
        reflectances,
        (responses.shape[0], N_WAVELENGTHS),
        "one 400..700 nm spectrum per target, same n as responses",
    )
    if responses.shape[0] < 2:
        raise ValueError(
            f"responses: {responses.shape[0]} target(s) cannot train a Wiener matrix; expected "
            "at least 2 (the paper uses 144)"
        )
    dtype = _checks.float_dtype(responses, reflectances)
    return responses.astype(dtype), reflectances.astype(dtype)


def _check_sensitivity(sensitivity, V):
    """A known sensitivity M as an array (B, 31) in V's dtype, for responses V (n, B)."""
    M = _checks.as_array("sensitivity", sensitivity)
    _checks.require_shape("sensitivity", M, (V.shape[1], N_WAVELENGTHS), "bands of responses x 31 wavelengths")
    return M.astype(V.dtype)


def _check_noise_variance(noise_variance):
    if _checks.is_concrete(noise_variance) and not float(noise_variance) >= 0:
        raise ValueError(f"noise_variance: expected a value >= 0, got {noise_variance!r}")


def _check_determined(V, R, what: str) -> None:
    """Refuse targets that cannot determine an estimator (concrete data only): non-finite
    values, or responses or reflectances that do not vary."""
    if not (_checks.is_concrete(V) and _checks.is_concrete(R)):
        return
    V_np, R_np = np.asarray(V), np.asarray(R)
    for name, x in (("responses", V_np), ("reflectances", R_np)):
        bad = ~np.isfinite(x)
        if bad.any():
            row = int(np.argwhere(bad)[0][0])
            raise ValueError(f"{name}: target {row} has a non-finite value; expected finite {what} data")
    if not np.any(np.ptp(V_np, axis=0) > 0):
        raise ValueError(
            f"responses: all {V_np.shape[0]} targets give the same response; expected targets of "
            f"different colours to fit {what}"
        )
    if not np.any(np.ptp(R_np, axis=0) > 0):
        raise ValueError(
            f"reflectances: all {R_np.shape[0]} targets have the same reflectance; expected targets "
            f"of different colours to fit {what}"
        )


def _weighted_centre(X, w):
    """(mean (d,), centred rows scaled by sqrt(w) (n, d)) of X (n, d) under weights w (n,)."""
    mean = jnp.sum(w[:, None] * X, axis=0) / jnp.sum(w)
    return mean, (X - mean) * jnp.sqrt(w)[:, None]
