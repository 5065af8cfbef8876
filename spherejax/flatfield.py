"""Correction Stage I of Zou et al. (2019): the white standard and the reference white patch.

Conventions: channels last. Camera frames are ``(..., H, W, B)`` with B bands; raw frames may be
uint16 counts or floats, and the dark frame is subtracted from both sample and white standard
("we subtract the dark current from the camera response in practical measurements", Section 3.1).
Computation runs in float32 unless a float64 input is given.

Equations (Zou, Shen, Li, Zhu, Xin, Sensors 19(16), 3501, 2019, doi:10.3390/s19163501):

- Eq. 10, flat field: v_s(x) = u_s(x) / u_r(x) = rho_s(x) / rho_r(x) * q_s, which removes the
  spatial non-uniformity beta(x) but keeps q_s, the lighting deviation caused by the sample's mean
  reflectance (through k_s, Eq. 9) and by the lamp (Delta Phi_0).
- Eq. 14-15, white-patch ratio: the small white patch beside the sample sees q_s alone, so
  p_s = u_r(x_p) / u_s(x_p) = 1 / q_s.
- Eq. 16-17, Stage I: v_check = p_s * v_s = rho_s / rho_r, with q_s eliminated on a Lambertian
  sphere.

Bad pixels never raise: a pixel whose white standard is not above its dark frame (or is not
finite) gives NaN in `flat_field` and is left out of the patch average in `white_patch_ratio`.
"""

from __future__ import annotations

import jax.numpy as jnp

from . import _checks


def _check_frames(raw, dark, white):
    """Validate and convert the (raw, dark, white) triple; returns float arrays of one dtype."""
    raw = _checks.band_array("raw", raw)
    dark = _checks.as_array("dark", dark)
    white = _checks.as_array("white", white)
    bands = raw.shape[-1]
    _checks.require_last_axis("dark", dark, bands, f"the same {bands} bands as raw")
    _checks.require_last_axis("white", white, bands, f"the same {bands} bands as raw")
    if tuple(dark.shape) != tuple(white.shape):
        raise ValueError(
            f"dark, white: expected one shape for the dark frame and the white standard, got "
            f"{tuple(dark.shape)} and {tuple(white.shape)}"
        )
    _checks.require_broadcastable("dark", dark, "raw", raw.shape)
    dtype = _checks.float_dtype(raw, dark, white)
    return raw.astype(dtype), dark.astype(dtype), white.astype(dtype)


def white_signal_usable(dark, white):
    """True where the white standard gives a usable flat field: finite and above the dark frame."""
    white_signal = white - dark
    return (white_signal > 0) & jnp.isfinite(white_signal)


def flat_field_unchecked(raw, dark, white):
    """Eq. 10 on float arrays that are already validated; see `flat_field`."""
    white_signal = white - dark
    usable = white_signal_usable(dark, white)
    # Safe-where: dividing by a non-positive denominator and masking afterwards would still put
    # NaN into the gradient, so the denominator itself is made harmless first.
    return jnp.where(usable, (raw - dark) / jnp.where(usable, white_signal, 1.0), jnp.nan)


def flat_field(raw, dark, white):
    """Normalised camera response v_s = (raw - dark) / (white - dark) (Eq. 10).

    Args:
      raw: sample frame(s), shape (..., B), uint16 counts or float.
      dark: dark frame, shape (..., B), broadcastable to `raw`.
      white: white-standard frame, same shape as `dark`.

    Returns:
      v_s, shape of `raw`, float: 1 where the sample is as bright as the white standard; NaN where
      white <= dark or an input is not finite.
    """
    return flat_field_unchecked(*_check_frames(raw, dark, white))


def patch_ratio_weighted(raw, dark, white, weights):
    """Eq. 14-15 with a per-pixel weight instead of a boolean mask.

    Args:
      raw: float, shape (..., H, W, B). dark, white: float, shape (H, W, B) (or broadcastable).
      weights: float, shape (H, W) or (..., H, W, 1)-broadcastable; 0 excludes a pixel.

    Returns:
      p_s, shape (..., B): the weighted sum of dark-subtracted white-standard responses over that
      of the sample. Pixels that are not finite or whose white is not above dark get weight 0,
      so a single bad pixel in the patch does not spoil the ratio; NaN if no usable pixel remains
      or the sample's patch signal is not positive. Differentiable in `weights`, at weight 0
      included (d p / d w_x = (u_r(x) - p u_s(x)) / sum_x w_x u_s(x)).
    """
    if weights.ndim == 2:
        weights = weights[..., None]
    white_signal = white - dark
    sample_signal = raw - dark
    # Zero weights are not masked out here: their pixels add 0 to both sums anyway, and masking
    # them would zero the gradient with respect to a weight at 0, which is not 0.
    usable = white_signal_usable(dark, white) & jnp.isfinite(sample_signal)
    w = jnp.where(usable, weights, 0.0)
    white_sum = jnp.sum(w * jnp.where(usable, white_signal, 0.0), axis=(-3, -2))
    sample_sum = jnp.sum(w * jnp.where(usable, sample_signal, 0.0), axis=(-3, -2))
    valid = (sample_sum > 0) & (white_sum > 0)
    return jnp.where(valid, white_sum / jnp.where(valid, sample_sum, 1.0), jnp.nan)


def white_patch_ratio(raw, dark, white, patch):
    """White-patch ratio p_s = u_r(x_p) / u_s(x_p) (Eq. 14-15), averaged over the patch.

    Args:
      raw: sample frame(s), shape (..., H, W, B).
      dark, white: dark frame and white standard, shape (H, W, B) (or broadcastable to `raw`).
      patch: boolean mask, shape (H, W), True on the reference white patch.

    Returns:
      p_s, shape (..., B): the patch-averaged dark-subtracted response of the white standard over
      that of the sample (> 1 when the sample darkens the sphere). Pixels in the patch that are
      unusable (non-finite, white <= dark) are left out; NaN for a band with none left.
    """
    raw, dark, white = _check_frames(raw, dark, white)
    if raw.ndim < 3:
        raise ValueError(f"raw: expected shape (..., H, W, B), got {tuple(raw.shape)}")
    patch = _checks.as_array("patch", patch)
    _checks.require_bool_mask("patch", patch, tuple(raw.shape[-3:-1]))
    _checks.require_nonempty_mask("patch", patch)
    return patch_ratio_weighted(raw, dark, white, patch.astype(raw.dtype))


def stage1(v, p):
    """Stage I correction v_check = p_s * v_s (Eq. 16-17).

    Args:
      v: normalised response from `flat_field`, shape (..., B).
      p: white-patch ratio, shape (B,) or broadcastable to `v` (e.g. (N, 1, 1, B) per image).

    Returns:
      v_check, shape of `v`: rho_s / rho_r on a Lambertian sphere, whatever the background and
      the lamp.
    """
    v, p = _checks.response_and_ratio(v, p)
    dtype = _checks.float_dtype(v, p)
    return v.astype(dtype) * p.astype(dtype)


__all__ = ["flat_field", "white_patch_ratio", "stage1"]
