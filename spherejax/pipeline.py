"""The public functions of a correction: `correct`, `plan`, `patch_ratio`, `patch_ratio_u`.

    raw (H, W, B) uint16 or float
      -> quality mask (saturated, non-finite, white <= dark, below dark; `spherejax.quality`)
      -> v = flat field (Eq. 10)            with the calibration's dark frame and white standard
      -> p = white-patch ratio (Eq. 14-15)  over the calibration's patch mask (or weights), usable
                                            pixels only
      -> v_check = p v (Stage I, Eq. 16-17)
      -> v_tilde = Stage II (Eq. 23)
      -> reflectance = W v_tilde + r0 (+ A k(v_tilde), the kernel residual E8), 16 -> 31
      -> Lab under the calibration's illuminant (ASTM E308 XYZ, perfect-diffuser white)

Bad pixels never raise: they become NaN in every output and carry bits in `quality`. Shapes and
configuration are checked here, before tracing, and raise ValueError naming the argument.

Two steps, so that an image too large for memory can be corrected in strips with the same
compiled code (`spherejax.stripwise`): `patch_ratio` reads only the white patch's bounding box,
and the per-pixel step takes p as an argument. `correct(raw, calibration)` traces both into one
program; `correct(strip, calibration_rows, p=p)` runs the second on rows of an image with the
whole image's p, and gives the same numbers bit for bit as the whole-image call (tested).

Where things live: the types below the engine (`spherejax.calibration.Calibration`,
`spherejax.quality.Quality`, `spherejax.correction_result.CorrectionResult`), the equations in
jax.numpy (`spherejax.equations`), and how a correction runs in the private engine
(`spherejax._engine`): `correct` checks its arguments and hands them to the calibration's plan for
the frames' shape and dtype (`spherejax._engine.plan`), which chose its per-pixel kernel when it
was made (`spherejax._engine.kernels`) and decides the route of every call.
"""

from __future__ import annotations

import jax
import numpy as np

from . import _checks, uncertainty
from ._engine.plan import plan_for
from .calibration import PARAMETERS, Calibration, patch_bounding_box
from .correction_result import CorrectionResult, delta_e_map
from .quality import (
    BELOW_DARK_LIMIT,
    QUALITY_BELOW_DARK,
    QUALITY_NONFINITE,
    QUALITY_NOT_COVERED,
    QUALITY_PATCH_UNUSABLE,
    QUALITY_SATURATED,
    QUALITY_WHITE_NOT_ABOVE_DARK,
    Quality,
)


#: The frame dtypes a plan takes (`plan`): the integer counts and floats JAX represents. Others
#: are refused: float128 (long double) has no JAX type, and complex frames mean nothing here.
SUPPORTED_DTYPES = ("uint8", "uint16", "uint32", "uint64", "int8", "int16", "int32", "int64", "float16", "float32",
                    "float64")


def _check_calibration(calibration) -> None:
    if not isinstance(calibration, Calibration):
        raise ValueError(
            f"calibration: expected a spherejax.Calibration, got {type(calibration).__name__}"
        )


def _check_raw(raw, calibration: Calibration, what: str):
    """raw checked against the calibration's frames: a jax.Array, or a NumPy array left as it is
    (the plan reads NumPy frames where they lie or stages them into reused memory: which, is its
    route's business, `spherejax._engine.plan`)."""
    if isinstance(raw, np.ndarray) and raw.dtype == jax.dtypes.canonicalize_dtype(raw.dtype):
        _checks.require_real("raw", raw)
        _checks.require_representable("raw", raw)
    else:
        raw = _checks.as_array("raw", raw)
    if raw.ndim < 3:
        raise ValueError(f"raw: expected shape (H, W, B) or (..., H, W, B), got {tuple(raw.shape)}")
    expected = (*calibration.image_shape, calibration.bands)
    if tuple(raw.shape[-3:]) != expected:
        raise ValueError(f"raw: expected frames of shape {expected} ({what}), got {tuple(raw.shape)}")
    if not (np.issubdtype(raw.dtype, np.integer) or np.issubdtype(raw.dtype, np.floating)):
        raise ValueError(f"raw: expected integer counts or floats, got dtype {raw.dtype}")
    return raw


