"""CIE colorimetry in JAX: reflectance -> XYZ -> CIELAB, and the CIEDE2000 colour difference.

Conventions: channels last, any number of leading dimensions. Reflectance is sampled at
`grid.WAVELENGTHS_NM` (400..700 nm every 10 nm, 31 samples, unit reflectance = 1), XYZ and Lab are
``(..., 3)``. XYZ is scaled so that the perfect reflecting diffuser has Y = 100.

Tristimulus values follow colour-science's ``sd_to_XYZ`` with its default method, the ASTM E308-15
tristimulus weighting factors (ASTM E2022 weights, with the weights outside 400-700 nm folded onto
the end samples). Plain multiplication of 10 nm samples of the colour-matching functions and the
illuminant is off by up to 0.3 ΔE00 under D65 and several units under F2, so the weights are taken
from colour-science once per (illuminant, observer), cached, and applied as one (31, 3) matmul.

References
----------
- ASTM E308-15, Standard Practice for Computing the Colors of Objects by Using the CIE System.
- CIE 15:2004, Colorimetry (CIELAB).
- G. Sharma, W. Wu, E. N. Dalal, "The CIEDE2000 color-difference formula: Implementation notes,
  supplementary test data, and mathematical observations", Color Research and Application 30(1),
  21-30 (2005), doi:10.1002/col.20070. Variable names below follow its equations.
"""

from __future__ import annotations

import functools
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from . import _checks
from .angles import atan2_degrees, sin_degrees, sincos_degrees
from .grid import N_WAVELENGTHS, WAVELENGTHS_NM

#: Accepted illuminant names -> colour-science's names. "F2" is colour-science's "FL2".
ILLUMINANTS = {"D65": "D65", "A": "A", "F2": "FL2", "FL2": "FL2"}

#: Accepted observer names -> colour-science's names.
OBSERVERS = {
    "CIE 1931 2 Degree Standard Observer": "CIE 1931 2 Degree Standard Observer",
    "CIE 1964 10 Degree Standard Observer": "CIE 1964 10 Degree Standard Observer",
    "1931": "CIE 1931 2 Degree Standard Observer",
    "1964": "CIE 1964 10 Degree Standard Observer",
}
DEFAULT_OBSERVER = "CIE 1931 2 Degree Standard Observer"

# CIE 1976 constants, exact rationals (CIE 15:2004): the cube-root / linear switch point and slope.
_LAB_EPSILON = 216.0 / 24389.0
_LAB_KAPPA = 24389.0 / 27.0

_HIGHEST = jax.lax.Precision.HIGHEST  # GPUs would otherwise run float32 matmuls in TF32.


def _resolve(illuminant: str, observer: str) -> tuple[str, str]:
    if not isinstance(illuminant, str) or illuminant not in ILLUMINANTS:
        raise ValueError(
            f"illuminant: unknown illuminant {illuminant!r}; expected one of "
            f"{sorted(set(ILLUMINANTS))}"
        )
    if not isinstance(observer, str) or observer not in OBSERVERS:
        raise ValueError(
            f"observer: unknown observer {observer!r}; expected one of {sorted(OBSERVERS)}"
        )
    return ILLUMINANTS[illuminant], OBSERVERS[observer]


@functools.lru_cache(maxsize=None)
def _weights_cached(colour_illuminant: str, colour_observer: str) -> np.ndarray:
    # colour-science is imported here, not at module import: it takes about a second and only
    # the first XYZ conversion of a process needs it.
    import colour

    cmfs = colour.MSDS_CMFS[colour_observer]
    illuminant = colour.SDS_ILLUMINANTS[colour_illuminant]
    shape = colour.SpectralShape(float(WAVELENGTHS_NM[0]), float(WAVELENGTHS_NM[-1]), 10.0)
    # sd_to_XYZ (ASTM E308) is linear in the reflectance: XYZ = sum_i W[i] R[i]. Evaluating it on
    # the 31 unit impulses therefore reads off its weight matrix exactly, including the folding of
    # the out-of-range weights, whatever colour-science does internally.
    weights = np.empty((N_WAVELENGTHS, 3), dtype=np.float64)
    with warnings.catch_warnings():
        # "Trimming ... spectral distribution" notices: expected for a 400-700 nm input.
        warnings.simplefilter("ignore")
        for i in range(N_WAVELENGTHS):
            impulse = np.zeros(N_WAVELENGTHS)
            impulse[i] = 1.0
            sd = colour.SpectralDistribution(impulse, shape.wavelengths)
            weights[i] = colour.sd_to_XYZ(sd, cmfs, illuminant, method="ASTM E308")
    weights.setflags(write=False)
    return weights


