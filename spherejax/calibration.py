"""`Calibration`: everything `correct` needs of an instrument, as a pytree, and what follows
from it alone (its compute dtype, its saturation level, the white patch's bounding box).

Below the engine (`spherejax._engine`) and the public functions (`spherejax.pipeline`), which
both read it. A calibration keeps the plans made for it (`Calibration._plan`), so that every
correction of one input, strip after strip, reuses one plan.
"""

from __future__ import annotations

import dataclasses
import threading

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _checks, colorimetry
from .estimation.kernel_residual import KernelResidual
from .grid import N_WAVELENGTHS

#: The calibration's parameters every pixel goes through: a NaN or infinity in any of them makes
#: every output NaN while the quality flags, which describe pixels, stay 0. Refused when concrete.
PARAMETERS = ("coeffs", "wiener", "wiener_offset")


#: Plans a calibration keeps (`Calibration._plan`): the frame shapes of a batch, a stack and its
#: frames, a few strip heights.
_PLANS_KEPT = 8
#: Crops a calibration keeps (`Calibration._part`): the strips of a large image and a few regions.
_PARTS_KEPT = 256
_plans_lock = threading.Lock()


class Calibration(eqx.Module):
    """Everything `correct` needs, as a pytree (its arrays are leaves; the names are static).

    Fields:
      dark: dark frame, (H, W, B), in raw counts.
      white: white-standard frame, (H, W, B), in raw counts, same exposure as the samples.
      patch: the reference white patch (Eq. 14-15), (H, W): a boolean mask, True on the patch
        (the normal case, and the only one a calibration file stores), or floating weights >= 0
        (0 = not in the patch), so that p, and all that follows, can be differentiated with
        respect to the patch: p is the weighted sum of white-standard signals over the weighted
        sum of sample signals. None for rows of a calibration (`rows`): `correct` then needs
        the whole image's p.
      coeffs: Stage II coefficients (B, 4), ordered c1..c4 (Eq. 23).
      wiener: Wiener matrix W (31, B) (`wiener.fit_wiener`): reflectance per unit of the Stage II
        response.
      illuminant: "D65", "A" or "F2" for Lab.
      observer: colour-matching functions for Lab (`colorimetry.OBSERVERS`).
      saturation: raw level at or above which a pixel counts as saturated; None = the full scale
        of an integer raw dtype (65535 for uint16) and no check for float raw.
      wiener_offset: the estimator's offset r0 (31,), reflectance (dimensionless, 400..700 nm
        step 10): the estimate is r = W v_tilde + r0 (`wiener.fit_wiener`). Default zeros, the
        plain linear Wiener estimate r = W v_tilde.
      wiener_residual: the estimator's kernel residual (`estimation.KernelResidual`, from
        `estimation.fit_kernel_estimator`): the estimate is then r = W v_tilde + r0 + A k(v_tilde)
        (E8). None (default): the affine estimator. Every kernel applies it (the kernel
        contract, `spherejax._engine.kernels`).
      wiener_offset and wiener_residual come last among the fields, so that positional
      construction keeps its meaning.
    """

    dark: jax.Array = eqx.field(converter=jnp.asarray)
    white: jax.Array = eqx.field(converter=jnp.asarray)
    patch: jax.Array | None = eqx.field(converter=lambda x: None if x is None else jnp.asarray(x))
    coeffs: jax.Array = eqx.field(converter=jnp.asarray)
    wiener: jax.Array = eqx.field(converter=jnp.asarray)
    illuminant: str = eqx.field(static=True, default="D65")
    observer: str = eqx.field(static=True, default=colorimetry.DEFAULT_OBSERVER)
    saturation: float | None = eqx.field(static=True, default=None)
    # A factory, not an array default: dataclasses refuse unhashable defaults. float32 zeros
    # promote nothing, so a float64 calibration without an offset still computes in float64.
    wiener_offset: jax.Array = eqx.field(
        converter=jnp.asarray, default_factory=lambda: np.zeros(N_WAVELENGTHS, np.float32)
    )
    wiener_residual: KernelResidual | None = None

    def __check_init__(self):
        # Unknown names raise here, at construction, rather than at the first correction.
        colorimetry.tristimulus_weights(self.illuminant, observer=self.observer)
        # jnp.asarray keeps complex values and a later cast drops their imaginary part; the patch
        # has a dtype check of its own (a boolean mask or real weights).
        for name in ("dark", "white", "coeffs", "wiener", "wiener_offset"):
            _checks.require_real(name, getattr(self, name))
        if self.dark.ndim != 3:
            raise ValueError(f"dark: expected shape (H, W, B), got {tuple(self.dark.shape)}")
        height, width, bands = self.dark.shape
        if 0 in self.dark.shape:
            raise ValueError(f"dark: expected at least one pixel and one band, got shape {tuple(self.dark.shape)}")
        _checks.require_shape("white", self.white, self.dark.shape, "the dark frame's (H, W, B)")
        if self.patch is not None:
            _checks.require_mask_or_weights("patch", self.patch, (height, width))
        _checks.require_shape(
            "coeffs", self.coeffs, (bands, 4), f"c1..c4 for each of the {bands} bands"
        )
        _checks.require_shape(
            "wiener", self.wiener, (N_WAVELENGTHS, bands), f"31 wavelengths x the {bands} bands"
        )
        _checks.require_shape(
            "wiener_offset", self.wiener_offset, (N_WAVELENGTHS,), "one reflectance offset r0 per wavelength, 400..700 nm step 10"
        )
        if self.wiener_residual is not None:
            if not isinstance(self.wiener_residual, KernelResidual):
                raise ValueError(f"wiener_residual: expected an estimation.KernelResidual or None, got {type(self.wiener_residual).__name__}")
            if self.wiener_residual.bands != bands:
                raise ValueError(f"wiener_residual: expected a residual of the {bands} bands, got one of {self.wiener_residual.bands}")
        if self.saturation is not None and not float(self.saturation) > 0:
            raise ValueError(f"saturation: expected a level > 0 or None, got {self.saturation!r}")
        for name in PARAMETERS:
            _checks.require_finite(name, getattr(self, name))

    @property
    def bands(self) -> int:
        return int(self.dark.shape[-1])

    @property
    def image_shape(self) -> tuple[int, int]:
        return int(self.dark.shape[0]), int(self.dark.shape[1])

    @property
    def patch_box(self) -> tuple[int, int, int, int] | None:
        """(row0, row1, col0, col1) bounding the patch (`patch_bounding_box`); None without a
        patch or when the patch is traced.

        Worked out once per calibration (finding it reads the whole mask, about 0.9 ms a
        megapixel): the patch is an immutable jax.Array, so its box cannot change."""
        if self.patch is None or not _checks.is_concrete(self.patch):
            return None
        known = self.__dict__.get("_patch_box")
        if known is None:
            known = (patch_bounding_box(self.patch),)
            object.__setattr__(self, "_patch_box", known)  # a frozen dataclass: its own memo
        return known[0]

    def _plan(self, key: tuple, make):
        """The plan this calibration keeps under `key` (frames' shape, dtype and kernel mode:
        `spherejax._engine.plan.plan_for`), made with `make()` at first use.

        The plans live and die with the calibration (an attribute of the instance, not a field:
        not part of the pytree, not pickled, not copied by `dataclasses.replace` or tree_map,
        whose new calibration gets plans of its own). The last `_PLANS_KEPT` shapes are kept."""
        with _plans_lock:
            plans = self.__dict__.get("_plans")
            if plans is None:
                plans = {}
                object.__setattr__(self, "_plans", plans)
            plan = plans.get(key)
        if plan is None:
            plan = make()  # outside the lock: it may compile
            with _plans_lock:
                plan = plans.setdefault(key, plan)
                while len(plans) > _PLANS_KEPT:
                    del plans[next(iter(plans))]
        return plan

    def __getstate__(self):
        # A pickled calibration (a dask worker's) carries its arrays, never its plans, which
        # hold compiled programs and device memory.
        return {name: value for name, value in self.__dict__.items() if name not in ("_plans", "_patch_box", "_parts")}

    def rows(self, row0: int, row1: int) -> Calibration:
        """This calibration for image rows row0:row1 only, without the patch (None).

        For correcting an image in strips: `correct(raw[row0:row1], calibration.rows(row0, row1),
        p=patch_ratio(raw, calibration))` equals rows row0:row1 of `correct(raw, calibration)`.
        The same rows give the same object while it is kept (`_part`), and with it its plans.
        """
        height = self.image_shape[0]
        if not 0 <= row0 < row1 <= height:
            raise ValueError(f"rows: expected 0 <= row0 < row1 <= {height}, got {row0}:{row1}")
        return self._part(row0, row1, 0, self.image_shape[1])

    def box(self, row0: int, row1: int, col0: int, col1: int) -> Calibration:
        """This calibration for the pixels [row0:row1, col0:col1] only, without the patch: a region
        corrected with the whole image's p (`spherejax.measure`). Kept as `rows` is."""
        height, width = self.image_shape
        if not (0 <= row0 < row1 <= height and 0 <= col0 < col1 <= width):
            raise ValueError(f"box: expected 0 <= row0 < row1 <= {height} and 0 <= col0 < col1 <= {width}, "
                             f"got {row0}:{row1}, {col0}:{col1}")
        return self._part(row0, row1, col0, col1)

    def _part(self, row0: int, row1: int, col0: int, col1: int) -> Calibration:
        """The patchless crop [row0:row1, col0:col1], kept for a concrete calibration (the last
        `_PARTS_KEPT`: the strips of an image, a few measured regions), so that every input
        corrected by those rows or that region reuses one plan."""
        def crop():
            # dataclasses.replace carries every other field (the Wiener offset included) and runs
            # the checks again.
            return dataclasses.replace(self, dark=self.dark[row0:row1, col0:col1],
                                       white=self.white[row0:row1, col0:col1], patch=None)

        if not _checks.is_concrete(self.dark):  # a traced calibration: its crops are traced too
            return crop()
        key = (row0, row1, col0, col1)
        with _plans_lock:
            parts = self.__dict__.setdefault("_parts", {})
            part = parts.get(key)
        if part is None:
            part = crop()
            with _plans_lock:
                part = parts.setdefault(key, part)
                while len(parts) > _PARTS_KEPT:
                    del parts[next(iter(parts))]
        return part