def _prepared(raw, calibration: Calibration):
    """The calibration's plan for raw's shape and dtype (`spherejax._engine.plan.plan_for`)."""
    return plan_for(calibration, raw.shape, raw.dtype)


def patch_ratio(raw, calibration: Calibration) -> jax.Array:
    """The white-patch ratio p (Eq. 14-15) of whole frames, from the patch's pixels only.

    Pixels of the patch that are saturated, not finite or whose white is not above dark are left
    out; a band with no usable pixel gives NaN (and `correct` then flags the whole image).

    Args:
      raw: (H, W, B) or (..., H, W, B), uint16 counts or float, the calibration's size; or only
        the patch's bounding box of it, (..., r1 - r0, c1 - c0, B), with `calibration` cropped
        to the same box (what an out-of-core reader passes: `Calibration.patch_box`).
      calibration: a `Calibration` with a patch.

    Returns:
      p, (..., B), in the dtype `correct` computes in.
    """
    _check_calibration(calibration)
    if calibration.patch is None:
        raise ValueError("calibration: has no patch (rows of a calibration): p needs the whole one")
    raw = _check_raw(raw, calibration, "the calibration's H, W, B")
    # Only the patch's bounding box is read: the ratio then costs nothing next to the per-pixel
    # path. Pixels of weight 0 in the box add nothing to it, so the crop is exact.
    return _prepared(raw, calibration).patch_ratio(raw)


def patch_ratio_u(raw, calibration: Calibration, noise) -> jax.Array:
    """The standard uncertainty of `patch_ratio(raw, calibration)`, (..., B), under a
    `NoiseModel` (`uncertainty.patch_ratio_std`): what `correct(strip, rows, p=, p_u=, noise=)`
    needs for strips of an image."""
    _check_calibration(calibration)
    if calibration.patch is None:
        raise ValueError("calibration: has no patch (rows of a calibration): u(p) needs the whole one")
    raw = _check_raw(raw, calibration, "the calibration's H, W, B")
    noise = uncertainty.check_noise(noise, calibration.bands)
    if noise is None:
        raise ValueError("noise: expected a spherejax.NoiseModel, got None")
    return _prepared(raw, calibration).patch_ratio_u(raw, noise)


def plan(calibration: Calibration, shape, *, dtype=np.uint16):
    """Prepare the correction of frames of `shape` and `dtype` with `calibration`, once.

    `correct(raw, calibration)` does this itself at its first call for a shape and keeps the plan
    with the calibration; call `plan` to pay that cost up front (before a batch's timing starts,
    or in a dask worker's set-up), or to hold the plan and call it directly. The plan holds the
    calibration's arrays cast to the compute dtype on the device they are on, the tristimulus
    weights, the white patch's box, the (H, W) flat-field mask, the route its calls take and,
    on CPU, the compiled program that writes into reused output memory.

    Args:
      calibration: a `Calibration` (rows of one need `p` at every call).
      shape: the frames' shape, (H, W, B) or (..., H, W, B), with the calibration's H, W, B.
      dtype: the frames' dtype, one of `SUPPORTED_DTYPES`: integer counts (uint16 by default) or float.

    Returns:
      A plan: call it as `correct` without the calibration, `plan(raw, p=None,
      intermediates=False, noise=None, p_u=None)`, with frames of that shape and dtype; it also
      has `patch_ratio(raw)` and `patch_ratio_u(raw, noise)`. The numbers are `correct`'s, bit
      for bit.

    Raises:
      ValueError: not a Calibration, a shape that is not the calibration's frames, or a dtype
        not in `SUPPORTED_DTYPES`.
    """
    _check_calibration(calibration)
    try:
        shape = tuple(int(n) for n in shape)
    except (TypeError, ValueError):
        raise ValueError(f"shape: expected a tuple of ints (..., H, W, B), got {shape!r}") from None
    expected = (*calibration.image_shape, calibration.bands)
    if len(shape) < 3 or shape[-3:] != expected or min(shape) < 0:
        raise ValueError(f"shape: expected (H, W, B) or (..., H, W, B) with H, W, B = {expected}, got {shape}")
    try:
        dtype = np.dtype(dtype)
    except TypeError:
        raise ValueError(f"dtype: expected a NumPy dtype, got {dtype!r}") from None
    if dtype.name not in SUPPORTED_DTYPES:
        raise ValueError(f"dtype: expected integer counts or floats, got {dtype} (supported: {', '.join(SUPPORTED_DTYPES)})")
    return _prepared(jax.ShapeDtypeStruct(shape, dtype), calibration)