def tristimulus_weights(illuminant: str = "D65", *, observer: str = DEFAULT_OBSERVER) -> np.ndarray:
    """ASTM E308 weights for 400..700 nm at 10 nm: XYZ = reflectance @ weights.

    Returns a read-only float64 array of shape (31, 3), scaled so that a perfect diffuser
    (reflectance 1 everywhere) has Y = 100. Computed from colour-science once per process.
    """
    return _weights_cached(*_resolve(illuminant, observer))


def white_point_xyz(illuminant: str = "D65", *, observer: str = DEFAULT_OBSERVER) -> np.ndarray:
    """XYZ of the perfect reflecting diffuser under `illuminant` (the Lab reference white).

    Returns a float64 array of shape (3,) with Y = 100: the column sums of `tristimulus_weights`.
    """
    return tristimulus_weights(illuminant, observer=observer).sum(axis=0)


def reflectance_to_xyz(refl, illuminant: str = "D65", *, observer: str = DEFAULT_OBSERVER):
    """CIE XYZ of reflectance spectra (ASTM E308, as colour-science's ``sd_to_XYZ``).

    Args:
      refl: reflectance, shape (..., 31), sampled 400..700 nm every 10 nm, 1 = perfect diffuser.
      illuminant: "D65", "A" or "F2" ("FL2" is accepted as colour-science's name for F2).
      observer: "CIE 1931 2 Degree Standard Observer" (default) or "CIE 1964 10 Degree Standard
        Observer" ("1931" / "1964" for short).

    Returns:
      XYZ, shape (..., 3), scaled so that the perfect diffuser has Y = 100; float32 unless `refl`
      is float64.
    """
    weights = tristimulus_weights(illuminant, observer=observer)
    refl = _checks.as_array("refl", refl)
    _checks.require_last_axis("refl", refl, N_WAVELENGTHS, "reflectance at 400..700 nm step 10")
    dtype = _checks.float_dtype(refl)
    return jnp.matmul(refl.astype(dtype), jnp.asarray(weights, dtype=dtype), precision=_HIGHEST)


def _lab_f(t):
    """CIE 1976 companding f(t): cube root above epsilon, the linear segment below (CIE 15:2004).

    Safe-where: cbrt has an infinite derivative at 0 and a NaN one below, and `jnp.where` only
    masks the value, not the gradient, so the cube root is fed a harmless 1 on the linear branch.
    """
    above = t > _LAB_EPSILON
    cube_root = _cube_root_positive(jnp.where(above, t, 1.0))
    return jnp.where(above, cube_root, (_LAB_KAPPA / 116.0) * t + 16.0 / 116.0)


def _cube_root_positive(x):
    """x^(1/3) for x > 0: exp(log(x) / 3), then one Newton step.

    Written out because XLA's CPU `cbrt` is slow: 22 ms for 3 x 10^6 float32 values on 2 cores
    against 2-4 ms for exp and log, which XLA vectorises. exp(log(x) / 3) alone is off by up to
    about |log x| ulp (the rounding of log x, scaled by exp); the Newton step for y^3 = x takes
    that to within 1 ulp of `jnp.cbrt` in float32 and 3 ulp in float64 over 1e-6..1e6 (tested),
    for one division more.
    """
    y = jnp.exp(jnp.log(x) * (1.0 / 3.0))
    return y + (x / (y * y) - y) * (1.0 / 3.0)


