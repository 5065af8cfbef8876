"""Textiles off the Lambertian ideal: a BRDF, and what it does to a d:0° sphere's reading.

Stage I assumes Lambertian samples (Zou et al. 2019, Section 3); Section 4 names the sample's
BRDF first among what it cannot remove: "the percentage of the reflected flux reaching the sensor
changed in different reflections". This module makes that statement computable: a textile BRDF,
and the reading it gives along the camera's axis (the sample's normal, d:0°) under the light a
point of the holder actually receives (`sphere_radiosity.incident_light`), relative to a
Lambertian surface of the same albedo under the same light.

The BRDF, f(l, v) in sr^-1, l and v unit vectors to the light and the viewer, n = +z:

  body           (1 - s) f_d, a rough diffuse term (Oren & Nayar 1994, "Generalization of
                 Lambert's reflectance model", SIGGRAPH '94, the qualitative model, their
                 Eq. 30): V-cavities whose slopes have standard deviation σ (rad),
                   f_d = ρ/π [A + B max(0, cos(φ_v - φ_l)) sin α tan β
                              + 0.17 ρ σ² / (σ² + 0.13) (1 - cos(φ_v - φ_l) (2β/π)²)],
                   A = 1 - σ² / (2 (σ² + 0.33)),  B = 0.45 σ² / (σ² + 0.09),
                   α = max(θ_l, θ_v),  β = min(θ_l, θ_v);
                 the last term is their inter-reflection inside the cavities (Eq. 31), the
                 texture's inter-reflection; σ = 0 is Lambert's law.
  sheen          (Estevez & Kulla 2017, "Production friendly microfacet sheen BRDF", the
                 "Charlie" distribution of fibres standing off the surface, with the visibility
                 term of Neubelt & Pettineo 2013, "Crafting a next-gen material pipeline for
                 The Order: 1886"),
                   f_s = s D(θ_h) / (4 (cos θ_l + cos θ_v - cos θ_l cos θ_v)),
                   D(θ_h) = (2 + 1/a) sin(θ_h)^(1/a) / (2π),
                 h the half vector, a in (0, 1] the sheen's roughness; s is colourless: the
                 fibres' surface reflection, not their dye.

Parameters (`TextileBRDF`) and their ranges: σ 0-0.6 rad (0-35°, smooth to the rough matte
surfaces of Oren & Nayar's figures); s 0-0.07, at most the Fresnel reflectance of a fibre's
surface at normal incidence ((n - 1)² / (n + 1)² = 0.04-0.07 for the refractive indices of
textile fibres, 1.5-1.7: cotton ~1.55, wool ~1.55, polyester 1.54-1.72; Morton & Hearle,
"Physical Properties of Textile Fibres", 4th ed. 2008, ch. 21); a 0.3-1 (Estevez & Kulla's
range of the parameter).

What it shows (tests/test_textile_brdf.py): along the normal the rough-diffuse term does not
depend on where the light comes from (β = 0: A ρ/π + 0.17 ρ² σ²/(σ² + 0.13)/π), so a sample's reading under a sphere departs from
a Lambertian one only through its sheen, by a grey offset that scales with the light like the
reflectance does. Under the paper's sphere the holder's light moves between directions by at
most 0.04 % when the background changes, so the reading relative to a Lambertian one changes by
far less than Stage I's residual (`reading_change_bound`).
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

#: Ranges of `TextileBRDF`'s parameters (module docstring for the sources).
ROUGHNESS_RANGE_RAD = (0.0, 0.6)
SHEEN_STRENGTH_RANGE = (0.0, 0.07)
SHEEN_ROUGHNESS_RANGE = (0.3, 1.0)


@dataclasses.dataclass(frozen=True)
class TextileBRDF:
    """A textile's reflection: rough diffuse (Oren-Nayar σ, rad) plus a colourless sheen of
    strength `sheen_strength` and roughness `sheen_roughness` (module docstring)."""

    roughness_rad: float = 0.3
    sheen_strength: float = 0.04
    sheen_roughness: float = 0.5


def oren_nayar(albedo, sigma, light, view):
    """Oren-Nayar BRDF (sr^-1), the qualitative model with the cavities' inter-reflection, for
    unit vectors light, view (..., 3), n = +z; albedo ρ broadcastable against their leading
    shape. Reciprocal in light and view; σ = 0 is ρ/π."""
    light, view = jnp.asarray(light), jnp.asarray(view)
    cos_l, cos_v = jnp.clip(light[..., 2], 0.0, 1.0), jnp.clip(view[..., 2], 0.0, 1.0)
    sin_l, sin_v = jnp.sqrt(1.0 - cos_l**2), jnp.sqrt(1.0 - cos_v**2)
    # cos(φ_v - φ_l) from the tangential parts; 0 where either direction is the normal.
    tangential = light[..., 0] * view[..., 0] + light[..., 1] * view[..., 1]
    cos_dphi = jnp.where(sin_l * sin_v > 1e-12, tangential / jnp.maximum(sin_l * sin_v, 1e-12), 0.0)
    sigma2 = jnp.asarray(sigma) ** 2
    a = 1.0 - 0.5 * sigma2 / (sigma2 + 0.33)
    b = 0.45 * sigma2 / (sigma2 + 0.09)
    # sin α tan β with α the larger polar angle, β the smaller: sin α = the larger sine, tan β
    # = the smaller sine over the larger cosine.
    sin_alpha = jnp.maximum(sin_l, sin_v)
    tan_beta = jnp.minimum(sin_l, sin_v) / jnp.maximum(jnp.maximum(cos_l, cos_v), 1e-12)
    albedo = jnp.asarray(albedo)
    single = a + b * jnp.maximum(0.0, cos_dphi) * sin_alpha * tan_beta
    # Light reflected twice inside a cavity (their Eq. 31 with β the smaller polar angle):
    # ρ² rather than ρ, so a textured surface's reflection is not linear in its albedo.
    beta = jnp.arcsin(jnp.clip(jnp.minimum(sin_l, sin_v), 0.0, 1.0))
    twice = 0.17 * albedo * sigma2 / (sigma2 + 0.13) * (1.0 - cos_dphi * (2.0 * beta / jnp.pi) ** 2)
    return albedo / jnp.pi * (single + twice)


def sheen(strength, roughness, light, view):
    """The colourless "Charlie" sheen lobe (sr^-1) for unit vectors light, view (..., 3), n = +z
    (module docstring)."""
    light, view = jnp.asarray(light), jnp.asarray(view)
    cos_l, cos_v = jnp.clip(light[..., 2], 0.0, 1.0), jnp.clip(view[..., 2], 0.0, 1.0)
    half = light + view
    half = half / jnp.maximum(jnp.linalg.norm(half, axis=-1, keepdims=True), 1e-12)
    sin_h = jnp.sqrt(jnp.clip(1.0 - half[..., 2] ** 2, 0.0, 1.0))
    inverse = 1.0 / jnp.asarray(roughness)
    distribution = (2.0 + inverse) * sin_h**inverse / (2.0 * jnp.pi)
    visibility = 1.0 / (4.0 * jnp.maximum(cos_l + cos_v - cos_l * cos_v, 1e-12))
    return jnp.asarray(strength) * distribution * visibility


def textile_brdf(brdf: TextileBRDF, albedo, light, view):
    """f = (1 - s) `oren_nayar` + `sheen` of `brdf` (sr^-1), zero where light or view is below the
    surface: the body's reflection is of the light the fibres' surface did not reflect."""
    light, view = jnp.asarray(light), jnp.asarray(view)
    above = (light[..., 2] > 0.0) & (view[..., 2] > 0.0)
    # The body reflection is what the fibres' surface lets in: 1 - s of the light.
    body = (1.0 - brdf.sheen_strength) * oren_nayar(albedo, brdf.roughness_rad, light, view)
    value = body + sheen(brdf.sheen_strength, brdf.sheen_roughness, light, view)
    return jnp.where(above, value, 0.0)


def normal_view_reading(brdf: TextileBRDF, albedo, directions, irradiance):
    """The sample's radiance along its normal relative to a Lambertian surface of the same albedo
    under the same light: π Σ_j f(l_j, n) E_j / (ρ Σ_j E_j).

    Args:
      brdf: the textile.
      albedo: ρ, (K,) per band or a number.
      directions: (N, 3) unit vectors from the sample point to where its light comes from
        (n = +z), e.g. `sphere_radiosity.incident_light`'s.
      irradiance: (K, N) or (N,) the irradiance each direction contributes (W m^-2).

    Returns:
      (K,) or (): 1 for a Lambertian surface under any light.
    """
    irradiance = jnp.asarray(irradiance)
    albedo = jnp.asarray(albedo)
    normal = jnp.array([0.0, 0.0, 1.0], dtype=irradiance.dtype)
    f = textile_brdf(brdf, albedo[..., None], jnp.asarray(directions), normal)  # (K, N) or (N,)
    return jnp.pi * jnp.sum(f * irradiance, axis=-1) / (albedo * jnp.sum(irradiance, axis=-1))


def parameter_corners() -> list[TextileBRDF]:
    """Every corner of the parameter box (module docstring): the extremes a bound must cover."""
    return [
        TextileBRDF(sigma, strength, roughness)
        for sigma in ROUGHNESS_RANGE_RAD
        for strength in SHEEN_STRENGTH_RANGE
        for roughness in SHEEN_ROUGHNESS_RANGE
    ]


def reading_change_bound(readings_a: np.ndarray, readings_b: np.ndarray) -> float:
    """The largest relative change max |b / a - 1| between two sets of `normal_view_reading`s
    (the same textiles and bands under two lights)."""
    return float(np.max(np.abs(np.asarray(readings_b) / np.asarray(readings_a) - 1.0)))


__all__ = [
    "ROUGHNESS_RANGE_RAD",
    "SHEEN_ROUGHNESS_RANGE",
    "SHEEN_STRENGTH_RANGE",
    "TextileBRDF",
    "normal_view_reading",
    "oren_nayar",
    "parameter_corners",
    "reading_change_bound",
    "sheen",
    "textile_brdf",
]
