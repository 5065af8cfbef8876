"""`CorrectionResult`, what `spherejax.correct` returns, and the CIEDE2000 map of its Lab.

Kept apart from the equations (`spherejax.pipeline`) so that the outputs' type can be read, and
converted (`to_xarray`), without the per-pixel path.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax

from . import _checks, uncertainty
from .colorimetry import delta_e_2000


class CorrectionResult(eqx.Module):
    """Output of `correct`. NaN wherever `quality` != 0.

    Fields:
      reflectance: (..., H, W, 31), 400..700 nm step 10.
      lab: (..., H, W, 3) under the calibration's illuminant.
      quality: (..., H, W) uint8 bit mask, see the QUALITY_* constants; 0 = good.
      p: white-patch ratio (..., B) (Eq. 15).
      v: flat-fielded response (..., H, W, B) (Eq. 10), or None unless intermediates=True.
      v_stage1: Stage I response p v (Eq. 17), or None.
      v_stage2: Stage II response (Eq. 23), the input of the Wiener step, or None.
      reflectance_u: standard uncertainty of `reflectance` (..., H, W, 31), or None unless
        `correct` was given a noise model (`spherejax.uncertainty`).
      lab_u: standard uncertainties of L*, a*, b* (..., H, W, 3), or None.
      lab_covariance: the covariance of Lab (..., H, W, 3, 3) (L*, a* and b* are correlated: they
        share X, Y and Z), or None.
      p_u: standard uncertainty of p (..., B), or None.
    """

    reflectance: jax.Array
    lab: jax.Array
    quality: jax.Array
    p: jax.Array
    v: jax.Array | None = None
    v_stage1: jax.Array | None = None
    v_stage2: jax.Array | None = None
    reflectance_u: jax.Array | None = None
    lab_u: jax.Array | None = None
    lab_covariance: jax.Array | None = None
    p_u: jax.Array | None = None

    @property
    def valid(self) -> jax.Array:
        """Boolean (..., H, W): True where the pixel is good."""
        return self.quality == 0

    def delta_e_map(self, reference):
        """ΔE00 of every pixel against `reference` (see `delta_e_map`)."""
        return delta_e_map(self.lab, reference)

    def delta_e_u(self, reference, reference_covariance=None):
        """Standard uncertainty of `delta_e_map(reference)`, (..., H, W), by first order
        (`uncertainty.delta_e_uncertainty`); needs a result of `correct(..., noise=)`.

        Args:
          reference: one Lab colour (3,) or a Lab image of `lab`'s shape.
          reference_covariance: the reference's covariance, (3, 3) or (..., H, W, 3, 3) (e.g.
            another result's `lab_covariance`), or None for an exact reference.

        0 where ΔE00 is 0, and an understatement near it: ΔE00 is a distance, whose spread about
        0 is not what its first-order term says (docs/uncertainty.md).
        """
        if self.lab_covariance is None:
            raise ValueError("delta_e_u: this result has no uncertainties; expected correct(raw, calibration, noise=NoiseModel(...))")
        reference = _checks.as_array("reference", reference)
        _checks.require_last_axis("reference", reference, 3, "one Lab colour or a Lab image")
        if reference.ndim != 1:
            _checks.require_shape("reference", reference, self.lab.shape, "one Lab colour (3,) or lab's shape")
        if reference_covariance is not None:
            reference_covariance = _checks.as_array("reference_covariance", reference_covariance)
            if reference_covariance.shape not in ((3, 3), tuple(self.lab_covariance.shape)):
                raise ValueError(
                    f"reference_covariance: expected shape (3, 3) or {tuple(self.lab_covariance.shape)}, "
                    f"got {tuple(reference_covariance.shape)}"
                )
        return _delta_e_u(self.lab, self.lab_covariance, reference, reference_covariance)

    def to_xarray(self, attrs=None):
        """The result as an `xarray.Dataset` (copied to host memory): reflectance (..., y, x,
        wavelength) with wavelength in nm, lab (..., y, x, lab), quality (..., y, x), p (...,
        band), and the uncertainties and intermediates this result holds; names and coordinates
        in `spherejax.labelled`. `attrs`: the dataset's attributes (e.g. the illuminant)."""
        from . import labelled

        arrays = {field.name: getattr(self, field.name) for field in dataclasses.fields(self)}
        return labelled.dataset(arrays, attrs=attrs)


@jax.jit
def _delta_e_u(lab, lab_covariance, reference, reference_covariance):
    return uncertainty.delta_e_uncertainty(lab, lab_covariance, reference, reference_covariance)


def delta_e_map(lab, reference):
    """CIEDE2000 map of a Lab image against a reference Lab image or one Lab colour.

    Args:
      lab: (..., H, W, 3), e.g. `correct(...).lab`.
      reference: (3,) for one colour, or a Lab image of the same shape as `lab`.

    Returns:
      ΔE00, shape (..., H, W); NaN where either input is NaN.
    """
    lab = _checks.as_array("lab", lab)
    reference = _checks.as_array("reference", reference)
    _checks.require_last_axis("lab", lab, 3, "L*, a*, b*")
    _checks.require_last_axis("reference", reference, 3, "one Lab colour or a Lab image")
    if reference.ndim != 1:
        _checks.require_shape("reference", reference, lab.shape, "one Lab colour (3,) or lab's shape")
    return delta_e_2000(lab, reference)


__all__ = ["CorrectionResult", "delta_e_map"]