def xyz_to_lab(xyz, white_xyz):
    """CIE 1976 L*a*b* from XYZ relative to a reference white.

    Args:
      xyz: shape (..., 3), any scale.
      white_xyz: the reference white in the same scale, shape (3,) or broadcastable to `xyz`.

    Returns:
      Lab, shape (..., 3): L* in 0..100 for 0 <= Y <= Y_n.
    """
    xyz = _checks.as_array("xyz", xyz)
    white_xyz = _checks.as_array("white_xyz", white_xyz)
    _checks.require_last_axis("xyz", xyz, 3, "X, Y, Z")
    _checks.require_last_axis("white_xyz", white_xyz, 3, "X_n, Y_n, Z_n")
    _checks.require_broadcastable("white_xyz", white_xyz, "xyz", xyz.shape)
    dtype = _checks.float_dtype(xyz, white_xyz)
    f = _lab_f(xyz.astype(dtype) / white_xyz.astype(dtype))
    f_x, f_y, f_z = f[..., 0], f[..., 1], f[..., 2]
    return jnp.stack([116.0 * f_y - 16.0, 500.0 * (f_x - f_y), 200.0 * (f_y - f_z)], axis=-1)


def reflectance_to_lab(refl, illuminant: str = "D65", *, observer: str = DEFAULT_OBSERVER):
    """CIELAB of reflectance spectra, white = the perfect diffuser under the same illuminant.

    Args:
      refl: shape (..., 31), 400..700 nm step 10. See `reflectance_to_xyz` for the options.

    Returns:
      Lab, shape (..., 3).
    """
    xyz = reflectance_to_xyz(refl, illuminant, observer=observer)
    white = jnp.asarray(white_point_xyz(illuminant, observer=observer), dtype=xyz.dtype)
    return xyz_to_lab(xyz, white)


@jax.custom_jvp
def _safe_sqrt(x):
    """sqrt that is 0 with a zero gradient for x <= 0 (where sqrt's gradient is inf or NaN).

    NaN stays NaN: a bad pixel must never turn into a plausible number (jnp.maximum propagates
    NaN). The gradient rule is written out (`_safe_sqrt_jvp`) rather than obtained with the
    double-where idiom, which reads x three times: XLA then keeps x in memory instead of fusing
    it into the sqrt, and in `delta_e_2000` that cost a fifth of the float64 time.
    """
    return jnp.sqrt(jnp.maximum(x, 0.0))


@_safe_sqrt.defjvp
def _safe_sqrt_jvp(primals, tangents):
    (x,), (x_dot,) = primals, tangents
    root = _safe_sqrt(x)
    positive = x > 0
    return root, jnp.where(positive, 0.5 / jnp.where(positive, root, 1.0), 0.0) * x_dot


def _hue_angle_degrees(b, a_prime):
    """h' = atan2(b, a') in [0, 360) degrees; 0 for a' = b = 0 (Sharma et al. 2005, Eq. 4).

    `angles.atan2_degrees` gives 0 at the origin with a finite gradient, so the origin needs no
    special case here (with `jnp.arctan2` it did: its gradient there is 0/0).
    """
    h = atan2_degrees(b, a_prime)
    return jnp.where(h < 0, h + 360.0, h)


# Constants of T (Eq. 15) for the angle-sum identities in `delta_e_2000`.
_COS_30, _SIN_30 = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
_COS_6, _SIN_6 = math.cos(math.radians(6.0)), math.sin(math.radians(6.0))
_COS_63, _SIN_63 = math.cos(math.radians(63.0)), math.sin(math.radians(63.0))


