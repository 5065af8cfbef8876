"""The calibration's arrays as the per-pixel step reads them: one named structure.

`correct`'s per-pixel step (`equations.pixel_outputs`), its fused CPU kernel
(`spherejax._engine.fused`), the propagated uncertainty (`uncertainty.pixel_uncertainty`) and a
region's statistics (`measurement`) all read the same arrays. As positional arguments they are easy to pass in the
wrong order, and "weights" could mean pixel weights (H, W) or tristimulus weights (31, 3). Here
each has one name, its shape and its unit, and they are cast to one compute dtype in one place (`PixelConstants.of`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import colorimetry
from .estimation.kernel_residual import KernelResidual

_HIGHEST = jax.lax.Precision.HIGHEST


class PixelConstants(eqx.Module):
    """The per-pixel step's calibration arrays, all in one float dtype (a pytree of them).

    Fields:
      dark: dark frame (H, W, B), raw counts.
      white: white-standard frame (H, W, B), raw counts, the samples' exposure.
      coeffs: Stage II coefficients c1..c4 (B, 4) (Eq. 23).
      wiener: the estimator's matrix W (31, B): reflectance per unit of Stage II response.
      wiener_offset: the estimator's offset r0 (31,), reflectance (r = W v_tilde + r0).
      tristimulus_weights: ASTM E308 weights (31, 3) of the illuminant and observer, scaled so
        that the perfect diffuser has Y = 100 (`colorimetry.tristimulus_weights`).
      wiener_residual: the estimator's kernel residual (`estimation.KernelResidual`: r = W
        v_tilde + r0 + A k(v_tilde), E8), or None for an affine estimator.

    H and W may be rows or a box of the image (`rows`, `box`): the per-pixel step needs the dark
    and white frames of exactly the pixels it corrects.
    """

    dark: jax.Array
    white: jax.Array
    coeffs: jax.Array
    wiener: jax.Array
    wiener_offset: jax.Array
    tristimulus_weights: jax.Array
    wiener_residual: KernelResidual | None = None

    @classmethod
    def of(cls, calibration, dtype) -> PixelConstants:
        """A `spherejax.Calibration`'s arrays cast to `dtype` (float32 or float64), with the
        tristimulus weights of its illuminant and observer. Traceable: under `jax.grad` with
        respect to the calibration the casts are part of the derivative."""
        dtype = np.dtype(dtype)
        weights = colorimetry.tristimulus_weights(calibration.illuminant, observer=calibration.observer)
        return cls(
            dark=calibration.dark.astype(dtype), white=calibration.white.astype(dtype),
            coeffs=calibration.coeffs.astype(dtype), wiener=calibration.wiener.astype(dtype),
            wiener_offset=calibration.wiener_offset.astype(dtype), tristimulus_weights=jnp.asarray(weights, dtype),
            wiener_residual=None if calibration.wiener_residual is None else calibration.wiener_residual.astype(dtype),
        )

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(self.dark.dtype)

    @property
    def bands(self) -> int:
        return int(self.dark.shape[-1])

    def xyz_projection(self) -> tuple[jax.Array, jax.Array]:
        """(W^T weights (B, 3), r0 weights (3,)): XYZ = v_tilde (W^T weights) + r0 weights, so that
        XYZ never goes through the 31-channel reflectance (the module docstring of pipeline)."""
        matrix = jnp.matmul(self.wiener.T, self.tristimulus_weights, precision=_HIGHEST)
        offset = jnp.matmul(self.wiener_offset, self.tristimulus_weights, precision=_HIGHEST)
        return matrix, offset

    def white_xyz(self) -> jax.Array:
        """XYZ of the perfect diffuser (3,): the weights' column sums (Y = 100)."""
        return jnp.sum(self.tristimulus_weights, axis=0)

    def pixels(self, dark, white) -> PixelConstants:
        """The same constants with other dark and white frames (rows, a box or blocks of pixels
        of these: the per-pixel step reads only the frames' pixels it corrects)."""
        return PixelConstants(dark, white, self.coeffs, self.wiener, self.wiener_offset, self.tristimulus_weights,
                              self.wiener_residual)

    def box(self, row0: int, row1: int, col0: int, col1: int) -> PixelConstants:
        """The constants of the pixels rows row0:row1, columns col0:col1."""
        return self.pixels(self.dark[row0:row1, col0:col1], self.white[row0:row1, col0:col1])


class PatchConstants(eqx.Module):
    """The white patch's bounding box of the calibration, as Eq. 14-15 read it, in one float dtype.

    Fields:
      dark, white: the dark and white-standard frames over the box, (h, w, B), raw counts.
      weights: the patch over the box, (h, w): 1 on the patch and 0 off it for a boolean mask, or
        the patch's weights (`Calibration.patch`).

    The box is the patch's bounding box (`pipeline.patch_bounding_box`), or the whole frame when
    the patch is traced (differentiated with respect to its weights).
    """

    dark: jax.Array
    white: jax.Array
    weights: jax.Array

    @classmethod
    def of(cls, calibration, dtype, box: tuple[int, int, int, int]) -> PatchConstants:
        """The calibration's box (row0, row1, col0, col1) cast to `dtype` (traceable)."""
        r0, r1, c0, c1 = box
        dtype = np.dtype(dtype)
        return cls(
            dark=calibration.dark[r0:r1, c0:c1].astype(dtype), white=calibration.white[r0:r1, c0:c1].astype(dtype),
            weights=calibration.patch[r0:r1, c0:c1].astype(dtype),
        )


__all__ = ["PixelConstants", "PatchConstants"]