def compute_dtype(raw, calibration: Calibration):
    return _checks.float_dtype(
        raw, calibration.dark, calibration.white, calibration.coeffs, calibration.wiener,
        calibration.wiener_offset,
    )


def saturation_level(raw, calibration: Calibration):
    if calibration.saturation is not None:
        return float(calibration.saturation)
    if jnp.issubdtype(raw.dtype, jnp.integer):
        return float(jnp.iinfo(raw.dtype).max)
    return None


def patch_bounding_box(patch) -> tuple[int, int, int, int] | None:
    """(row0, row1, col0, col1) bounding the patch's nonzero entries (True or weight != 0), or
    None if the patch is traced.

    The white-patch ratio needs only the patch's pixels (0.1 % of the image in the paper's
    layout): slicing to this box keeps the ratio from making three passes over the whole cube.
    Pixels of weight 0 contribute nothing to the ratio's value, so leaving them out is exact.
    Differentiating with respect to the weights makes them tracers, so the ratio is then taken
    over the whole image and a weight of 0 gets its gradient too (which is not 0).
    """
    if not _checks.is_concrete(patch):
        return None
    mask = np.asarray(patch) != 0
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    return None if rows.size == 0 else (int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1)


__all__ = ["PARAMETERS", "Calibration", "compute_dtype", "saturation_level", "patch_bounding_box"]
