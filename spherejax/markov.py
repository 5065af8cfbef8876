"""The baseline: the Markov model of an integrating sphere (Hidović-Rowe, Rowe, Lualdi 2006).

I. Hidović-Rowe, J. E. Rowe, M. Lualdi, "Markov models of integrating spheres for hyperspectral
imaging", Applied Optics 45(21), 5248-5257 (2006). Light leaving one diffuse patch of the sphere
reaches another in proportion to its area; the expected number of visits of a photon follows from
an absorbing Markov chain, n = π0ᵀ (I − Q)⁻¹ with Q[i, k] = ρ_i a_k. For an ideal sphere this
gives a per-pixel correction of the flat-fielded reflectance g:

    R_j = g_j / (1 − κ (R_W − ḡ))

where ḡ is g's mean over the whole holder, R_W the white board's reflectance and
κ = a_s / (1 − a_w ρ_w) a per-band constant of the sphere (holder area fraction a_s, wall area
fraction a_w, wall reflectance ρ_w), fitted from grey tiles of known reflectance.

Zou et al. (2019) compare against it in Table 6. It assumes a constant lamp and Lambertian
samples: it corrects the sample's effect on the sphere but neither lamp fluctuation (it has no
white reference patch) nor glare or non-Lambertian coupling.

Shapes: channels last, B bands; g, ḡ and R are (..., B), R_W and κ are (B,).
"""

from __future__ import annotations

import jax.numpy as jnp

from . import _checks


def markov_correct(g, g_holder_mean, kappa, white_reflectance):
    """R = g / (1 − κ (R_W − ḡ)) per band.

    Args:
      g: flat-fielded reflectance v R_W, shape (..., B).
      g_holder_mean: ḡ, the mean of g over the whole holder, broadcastable to `g` (e.g. (B,)
        for one image, or (..., 1, 1, B) per image of a stack).
      kappa: κ per band, shape (B,).
      white_reflectance: R_W per band, shape (B,).

    Returns:
      R, shape of `g`: the reflectance the sphere would have shown with the white board in it.
    """
    g = _checks.band_array("g", g)
    bands = g.shape[-1]
    g_holder_mean = _checks.as_array("g_holder_mean", g_holder_mean)
    kappa = _checks.as_array("kappa", kappa)
    white_reflectance = _checks.as_array("white_reflectance", white_reflectance)
    _checks.require_last_axis("g_holder_mean", g_holder_mean, bands, f"one mean per band of g, B = {bands}")
    _checks.require_shape("kappa", kappa, (bands,), "one κ per band")
    _checks.require_shape("white_reflectance", white_reflectance, (bands,), "R_W per band")
    dtype = _checks.float_dtype(g, g_holder_mean, kappa, white_reflectance)
    g, g_holder_mean, kappa, white_reflectance = (
        x.astype(dtype) for x in (g, g_holder_mean, kappa, white_reflectance)
    )
    return g / (1.0 - kappa * (white_reflectance - g_holder_mean))


def fit_markov_kappa(g, g_holder_mean, reflectance, white_reflectance):
    """Per-band κ from tiles of known reflectance, by least squares.

    R (1 − κ (R_W − ḡ)) = g is linear in κ: with d = R_W − ḡ, R − g = κ R d, so
    κ = Σ R d (R − g) / Σ (R d)² over the tiles, band by band.

    Args:
      g: flat-fielded reflectance of the tiles, (n, B) (each averaged over its region).
      g_holder_mean: ḡ of the frame each tile was measured in, (n, B).
      reflectance: the tiles' known reflectance per band, (n, B).
      white_reflectance: R_W per band, (B,).

    Returns:
      κ, shape (B,). Non-finite samples are left out; a band with none left is NaN.
    """
    g = _checks.as_array("g", g)
    if g.ndim != 2:
        raise ValueError(f"g: expected shape (n, B) (tiles, bands), got {tuple(g.shape)}")
    for name, x in (("g_holder_mean", g_holder_mean), ("reflectance", reflectance)):
        _checks.require_shape(name, _checks.as_array(name, x), g.shape, "one value per tile and band, like g")
    _checks.require_shape("white_reflectance", _checks.as_array("white_reflectance", white_reflectance), (g.shape[1],), "R_W per band")
    dtype = _checks.float_dtype(g, jnp.asarray(g_holder_mean), jnp.asarray(reflectance), jnp.asarray(white_reflectance))
    g = g.astype(dtype)
    R = jnp.asarray(reflectance).astype(dtype)
    d = jnp.asarray(white_reflectance).astype(dtype) - jnp.asarray(g_holder_mean).astype(dtype)
    x = R * d
    y = R - g
    usable = jnp.isfinite(x) & jnp.isfinite(y)
    x = jnp.where(usable, x, 0.0)
    y = jnp.where(usable, y, 0.0)
    denominator = jnp.sum(x * x, axis=0)
    return jnp.where(denominator > 0, jnp.sum(x * y, axis=0) / jnp.where(denominator > 0, denominator, 1.0), jnp.nan)


__all__ = ["markov_correct", "fit_markov_kappa"]