def delta_e_2000(lab1, lab2, *, k_L: float = 1.0, k_C: float = 1.0, k_H: float = 1.0):
    """CIEDE2000 colour difference (CIE 142-2001), as written out by Sharma et al. (2005).

    Args:
      lab1, lab2: CIELAB, shape (..., 3) each, broadcastable to one another.
      k_L, k_C, k_H: parametric weighting factors (1 for reference conditions).

    Returns:
      ΔE00, shape (...) (the broadcast leading shape). Non-negative and symmetric; gradients are
      finite everywhere the value is (identical colours, zero chroma and the hue wrap included).
    """
    lab1 = _checks.as_array("lab1", lab1)
    lab2 = _checks.as_array("lab2", lab2)
    _checks.require_last_axis("lab1", lab1, 3, "L*, a*, b*")
    _checks.require_last_axis("lab2", lab2, 3, "L*, a*, b*")
    try:
        jnp.broadcast_shapes(lab1.shape, lab2.shape)
    except ValueError:
        raise ValueError(
            f"lab1, lab2: shapes {tuple(lab1.shape)} and {tuple(lab2.shape)} do not broadcast"
        ) from None
    dtype = _checks.float_dtype(lab1, lab2)
    arguments = (lab1.astype(dtype), lab2.astype(dtype), k_L, k_C, k_H)
    if all(_checks.is_concrete(x) for x in arguments):
        return _delta_e_2000_compiled(*arguments)
    return _delta_e_2000(*arguments)  # traced by a caller's jit, grad or vmap: part of its program