def correct(raw, calibration: Calibration, *, p=None, intermediates: bool = False, noise=None, p_u=None) -> CorrectionResult:
    """Correct camera frames into reflectance and CIELAB (flat field -> Stage I -> Stage II ->
    Wiener -> Lab), jitted.

    Args:
      raw: sample frames, (H, W, B) or (..., H, W, B), uint16 counts or float, same exposure as
        the calibration's white standard.
      calibration: a `Calibration` with matching (H, W, B); rows of one (`Calibration.rows`)
        when `raw` holds those rows of an image.
      p: the white-patch ratio (B,) or (..., B) of the whole image(s) (`patch_ratio`); None =
        computed here from `raw`, which then must be whole frames.
      intermediates: also return v, v_stage1 and v_stage2 (costs three more (H, W, B) cubes).
      noise: a `spherejax.NoiseModel`: the result then also carries reflectance_u, lab_u,
        lab_covariance and p_u, standard uncertainties by first-order propagation through this
        same path (`spherejax.uncertainty`; the sample's, dark and white frames' noise, p's, and
        the model's systematic terms). None (default): nothing of it is computed.
      p_u: with `p` and `noise`, the standard uncertainty of that p (`patch_ratio_u` of the
        whole image).

    Returns:
      `CorrectionResult`: reflectance (..., H, W, 31), lab (..., H, W, 3), quality (..., H, W),
      p (..., B), if asked the intermediates, and with `noise` the uncertainties. float32 unless
      the calibration is float64.

    The work is prepared once per calibration and frame shape (`plan`) and kept with the
    calibration, so the first call of a shape costs more than the next ones.
    """
    _check_calibration(calibration)
    what = "the calibration's H, W, B" if calibration.patch is not None else "the calibration rows' H, W, B"
    raw = _check_raw(raw, calibration, what)
    intermediates = bool(intermediates)
    noise = uncertainty.check_noise(noise, calibration.bands)
    if p is None:
        if calibration.patch is None:
            raise ValueError(
                "p: expected the whole image's white-patch ratio with rows of a calibration "
                "(patch_ratio of the whole image), got None"
            )
        if p_u is not None:
            raise ValueError("p_u: expected None without p (u(p) is computed with p from the patch)")
        return _prepared(raw, calibration)(raw, intermediates=intermediates, noise=noise)
    p = _checks.as_array("p", p)
    bands = calibration.bands
    _checks.require_last_axis("p", p, bands, f"one ratio per band, B = {bands}")
    _checks.require_shape("p", p, (*raw.shape[:-3], bands), "one ratio per band of each image")
    if noise is not None:
        if p_u is None:
            raise ValueError("p_u: expected u(p) (patch_ratio_u of the whole image) with p and noise, got None")
        p_u = _checks.as_array("p_u", p_u)
        _checks.require_shape("p_u", p_u, p.shape, "one standard uncertainty per ratio, like p")
    elif p_u is not None:
        raise ValueError("p_u: expected None without noise (u(p) is used only with a NoiseModel)")
    return _prepared(raw, calibration)(raw, p=p, intermediates=intermediates, noise=noise, p_u=p_u)


__all__ = [
    "Quality",
    "SUPPORTED_DTYPES",
    "PARAMETERS",
    "QUALITY_SATURATED",
    "QUALITY_NONFINITE",
    "QUALITY_WHITE_NOT_ABOVE_DARK",
    "QUALITY_PATCH_UNUSABLE",
    "QUALITY_BELOW_DARK",
    "QUALITY_NOT_COVERED",
    "BELOW_DARK_LIMIT",
    "Calibration",
    "CorrectionResult",
    "correct",
    "plan",
    "patch_ratio",
    "patch_ratio_u",
    "patch_bounding_box",
    "delta_e_map",
]
