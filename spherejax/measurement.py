"""Measuring a region as a spectrophotometer does: its mean reflectance, Lab, and their
uncertainties.

A spectrophotometer averages the light of its aperture and computes colour from the mean
spectrum. `measure` does the same over a region of the image: the mean of the per-pixel
reflectances (the estimate is affine, so this is the estimate of the mean Stage II response),
then Lab of that mean under an illuminant. With a `NoiseModel`, the first-order covariance of
both (`spherejax.uncertainty`, N1-N8), source by source:

    pixel sources (sample, dark and white frames' noise, N1-N3): independent between pixels, so
      Cov(mean) = Σ_i w_i² J_i Σ_i J_iᵀ, which falls as 1 / (number of pixels);
    common sources (the white-patch ratio, the white standard, Stage II, the estimator, N4-N7):
      the same draw for every pixel, so the mean moves with the mean sensitivity,
      Cov(mean) = J̄ Σ J̄ᵀ, which no region size averages away;
    the kernel residual's own variance (N8, a kernel estimator that carries it): the residual
      is one function for every pixel, so its error at the region's mean response is the
      error of the region's reflectance, Σ_j var_j(v̄) P_j P_jᵀ (E15), whatever the region's size.

The region's pixels are weighted equally; pixels `correct` flags (saturated, non-finite, no flat
field) are left out and counted.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from . import _checks, colorimetry, uncertainty
from .number_text import json_ready
from .pipeline import Calibration, _check_calibration, _check_raw, correct, plan
from .pixel_constants import PixelConstants
from .uncertainty import COMMON_SOURCES, ESTIMATOR_SOURCE, PIXEL_SOURCES, NoiseModel

_HIGHEST = jax.lax.Precision.HIGHEST


@dataclasses.dataclass(frozen=True)
class Measurement:
    """One region's measurement (`measure`). NumPy arrays, float64 (whatever `precision`).

    Fields:
      reflectance: (31,) mean reflectance, 400..700 nm step 10.
      lab: (3,) L*, a*, b* of the mean reflectance under `illuminant`.
      illuminant: "D65", "A" or "F2"; observer: the colour-matching functions.
      pixels: pixels averaged; excluded: pixels of the region `correct` flagged (left out).
      reflectance_spread: (31,) standard deviation of the per-pixel reflectances over the region
        (the sample's non-uniformity plus pixel noise; not an uncertainty of the mean).
      reflectance_covariance: (31, 31) covariance of `reflectance`, or None without a noise model.
      lab_covariance: (3, 3) covariance of `lab`, or None.
      reflectance_budget: {source: (31, 31)} each source's part of `reflectance_covariance`
        (`uncertainty.SOURCES`); empty without a noise model.
      lab_budget: {source: (3, 3)} the same for Lab.
      precision: the floating dtype `measure` computed in (float32; float64 where the image or
        the calibration is float64 and JAX's x64 is on): the digits the values carry. Files write
        every number of the measurement as the shortest decimal of its value at this precision
        (`to_dict`, `spherejax.number_text`), not the float64 digits a float32 result shows.
    """

    reflectance: np.ndarray
    lab: np.ndarray
    illuminant: str
    observer: str
    pixels: int
    excluded: int
    reflectance_spread: np.ndarray
    reflectance_covariance: np.ndarray | None = None
    lab_covariance: np.ndarray | None = None
    reflectance_budget: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    lab_budget: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    precision: np.dtype = np.dtype(np.float64)

    @property
    def reflectance_u(self) -> np.ndarray | None:
        """(31,) standard uncertainties of `reflectance`, or None."""
        return None if self.reflectance_covariance is None else np.sqrt(np.diag(self.reflectance_covariance))

    @property
    def lab_u(self) -> np.ndarray | None:
        """(3,) standard uncertainties of L*, a*, b*, or None."""
        return None if self.lab_covariance is None else np.sqrt(np.diag(self.lab_covariance))

    def under(self, illuminant: str) -> Measurement:
        """This measurement with Lab (and its covariance) under another illuminant."""
        lab, jacobian = _lab_and_jacobian(self.reflectance, illuminant, self.observer)
        lab_budget = {name: jacobian @ cov @ jacobian.T for name, cov in self.reflectance_budget.items()}
        return dataclasses.replace(
            self, lab=lab, illuminant=illuminant,
            lab_covariance=None if self.reflectance_covariance is None else jacobian @ self.reflectance_covariance @ jacobian.T,
            lab_budget=lab_budget,
        )

    def delta_e(self, reference_lab, reference_covariance=None) -> tuple[float, float]:
        """(ΔE00 against `reference_lab` (3,), its standard uncertainty).

        Args:
          reference_lab: the standard's L*, a*, b* (3,), or another `Measurement` (its Lab and
            covariance are used, and the two are taken as independent: their common sources,
            p of one image excepted, then count twice, which overstates u).
          reference_covariance: (3, 3) of the reference, or None for an exact reference.

        The uncertainty is NaN without a noise model; it is first order, so 0 at ΔE00 = 0 and an
        understatement near it (docs/uncertainty.md).
        """
        if isinstance(reference_lab, Measurement):
            if reference_covariance is None:
                reference_covariance = reference_lab.lab_covariance
            reference_lab = reference_lab.lab
        return delta_e_and_u(self.lab, self.lab_covariance, reference_lab, reference_covariance)

    def to_dict(self) -> dict:
        """Plain JSON: the values, standard uncertainties, covariances and the budget, every
        number the shortest decimal of its value at `precision` (`number_text.json_ready`)."""
        def listed(x):
            return None if x is None else json_ready(np.asarray(x, np.float64), self.precision)

        return {
            "illuminant": self.illuminant,
            "observer": self.observer,
            "pixels": self.pixels,
            "excluded_pixels": self.excluded,
            "reflectance": listed(self.reflectance),
            "reflectance_u": listed(self.reflectance_u),
            "reflectance_spread": listed(self.reflectance_spread),
            "reflectance_covariance": listed(self.reflectance_covariance),
            "lab": listed(self.lab),
            "lab_u": listed(self.lab_u),
            "lab_covariance": listed(self.lab_covariance),
            "lab_u_by_source": {name: listed(np.sqrt(np.diag(cov))) for name, cov in self.lab_budget.items()},
        }


def delta_e_and_u(lab, lab_covariance, reference_lab, reference_covariance=None) -> tuple[float, float]:
    """(ΔE00 of `lab` (3,) against `reference_lab` (3,), its first-order standard uncertainty).

    lab_covariance, reference_covariance: (3, 3) or None (exact). u is NaN when `lab_covariance`
    is None (`Measurement.delta_e`, whose rules these are).
    """
    reference = np.asarray(reference_lab, np.float64)
    if reference.shape != (3,) or not np.all(np.isfinite(reference)):
        raise ValueError(f"reference_lab: expected three finite numbers L*, a*, b*, got {reference.tolist()}")
    if reference_covariance is not None:
        reference_covariance = np.asarray(reference_covariance, np.float64)
        if reference_covariance.shape != (3, 3):
            raise ValueError(f"reference_covariance: expected shape (3, 3), got {reference_covariance.shape}")
    # float64 where x64 is on, float32 otherwise (no dtype request: that would warn).
    as_jax = lambda x: None if x is None else jnp.asarray(np.asarray(x, np.float64))  # noqa: E731
    value, u = _delta_e_and_u(as_jax(lab), as_jax(lab_covariance), as_jax(reference), as_jax(reference_covariance))
    return float(value), float(u)


def _lab_and_jacobian(reflectance, illuminant: str, observer: str):
    """Lab (3,) of a reflectance (31,) and ∂Lab/∂reflectance (3, 31), by `jax.jacfwd`."""
    r = jnp.asarray(reflectance, jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)
    lab, jacobian = _lab_and_jacobian_compiled(r, illuminant, observer)
    return np.asarray(lab, np.float64), np.asarray(jacobian, np.float64)


@functools.partial(jax.jit, static_argnames=("illuminant", "observer"))
def _lab_and_jacobian_compiled(reflectance, illuminant: str, observer: str):
    def lab_of(r):
        return colorimetry.reflectance_to_lab(r, illuminant, observer=observer)

    return lab_of(reflectance), jax.jacfwd(lab_of)(reflectance)


@jax.jit
def _delta_e_and_u(lab, lab_covariance, reference, reference_covariance):
    """ΔE00 and its first-order u for one colour (`uncertainty.delta_e_uncertainty`), compiled:
    op by op, the gradient of ΔE00 takes seconds to dispatch."""
    value = colorimetry.delta_e_2000(lab, reference)
    if lab_covariance is None:
        return value, jnp.full((), jnp.nan, value.dtype)
    return value, uncertainty.delta_e_uncertainty(lab, lab_covariance, reference, reference_covariance)


@jax.jit
def _region_statistics(raw_f, pixel_weights, p, p_u, constants: PixelConstants, noise):
    """The region's mean Stage II response and every source's covariance of it.

    Args: raw_f (h, w, B); pixel_weights (h, w) (1 on pixels averaged, 0 elsewhere); p and p_u
    (B,); constants: the calibration over the region's box (`PixelConstants.box`); all one float
    dtype; noise: a `NoiseModel` or None.

    Returns:
      (mean reflectance (31,), spread (31,), {source: reflectance covariance (31, 31)}).
    """
    dark, white, coeffs = constants.dark, constants.white, constants.coeffs
    wiener, wiener_offset, residual = constants.wiener, constants.wiener_offset, constants.wiener_residual
    w = pixel_weights / jnp.sum(pixel_weights)
    safe = pixel_weights[..., None] > 0
    raw_safe = jnp.where(safe, raw_f, white)  # flagged pixels out of harm's way, as `correct`
    p_pixel = p[None, None, :]
    if noise is None:
        from .flatfield import flat_field_unchecked
        from .polynomial import stage2_unchecked

        v_tilde = stage2_unchecked(flat_field_unchecked(raw_safe, dark, white), p_pixel, coeffs)
    else:
        v_tilde, tangents, coeff_jacobian = uncertainty.band_tangents(
            raw_safe, dark, white, p_pixel, p_u[None, None, :], coeffs, noise
        )
    v_tilde = jnp.where(safe, v_tilde, 0.0)
    mean_v_tilde = jnp.sum(w[..., None] * v_tilde, axis=(0, 1))

    def estimate(v):
        """The calibration's estimate of responses v (..., B) (E1, or E8 with a kernel residual)."""
        reflectance = jnp.matmul(v, wiener.T, precision=_HIGHEST) + wiener_offset
        return reflectance if residual is None else reflectance + residual(v)

    # The region's reflectance is the estimate of its mean response: its first order there (W
    # itself for an affine estimator).
    j_reflectance = jax.jacfwd(estimate)(mean_v_tilde)
    budget = {}
    if noise is not None:
        for name in PIXEL_SOURCES:  # independent pixels: Σ w_i² t_i²
            variance = jnp.sum((w**2)[..., None] * jnp.where(safe, tangents[name], 0.0) ** 2, axis=(0, 1))
            budget[name] = (j_reflectance * variance) @ j_reflectance.T
        for name in ("white-patch ratio", "white standard"):
            # One draw for every pixel: the mean moves by Σ w_i t_i in each band, and the bands'
            # draws are independent (a diagonal, not an outer product of the tangents).
            mean_tangent = jnp.sum(w[..., None] * jnp.where(safe, tangents[name], 0.0), axis=(0, 1))
            budget[name] = (j_reflectance * mean_tangent**2) @ j_reflectance.T
        if coeff_jacobian is not None:
            mean_jacobian = jnp.sum(w[..., None, None] * jnp.where(safe[..., None], coeff_jacobian, 0.0), axis=(0, 1))
            variance = uncertainty.coefficient_variance(mean_jacobian, noise.coeffs_covariance)
            budget["Stage II coefficients"] = (j_reflectance * variance) @ j_reflectance.T
        if noise.estimator_covariance is not None:
            scale = uncertainty.estimator_scale(mean_v_tilde, noise.estimator_covariance)
            budget[ESTIMATOR_SOURCE] = scale * noise.estimator_covariance.residual.astype(raw_f.dtype)
        if residual is not None and residual.variance is not None:
            # The region's reflectance is the estimate at its mean response (above): the
            # residual's own uncertainty there, not the mean of the pixels' (E15).
            budget[uncertainty.RESIDUAL_SOURCE] = uncertainty.residual_covariance(mean_v_tilde, residual)
    mean = estimate(mean_v_tilde)
    pixel_reflectance = estimate(v_tilde)
    spread = jnp.sqrt(jnp.sum(w[..., None] * (pixel_reflectance - mean) ** 2, axis=(0, 1)))
    return mean, spread, budget


def _check_mask(mask, image_shape) -> np.ndarray:
    if not _checks.is_concrete(mask):
        raise ValueError("mask: expected a concrete (H, W) boolean array, got a traced value")
    mask = np.asarray(mask)
    if mask.shape != tuple(image_shape):
        raise ValueError(f"mask: expected shape {tuple(image_shape)} (the image's H, W), got {mask.shape}")
    if mask.dtype != bool:
        raise ValueError(f"mask: expected a boolean array, got dtype {mask.dtype}")
    if not mask.any():
        raise ValueError("mask: selects no pixel; expected at least one True entry")
    return mask


def measure(raw, calibration: Calibration, mask, noise: NoiseModel | None = None, *, illuminant: str | None = None) -> Measurement:
    """Measure a region of one image: mean reflectance and Lab, with their covariances.

    Args:
      raw: sample frames (H, W, B), uint16 counts or float, the calibration's size.
      calibration: a `Calibration` with a patch.
      mask: (H, W) bool, True on the region.
      noise: a `NoiseModel`, or None for values without uncertainties.
      illuminant: Lab's illuminant, "D65", "A" or "F2"; None = the calibration's.

    Returns:
      `Measurement`. ValueError when every pixel of the region is flagged by `correct`, or on
      bad shapes, names or types (naming the argument).
    """
    _check_calibration(calibration)
    raw = _check_raw(raw, calibration, "the calibration's H, W, B")
    if raw.ndim != 3:
        raise ValueError(f"raw: expected one image (H, W, B), got shape {tuple(raw.shape)}")
    if calibration.patch is None:
        raise ValueError("calibration: has no patch (rows of a calibration): measure needs the whole one")
    mask = _check_mask(mask, calibration.image_shape)
    noise = uncertainty.check_noise(noise, calibration.bands)
    illuminant = calibration.illuminant if illuminant is None else illuminant
    colorimetry.tristimulus_weights(illuminant, observer=calibration.observer)  # unknown names raise here

    prepared = plan(calibration, raw.shape, dtype=raw.dtype)  # what `correct` of this frame uses
    if calibration.band_transforms is not None:
        # Bands in register first, as `correct` does (`spherejax._engine.registered`): the region
        # is measured on the registered frames with the registered calibration. A pixel the
        # registration flags carries a placeholder every kernel flags, so it is left out below.
        raw, _ = prepared.register(raw)
        calibration, prepared = prepared.registered, prepared.inner
    p = prepared.patch_ratio(raw)
    p_u = prepared.patch_ratio_u(raw, noise) if noise is not None else jnp.zeros_like(p)
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    box = calibration.box(r0, r1, c0, c1)  # kept by the calibration: the same region reuses its plan
    raw_box = raw[r0:r1, c0:c1]
    quality = np.asarray(correct(raw_box, box, p=p).quality)
    region = mask[r0:r1, c0:c1]
    used = region & (quality == 0)
    pixels, excluded = int(used.sum()), int(region.sum() - used.sum())
    if pixels == 0:
        raise ValueError(
            f"mask: all {excluded} pixels of the region are flagged (saturated, not finite, white not "
            "above dark, or an unusable white patch); expected at least one good pixel"
        )
    dtype = prepared.compute_dtype
    cast = lambda x: jnp.asarray(x).astype(dtype)  # noqa: E731
    mean, spread, budget = _region_statistics(
        cast(raw_box), cast(used), cast(p), cast(p_u), prepared.constants.box(r0, r1, c0, c1), noise,
    )
    reflectance = np.asarray(mean, np.float64)
    lab, jacobian = _lab_and_jacobian(reflectance, illuminant, calibration.observer)
    reflectance_budget = {name: np.asarray(cov, np.float64) for name, cov in budget.items()}
    order = [name for name in uncertainty.SOURCES if name in reflectance_budget]
    reflectance_budget = {name: reflectance_budget[name] for name in order}
    covariance = sum(reflectance_budget.values()) if noise is not None else None
    return Measurement(
        reflectance=reflectance, lab=lab, illuminant=illuminant, observer=calibration.observer,
        pixels=pixels, excluded=excluded, reflectance_spread=np.asarray(spread, np.float64),
        reflectance_covariance=covariance,
        lab_covariance=None if covariance is None else jacobian @ covariance @ jacobian.T,
        reflectance_budget=reflectance_budget,
        lab_budget={name: jacobian @ cov @ jacobian.T for name, cov in reflectance_budget.items()},
        precision=np.dtype(mean.dtype),
    )


def measure_reflectances(reflectance, mask, quality=None, *, illuminant: str = "D65",
                         observer: str = colorimetry.DEFAULT_OBSERVER) -> Measurement:
    """Measure a region of a corrected image: `measure`'s values from the per-pixel reflectances.

    `measure` estimates the reflectance at the region's mean response; for an affine estimator
    (the Wiener forms) that is the mean of the per-pixel reflectances, so a region of an output
    of `correct` (a file, read back by `spherejax.open_corrected`) gives the same reflectance, Lab,
    pixel counts and spread without the raw frames. For a kernel estimator (an affine mean plus a
    nonlinear residual) the two differ by the residual's curvature over the region's spread of
    responses. What it cannot give is the covariance, which needs the raw frames and a noise
    model (`measure`).

    Args:
      reflectance: (H, W, 31) per-pixel reflectances (NaN where `correct` flagged the pixel).
      mask: (H, W) bool, True on the region.
      quality: (H, W) quality bits, or None (then only non-finite pixels are left out).
      illuminant, observer: Lab's (`colorimetry.tristimulus_weights`).

    Returns:
      `Measurement` without covariances, precision float32 (the files' values). ValueError when
      every pixel of the region is flagged or not finite, or on bad shapes.
    """
    reflectance = np.asarray(reflectance)
    if reflectance.ndim != 3:
        raise ValueError(f"reflectance: expected one image (H, W, 31), got shape {reflectance.shape}")
    mask = _check_mask(mask, reflectance.shape[:2])
    colorimetry.tristimulus_weights(illuminant, observer=observer)  # unknown names raise here
    values = reflectance[mask].astype(np.float64)
    good = np.all(np.isfinite(values), axis=-1)
    if quality is not None:
        good &= np.asarray(quality)[mask] == 0
    pixels, excluded = int(good.sum()), int(good.size - good.sum())
    if pixels == 0:
        raise ValueError(
            f"mask: all {excluded} pixels of the region are flagged or not finite; expected at least one good pixel"
        )
    mean = values[good].mean(axis=0)
    spread = values[good].std(axis=0)  # as `measure`'s: weights 1 / pixels, no Bessel correction
    lab, _ = _lab_and_jacobian(mean, illuminant, observer)
    return Measurement(
        reflectance=mean, lab=lab, illuminant=illuminant, observer=observer, pixels=pixels, excluded=excluded,
        reflectance_spread=spread, precision=np.dtype(np.float32),
    )


__all__ = ["Measurement", "delta_e_and_u", "measure", "measure_reflectances", "COMMON_SOURCES", "PIXEL_SOURCES"]