def _delta_e_2000(lab1, lab2, k_L, k_C, k_H):
    """Eq. 1-22 of Sharma et al. (2005) on checked Lab arrays of one float dtype (`delta_e_2000`)."""
    L_1, a_1, b_1 = lab1[..., 0], lab1[..., 1], lab1[..., 2]
    L_2, a_2, b_2 = lab2[..., 0], lab2[..., 1], lab2[..., 2]

    # Eq. 2-3: chroma and the a* rescaling G that lifts near-neutral colours.
    C_1 = _safe_sqrt(a_1**2 + b_1**2)
    C_2 = _safe_sqrt(a_2**2 + b_2**2)
    C_bar = (C_1 + C_2) / 2.0
    C_bar_7 = C_bar**7
    G = 0.5 * (1.0 - _safe_sqrt(C_bar_7 / (C_bar_7 + 25.0**7)))
    a_p_1 = (1.0 + G) * a_1
    a_p_2 = (1.0 + G) * a_2

    # Eq. 4-5.
    C_p_1 = _safe_sqrt(a_p_1**2 + b_1**2)
    C_p_2 = _safe_sqrt(a_p_2**2 + b_2**2)
    h_p_1 = _hue_angle_degrees(b_1, a_p_1)
    h_p_2 = _hue_angle_degrees(b_2, a_p_2)

    # Eq. 8-11: differences; the hue difference takes the short way round the circle.
    delta_L_p = L_2 - L_1
    delta_C_p = C_p_2 - C_p_1
    C_p_1_C_p_2 = C_p_1 * C_p_2
    chroma_zero = C_p_1_C_p_2 == 0
    h_diff = h_p_2 - h_p_1
    # |h1' - h2'| = 180° exactly (Sharma's pair 14) is decided from a', b: exactly opposite
    # hues take the unwrapped branch of Eq. 10 and 14. The two hue angles are rounded separately,
    # so their difference can come out an ulp either side of 180°. Two products compared for
    # equality (not a cross product tested against 0) so that no fused multiply-add can round
    # one side only.
    opposite = (a_p_1 * b_2 == a_p_2 * b_1) & (a_p_1 * a_p_2 + b_1 * b_2 < 0)
    wraps = (jnp.abs(h_diff) > 180.0) & ~opposite
    delta_h_p = jnp.where(wraps, jnp.where(h_diff > 0, h_diff - 360.0, h_diff + 360.0), h_diff)
    delta_h_p = jnp.where(chroma_zero, 0.0, delta_h_p)
    delta_H_p = 2.0 * _safe_sqrt(C_p_1_C_p_2) * sin_degrees(delta_h_p / 2.0)

    # Eq. 12-14: means; the hue mean also takes the short way (Eq. 14's four cases).
    L_bar_p = (L_1 + L_2) / 2.0
    C_bar_p = (C_p_1 + C_p_2) / 2.0
    h_sum = h_p_1 + h_p_2
    h_bar_p = jnp.where(
        ~wraps,
        h_sum / 2.0,
        jnp.where(h_sum < 360.0, (h_sum + 360.0) / 2.0, (h_sum - 360.0) / 2.0),
    )
    h_bar_p = jnp.where(chroma_zero, h_sum, h_bar_p)

    # Eq. 15-22: weighting functions and the rotation term.
    # T = 1 - 0.17 cos(h - 30°) + 0.24 cos(2h) + 0.32 cos(3h + 6°) - 0.20 cos(4h - 63°), written
    # with the angle-sum and multiple-angle identities from one cos and one sin of h: exact, and
    # two transcendental evaluations instead of four. All angles here are in degrees and go
    # through `spherejax.angles`, whose polynomials XLA vectorises (its own sin, cos and atan2
    # were 70 % of this function's time on CPU).
    sin_1, cos_1 = sincos_degrees(h_bar_p)
    cos_2, sin_2 = 2.0 * cos_1 * cos_1 - 1.0, 2.0 * sin_1 * cos_1
    cos_3, sin_3 = cos_1 * (4.0 * cos_1 * cos_1 - 3.0), sin_1 * (3.0 - 4.0 * sin_1 * sin_1)
    cos_4, sin_4 = 2.0 * cos_2 * cos_2 - 1.0, 2.0 * sin_2 * cos_2
    T = (
        1.0
        - 0.17 * (cos_1 * _COS_30 + sin_1 * _SIN_30)
        + 0.24 * cos_2
        + 0.32 * (cos_3 * _COS_6 - sin_3 * _SIN_6)
        - 0.20 * (cos_4 * _COS_63 + sin_4 * _SIN_63)
    )
    delta_theta = 30.0 * jnp.exp(-(((h_bar_p - 275.0) / 25.0) ** 2))
    C_bar_p_7 = C_bar_p**7
    R_C = 2.0 * _safe_sqrt(C_bar_p_7 / (C_bar_p_7 + 25.0**7))
    L_bar_p_50_2 = (L_bar_p - 50.0) ** 2
    S_L = 1.0 + 0.015 * L_bar_p_50_2 / jnp.sqrt(20.0 + L_bar_p_50_2)
    S_C = 1.0 + 0.045 * C_bar_p
    S_H = 1.0 + 0.015 * C_bar_p * T
    R_T = -sin_degrees(2.0 * delta_theta) * R_C

    # The three quotients of Eq. 23 from one division: divisions (and square roots) are what is
    # left of this function's cost on CPU, and each one XLA materialises as a pass over memory.
    # S_L, S_C, S_H >= 1 (T is within 0.36..1.58), so the product neither overflows nor loses
    # precision.
    inverse = 1.0 / (S_L * S_C * S_H)
    L_term = delta_L_p * (S_C * S_H * inverse) / k_L
    C_term = delta_C_p * (S_L * S_H * inverse) / k_C
    H_term = delta_H_p * (S_L * S_C * inverse) / k_H
    # Eq. 23. The radicand is >= 0 (|R_T| < 2); identical colours give exactly 0, where sqrt's
    # gradient would be infinite.
    return _safe_sqrt(L_term**2 + C_term**2 + H_term**2 + R_T * C_term * H_term)


# A direct call is one compiled program rather than some 150 operations dispatched one by one.
# 512-bit vectors: XLA's CPU default is 256 bits (some Intel CPUs slow their clock for 512-bit
# code). On the reference machine (AMD EPYC, AVX-512) 512 bits make ΔE00 about 20 % faster in
# float64 and 5-15 % in float32 (benchmarks/README.md); without AVX-512 the option changes
# nothing. JAX takes compiler options only on an outermost jit, hence the two entry points.
_delta_e_2000_compiled = jax.jit(_delta_e_2000, compiler_options={"xla_cpu_prefer_vector_width": 512})


__all__ = [
    "ILLUMINANTS",
    "OBSERVERS",
    "DEFAULT_OBSERVER",
    "tristimulus_weights",
    "white_point_xyz",
    "reflectance_to_xyz",
    "xyz_to_lab",
    "reflectance_to_lab",
    "delta_e_2000",
]
