"""Measurement uncertainty by first-order propagation through the per-pixel path (the GUM).

JCGM 100:2008 (the GUM), Sec. 5.1, the law of propagation of uncertainty: for y = f(x) with
input covariance U_x, U_y = J U_x Jᵀ, J = ∂f/∂x at the measured x. Here f is the same jax.numpy
path `spherejax.correct` runs (flat field, Eq. 10 -> Stage I and II, Eq. 17 and 23 -> the affine
Wiener estimate -> XYZ -> CIELAB), and J comes from JAX (`jax.linearize` and `jax.jvp`), not
from a second, hand-derived formula that could drift from the code it describes.

What is propagated (`NoiseModel`), per band b, in raw counts:

    N1  a raw count x averaged over n frames, dark-subtracted signal s = x - dark:
          var(x) = (max(s, 0) / gain + read_noise²) / n                (shot + read noise)
    N2  the dark frame (averaged over dark_frames): var = read_noise² / dark_frames
    N3  the white-standard frame (white_frames): var = (max(white - dark, 0) / gain
          + read_noise²) / white_frames
    N4  the white-patch ratio p (Eq. 14-15): its variance from N1-N3 over the patch's pixels,
          by the gradient of p with respect to each of them (`patch_ratio_std`)
    N5  the white standard's certified reflectance: a relative standard uncertainty per band
          that scales the flat field of every pixel of every image
    N6  the Stage II coefficients (c1..c4 of each band, Eq. 23): their (B, 4, 4) covariance from
          the fit (`spherejax.polynomial.Stage2Fit.covariance`)
    N7  the reflectance estimator's parameters, from a finite set of targets
          (`spherejax.estimation.EstimatorCovariance`): Cov(r | x) = (x̃ᵀ G x̃) Σ_res
    N8  the kernel residual's own predictive variance (E15 of `spherejax.estimation.estimator`,
          `ResidualVariance`), where the calibration's estimator is the kernel one and carries
          it (`Calibration.wiener_residual.variance`): at each pixel's v_tilde,
          Cov(r) = Σ_j var_j(v_tilde) P_j P_jᵀ, so var(r_w) = Σ_j var_j P_jw² and
          Cov(XYZ) = Σ_j var_j (P_jᵀ T)ᵀ (P_jᵀ T), T the tristimulus weights (31, 3). Not part of
          the `NoiseModel`: it comes with the estimator, and is added whenever a noise model asks
          for uncertainties. Its `noise` (the scatter of a target's measured reflectance about
          the fit) is not added: it is the reference instrument's noise and the residual beyond
          rank r, not an uncertainty of this estimate

Bands are exposed separately, so N1-N6 are independent between bands, and the first three
steps of the path act band by band: each source's effect on the Stage II response v_tilde is a
tangent of that band alone. So one `jax.linearize` of the band-wise path and one tangent per
source give every source's standard deviation of v_tilde (..., B); the linear Wiener step
carries them to reflectance and XYZ through its Jacobian (its matrix, taken with `jax.jacfwd`),
and `jax.jvp` of `xyz_to_lab` at each pixel gives the 3 x 3 Jacobian of Lab.

N1-N3 differ from pixel to pixel and average down over a region (`spherejax.measure`); N4-N8
are common to every pixel of an image (N4) or of every image (N5-N8) and do not (N8 is one
function for every pixel, its variance taken at each pixel's response).

What first order leaves out, and where it breaks down (docs/uncertainty.md has the Monte Carlo
comparison): ΔE00 near 0 (its distribution is a folded one, not Gaussian, and its derivative
is 0 at 0, so the propagated u is 0 there), very dark pixels (few counts; L* near 0), the
correlation between a pixel inside the white patch and p (the patch is white, not the sample),
and every model error: Stage II's residual background effect, the estimator's bias on materials
unlike its targets, fluorescence.
"""

from __future__ import annotations

from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _checks
from .colorimetry import xyz_to_lab
from .flatfield import flat_field_unchecked, patch_ratio_weighted
from .polynomial import stage2_unchecked
from .estimation import EstimatorCovariance
from .noise_bands import band_problem

_HIGHEST = jax.lax.Precision.HIGHEST

#: The sources of `band_tangents`, in the order of the budget tables: pixel noise first (these
#: average down over a region), then the common terms.
PIXEL_SOURCES = ("sample frame", "dark frame", "white frame")
COMMON_SOURCES = ("white-patch ratio", "white standard", "Stage II coefficients")
#: The estimator's term (N7) acts on the reflectance, not on v_tilde.
ESTIMATOR_SOURCE = "reflectance estimator"
#: The kernel residual's own variance (N8), on the reflectance too; only with a kernel estimator
#: that carries it (`Calibration.wiener_residual.variance`).
RESIDUAL_SOURCE = "kernel residual"
SOURCES = (*PIXEL_SOURCES, *COMMON_SOURCES, ESTIMATOR_SOURCE, RESIDUAL_SOURCE)


def _positive(name: str, x, *, minimum: float = 0.0, strict: bool = True) -> None:
    if not _checks.is_concrete(x):
        return
    values = np.asarray(x, np.float64)
    ok = np.isfinite(values) & ((values > minimum) if strict else (values >= minimum))
    if not np.all(ok):
        bound = f"> {minimum:g}" if strict else f">= {minimum:g}"
        raise ValueError(f"NoiseModel: {name} expected finite numbers {bound}, got {values.tolist()}")


def _band_parameter(name: str, x) -> jax.Array:
    x = jnp.asarray(x)
    if x.ndim > 1:
        raise ValueError(f"NoiseModel: {name} expected a number or one value per band (B,), got shape {tuple(x.shape)}")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.float32)
    return x


class NoiseModel(eqx.Module):
    """The camera's noise and the calibration's uncertainties, for `correct(..., noise=)` and
    `measure` (module docstring, N1-N7). A pytree: its numbers are leaves, so one compiled
    program serves every noise model of the same structure.

    Fields:
      gain: electrons per count (> 0), a number or (B,).
      read_noise: read noise of one frame in counts rms (>= 0), a number or (B,).
      dark_frames: frames averaged in the calibration's dark frame (>= 1).
      white_frames: frames averaged in the calibration's white-standard frame (>= 1).
      sample_frames: frames averaged in the sample frames being corrected (>= 1; default 1).
      white_reflectance_u: relative standard uncertainty of the white standard's certified
        reflectance (e.g. 0.003 for 0.3 %), a number or (B,); default 0. It scales the flat field
        of every pixel of every image alike. Leave it 0 when the estimator's targets were measured
        against this same white standard (the error then cancels between training and use); set
        it when the scale of reflectance rests on the certificate (an estimator built from a
        known sensitivity, targets measured against another standard).
      coeffs_covariance: (B, 4, 4) covariance of the Stage II coefficients c1..c4 of each band
        (`fit_stage2_detailed(...).covariance`), or None (coefficients taken as exact).
      estimator_covariance: the reflectance estimator's `EstimatorCovariance`, or None.
    """

    gain: jax.Array = eqx.field(converter=lambda x: _band_parameter("gain", x))
    read_noise: jax.Array = eqx.field(converter=lambda x: _band_parameter("read_noise", x))
    dark_frames: jax.Array = eqx.field(converter=lambda x: jnp.asarray(x, jnp.float32), default=1)
    white_frames: jax.Array = eqx.field(converter=lambda x: jnp.asarray(x, jnp.float32), default=1)
    sample_frames: jax.Array = eqx.field(converter=lambda x: jnp.asarray(x, jnp.float32), default=1)
    white_reflectance_u: jax.Array = eqx.field(
        converter=lambda x: _band_parameter("white_reflectance_u", x), default=0.0
    )
    coeffs_covariance: jax.Array | None = eqx.field(
        converter=lambda x: None if x is None else jnp.asarray(x), default=None
    )
    estimator_covariance: EstimatorCovariance | None = None

    def __check_init__(self):
        _positive("gain (electrons per count)", self.gain)
        _positive("read_noise (counts rms)", self.read_noise, strict=False)
        for name in ("dark_frames", "white_frames", "sample_frames"):
            value = getattr(self, name)
            if value.ndim != 0:
                raise ValueError(f"NoiseModel: {name} expected one number of frames, got shape {tuple(value.shape)}")
            _positive(f"{name} (frames averaged)", value, minimum=1.0, strict=False)
        _positive("white_reflectance_u (relative)", self.white_reflectance_u, strict=False)
        if self.coeffs_covariance is not None:
            shape = tuple(self.coeffs_covariance.shape)
            if len(shape) != 3 or shape[1:] != (4, 4):
                raise ValueError(f"NoiseModel: coeffs_covariance expected shape (B, 4, 4), got {shape}")
        if self.estimator_covariance is not None and not isinstance(self.estimator_covariance, EstimatorCovariance):
            raise ValueError(
                "NoiseModel: estimator_covariance expected a spherejax.EstimatorCovariance or None, "
                f"got {type(self.estimator_covariance).__name__}"
            )

    def check_bands(self, bands: int) -> None:
        """Raise ValueError unless every per-band field fits `bands` bands (`band_problem`)."""
        estimator = self.estimator_covariance
        problem = band_problem(
            {
                "gain": self.gain.shape, "read_noise": self.read_noise.shape,
                "white_reflectance_u": self.white_reflectance_u.shape,
                "coeffs_covariance": None if self.coeffs_covariance is None else self.coeffs_covariance.shape,
                "estimator_covariance.gram": None if estimator is None else estimator.gram.shape,
            },
            bands,
        )
        if problem is not None:
            raise ValueError(f"NoiseModel: {problem}")

    # -- the variances of N1-N3, in counts² ---------------------------------------------------

    def _frame_variance(self, signal, frames):
        dtype = signal.dtype
        gain, read, frames = (x.astype(dtype) for x in (self.gain, self.read_noise, frames))
        return (jnp.maximum(signal, 0.0) / gain + read**2) / frames

    def raw_variance(self, raw, dark):
        """N1: variance of the sample's counts (..., B) given the dark frame (counts², the
        computation's dtype)."""
        return self._frame_variance(raw - dark, self.sample_frames)

    def dark_variance(self, dark):
        """N2: variance of the averaged dark frame, shaped like `dark` (counts²): its
        dark-subtracted signal is 0, so read noise alone."""
        return self._frame_variance(jnp.zeros_like(dark), self.dark_frames)

    def white_variance(self, white, dark):
        """N3: variance of the averaged white-standard frame (counts²)."""
        return self._frame_variance(white - dark, self.white_frames)

    # -- files ------------------------------------------------------------------------------------

    def to_json(self) -> dict:
        """Plain JSON (numbers and lists, every number a float64) that `from_json` reads back
        exactly: the model's document (`spherejax.noise_document`, which says what each key
        holds)."""
        from .noise_document import NoiseModelDocument  # pydantic only when a model is written

        return NoiseModelDocument.of(self).model_dump()

    @classmethod
    def from_json(cls, doc: Mapping, *, bands: int | None = None) -> NoiseModel:
        """The model `to_json` wrote, its per-band values checked against `bands` bands when
        given; ValueError on one line naming the key, the value found and what was expected on
        anything else (`spherejax.noise_document`)."""
        from .noise_document import check  # pydantic only when a model is read

        checked = check(doc, bands=bands)
        estimator = checked.estimator_covariance
        return cls(
            gain=checked.gain_e_per_count,
            read_noise=checked.read_noise_counts,
            dark_frames=checked.dark_frames,
            white_frames=checked.white_frames,
            sample_frames=checked.sample_frames,
            white_reflectance_u=checked.white_reflectance_u,
            coeffs_covariance=checked.coeffs_covariance,
            estimator_covariance=None if estimator is None else EstimatorCovariance(
                gram=estimator.gram, residual=estimator.residual,
            ),
        )


def check_noise(noise, bands: int) -> NoiseModel | None:
    """`noise` if it is a NoiseModel for `bands` bands (or None); ValueError otherwise."""
    if noise is None:
        return None
    if not isinstance(noise, NoiseModel):
        raise ValueError(f"noise: expected a spherejax.NoiseModel or None, got {type(noise).__name__}")
    noise.check_bands(bands)
    return noise


# ------------------------------------------------------------------------------ propagation


def patch_ratio_std(raw_f, dark, white, weights, noise: NoiseModel):
    """N4: standard uncertainty of the white-patch ratio p (Eq. 14-15) from the patch's pixels.

    Args:
      raw_f: (..., h, w, B) float, the sample frames over the patch's box.
      dark, white: (h, w, B) float, the calibration's frames over the same box.
      weights: (..., h, w) float, the patch weights with unusable pixels at 0 (as `correct`
        computes p).
      noise: the `NoiseModel`.

    Returns:
      u(p), (..., B), same dtype. p_b depends on band b only, so the gradient of Σ_b p_b with
      respect to each pixel's count is ∂p_b/∂x: one reverse pass gives every pixel's
      sensitivity, and var(p_b) = Σ_pixels (∂p_b/∂x)² var(x) over the sample, dark and white
      counts (independent pixels).
    """
    lead = raw_f.shape[:-3]
    images = int(np.prod(lead, dtype=np.int64))
    raw_flat = raw_f.reshape(images, *raw_f.shape[-3:])
    weights_flat = jnp.broadcast_to(weights, (*lead, *weights.shape[-2:])).reshape(images, *weights.shape[-2:])

    def one_image(raw_one, weights_one):
        def total(raw_x, dark_x, white_x):
            return jnp.sum(patch_ratio_weighted(raw_x, dark_x, white_x, weights_one[..., None]))

        g_raw, g_dark, g_white = jax.grad(total, argnums=(0, 1, 2))(raw_one, dark, white)
        variance = (
            g_raw**2 * noise.raw_variance(raw_one, dark)
            + g_dark**2 * noise.dark_variance(dark)
            + g_white**2 * noise.white_variance(white, dark)
        )
        return jnp.sqrt(jnp.sum(variance, axis=(-3, -2)))

    return jax.vmap(one_image)(raw_flat, weights_flat).reshape(*lead, raw_f.shape[-1])


def band_tangents(raw_f, dark, white, p, p_std, coeffs, noise: NoiseModel):
    """Every source's signed effect on the Stage II response v_tilde, band by band.

    The band-wise part of the path, v_tilde = Stage II(s · flat_field(raw, dark, white), p)
    (Eq. 10, 23; s = 1 is the white standard's reflectance scale), is linearised once
    (`jax.linearize`); each source's tangent is its standard deviation in the direction of its
    input, so the tangent's output is that source's standard deviation of v_tilde, with sign
    (the sign matters when a common source is averaged over a region).

    Args:
      raw_f: (..., H, W, B) float sample frames. dark, white: (H, W, B) float.
      p: (..., 1, 1, B) white-patch ratio; p_std: the same shape, u(p) (`patch_ratio_std`).
      coeffs: (B, 4) Stage II coefficients.
      noise: the `NoiseModel`.

    Returns:
      (v_tilde, tangents, coeff_jacobian):
        v_tilde (..., H, W, B);
        tangents: {source: (..., H, W, B)} for `PIXEL_SOURCES` and the white-patch ratio and
          white standard;
        coeff_jacobian: (..., H, W, B, 4), ∂v_tilde_b/∂c_bk, for the Stage II coefficients'
          covariance (N6), or None when the model has none.
    """
    dtype = raw_f.dtype
    bands = raw_f.shape[-1]

    def band_path(raw_x, dark_x, white_x, p_x, scale, coeffs_x):
        return stage2_unchecked(flat_field_unchecked(raw_x, dark_x, white_x) * scale, p_x, coeffs_x)

    primals = (raw_f, dark, white, p, jnp.ones((bands,), dtype), coeffs)
    v_tilde, linear = jax.linearize(band_path, *primals)
    zeros = [jnp.zeros_like(x) for x in primals]

    def along(index, tangent):
        tangents = list(zeros)
        tangents[index] = jnp.broadcast_to(tangent, primals[index].shape).astype(dtype)
        return linear(*tangents)

    tangents = {
        "sample frame": along(0, jnp.sqrt(noise.raw_variance(raw_f, dark))),
        "dark frame": along(1, jnp.sqrt(noise.dark_variance(dark))),
        "white frame": along(2, jnp.sqrt(noise.white_variance(white, dark))),
        "white-patch ratio": along(3, p_std),
        "white standard": along(4, jnp.broadcast_to(noise.white_reflectance_u, (bands,))),
    }
    coeff_jacobian = None
    if noise.coeffs_covariance is not None:
        eye = jnp.eye(4, dtype=dtype)
        coeff_jacobian = jnp.stack([along(5, jnp.broadcast_to(eye[k], (bands, 4))) for k in range(4)], axis=-1)
    return v_tilde, tangents, coeff_jacobian


def coefficient_variance(coeff_jacobian, coeffs_covariance):
    """N6: var(v_tilde_b) = g_bᵀ C_b g_b with g_b = ∂v_tilde_b/∂c_b (..., B, 4) and C (B, 4, 4)."""
    return jnp.einsum("...bk,bkl,...bl->...b", coeff_jacobian, coeffs_covariance.astype(coeff_jacobian.dtype), coeff_jacobian)


def linear_jacobians(wiener, wiener_offset, weights):
    """The Jacobians of the affine estimate and of XYZ with respect to v_tilde, by `jax.jacfwd`.

    Returns (J_r (31, B), J_xyz (3, B)): the derivative of r = W v_tilde + r0 and of
    XYZ = r · weights (ASTM E308) with respect to v_tilde (constant: the map is affine).
    """
    bands = wiener.shape[1]

    def estimate(v_tilde):
        reflectance = jnp.matmul(wiener, v_tilde, precision=_HIGHEST) + wiener_offset
        return reflectance, jnp.matmul(reflectance, weights, precision=_HIGHEST)

    return jax.jacfwd(estimate)(jnp.zeros((bands,), wiener.dtype))


def _kernel_estimate_variances(v_tilde, variance, j_affine, weights, residual):
    """(reflectance variance (..., 31), XYZ covariance (..., 3, 3)) of an estimate with a kernel
    residual, r = W v_tilde + r0 + A k(v_tilde) (E8), by first order at each pixel's v_tilde:
    column b of the Jacobian is W[:, b] + ∂(A k)/∂v_b, the latter one tangent of the residual
    linearised once (`jax.linearize`), the bands independent as in the affine case."""
    _, tangent_of = jax.linearize(residual, v_tilde)
    bands = v_tilde.shape[-1]
    eye = jnp.eye(bands, dtype=v_tilde.dtype)
    reflectance_var = jnp.zeros((*v_tilde.shape[:-1], j_affine.shape[0]), v_tilde.dtype)
    xyz_cov = jnp.zeros((*v_tilde.shape[:-1], 3, 3), v_tilde.dtype)
    for b in range(bands):
        column = j_affine[:, b] + tangent_of(jnp.broadcast_to(eye[b], v_tilde.shape))  # (..., 31)
        xyz_column = jnp.matmul(column, weights, precision=_HIGHEST)  # (..., 3)
        var_b = variance[..., b, None]
        reflectance_var = reflectance_var + var_b * column**2
        xyz_cov = xyz_cov + var_b[..., None] * xyz_column[..., :, None] * xyz_column[..., None, :]
    return reflectance_var, xyz_cov


def residual_variances(v_tilde, residual, weights):
    """N8: (reflectance variance (..., 31), XYZ covariance (..., 3, 3)) of the kernel residual's
    own uncertainty at responses v_tilde (..., B) (E15), for a `KernelResidual` whose `variance`
    is not None and tristimulus weights T (31, 3):

        var(r_w) = Σ_j var_j(v) P_jw²,   Cov(XYZ) = Σ_j var_j(v) (P_jᵀ T)ᵀ (P_jᵀ T)

    with P (r, 31) the residual's components and var_j (..., r) their predictive variances
    (`ResidualVariance.component_variance`). The components are independent Gaussian processes
    (E13-E15), hence a sum of rank-one terms."""
    variance = residual.variance
    component_var = variance.component_variance(residual.features(v_tilde))  # (..., r)
    P = variance.components.astype(v_tilde.dtype)
    reflectance_var = jnp.matmul(component_var, P * P, precision=_HIGHEST)
    P_xyz = jnp.matmul(P, weights, precision=_HIGHEST)  # (r, 3): each component's XYZ
    pairs = (P_xyz[:, :, None] * P_xyz[:, None, :]).reshape(P.shape[0], 9)
    xyz_cov = jnp.matmul(component_var, pairs, precision=_HIGHEST).reshape(*component_var.shape[:-1], 3, 3)
    return reflectance_var, xyz_cov


def residual_covariance(v_tilde, residual):
    """N8's full reflectance covariance (..., 31, 31) at responses v_tilde (..., B): Σ_j var_j(v)
    P_j P_jᵀ (`residual_variances`; a region's mean, `spherejax.measure`)."""
    variance = residual.variance
    component_var = variance.component_variance(residual.features(v_tilde))
    P = variance.components.astype(v_tilde.dtype)
    return jnp.einsum("...j,jw,jx->...wx", component_var, P, P, precision=_HIGHEST)


def lab_jacobian(xyz, white_xyz):
    """(..., 3, 3) ∂Lab/∂XYZ at every pixel: `xyz_to_lab` linearised once (`jax.linearize`),
    then one tangent per column (the map acts pixel by pixel, so a tangent of e_i at every pixel
    gives column i)."""
    _, linear = jax.linearize(lambda x: xyz_to_lab(x, white_xyz), xyz)
    eye = jnp.eye(3, dtype=xyz.dtype)
    return jnp.stack([linear(jnp.broadcast_to(eye[i], xyz.shape)) for i in range(3)], axis=-1)


def congruence_3x3(jacobian, covariance):
    """J Σ Jᵀ for (..., 3, 3) stacks, written out element by element: XLA on CPU runs a batched
    3 x 3 dot (what einsum gives) as millions of tiny matrix products, several times slower than
    the same sums as one fused elementwise loop."""
    rows = []
    for i in range(3):
        # (J Σ)[i, k] = Σ_j J[i, j] Σ[j, k]
        js = [sum(jacobian[..., i, j] * covariance[..., j, k] for j in range(3)) for k in range(3)]
        rows.append([sum(js[k] * jacobian[..., l, k] for k in range(3)) for l in range(3)])
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)


def estimator_scale(v_tilde, estimator_covariance: EstimatorCovariance):
    """N7's x̃ᵀ G x̃ for x̃ = (v_tilde, 1): Cov(r) from the estimator is this times Σ_res."""
    gram = estimator_covariance.gram.astype(v_tilde.dtype)
    bands = v_tilde.shape[-1]
    # x̃ᵀ G x̃ = vᵀ G_vv v + 2 G_v1 · v + G_11, without concatenating a column of ones.
    quadratic = jnp.sum(jnp.matmul(v_tilde, gram[:bands, :bands], precision=_HIGHEST) * v_tilde, axis=-1)
    return quadratic + 2.0 * jnp.matmul(v_tilde, gram[:bands, bands], precision=_HIGHEST) + gram[bands, bands]


def pixel_uncertainty(raw_f, good, p, p_std, constants, noise: NoiseModel):
    """Per-pixel standard uncertainties of reflectance and the covariance of Lab (N1-N8).

    Args:
      raw_f: (..., H, W, B) float; good: (..., H, W, 1) bool, the pixels `correct` keeps; p,
        p_std: (..., B); constants: the calibration's arrays (`PixelConstants`: dark, white
        (H, W, B), coeffs (B, 4), wiener W (31, B), wiener_offset r0 (31,), tristimulus_weights
        (31, 3)); all one float dtype.
      noise: the `NoiseModel`.

    Returns:
      (reflectance_u (..., H, W, 31), lab_covariance (..., H, W, 3, 3)); NaN where not `good`.
      With a kernel residual that carries its variance (`constants.wiener_residual.variance`),
      its own uncertainty at each pixel's v_tilde (N8) is added; without one, nothing of N8 is
      traced (the same program as before).
    """
    dark, white, coeffs = constants.dark, constants.white, constants.coeffs
    wiener, wiener_offset, weights = constants.wiener, constants.wiener_offset, constants.tristimulus_weights
    dtype = raw_f.dtype
    # Safe-where, as in `correct`: bad pixels continue as harmless numbers and become NaN at the
    # end, so that nothing here raises or poisons a gradient.
    raw_safe = jnp.where(good, raw_f, white)
    p_pixel, p_std_pixel = p[..., None, None, :], p_std[..., None, None, :]
    v_tilde, tangents, coeff_jacobian = band_tangents(raw_safe, dark, white, p_pixel, p_std_pixel, coeffs, noise)
    variance = sum(t**2 for t in tangents.values())  # (..., H, W, B), bands independent
    if coeff_jacobian is not None:
        variance = variance + coefficient_variance(coeff_jacobian, noise.coeffs_covariance)
    variance = jnp.where(good, variance, 0.0)
    v_tilde = jnp.where(good, v_tilde, 0.0)

    j_reflectance, j_xyz = linear_jacobians(wiener, wiener_offset, weights)
    if constants.wiener_residual is None:
        reflectance_var = jnp.matmul(variance, (j_reflectance**2).T, precision=_HIGHEST)
        # Σ_xyz[i, j] = Σ_b J_ib J_jb var_b: one (B, 9) product per pixel.
        pairs = (j_xyz[:, None, :] * j_xyz[None, :, :]).reshape(9, -1).T
        xyz_cov = jnp.matmul(variance, pairs, precision=_HIGHEST).reshape(*variance.shape[:-1], 3, 3)
    else:
        reflectance_var, xyz_cov = _kernel_estimate_variances(v_tilde, variance, j_reflectance, weights, constants.wiener_residual)
    if noise.estimator_covariance is not None:
        scale = estimator_scale(v_tilde, noise.estimator_covariance)[..., None]
        residual = noise.estimator_covariance.residual.astype(dtype)
        reflectance_var = reflectance_var + scale * jnp.diagonal(residual)
        xyz_residual = jnp.matmul(weights.T, jnp.matmul(residual, weights, precision=_HIGHEST), precision=_HIGHEST)
        xyz_cov = xyz_cov + scale[..., None] * xyz_residual
    kernel = constants.wiener_residual
    if kernel is not None and kernel.variance is not None:
        own_reflectance_var, own_xyz_cov = residual_variances(v_tilde, kernel, weights)
        reflectance_var = reflectance_var + own_reflectance_var
        xyz_cov = xyz_cov + own_xyz_cov

    xyz = jnp.matmul(v_tilde, j_xyz.T, precision=_HIGHEST) + jnp.matmul(wiener_offset, weights, precision=_HIGHEST)
    if constants.wiener_residual is not None:
        xyz = xyz + jnp.matmul(constants.wiener_residual(v_tilde), weights, precision=_HIGHEST)
    jacobian = lab_jacobian(xyz, jnp.sum(weights, axis=0))
    lab_cov = congruence_3x3(jacobian, xyz_cov)
    reflectance_u = jnp.where(good, jnp.sqrt(reflectance_var), jnp.nan)
    lab_cov = jnp.where(good[..., None], lab_cov, jnp.nan)
    return reflectance_u, lab_cov


def delta_e_uncertainty(lab, lab_covariance, reference, reference_covariance=None):
    """Standard uncertainty of ΔE00(lab, reference) by first order: u² = g Σ gᵀ, g = ∇ΔE00.

    Args:
      lab: (..., 3); lab_covariance: (..., 3, 3).
      reference: (3,) or (..., 3); reference_covariance: its (..., 3, 3) covariance, or None for
        an exact reference (a standard's certified values, a typed-in colour).

    Returns:
      u(ΔE00), (...). 0 where ΔE00 = 0: the first-order term vanishes there (ΔE00 is a norm), so
      near 0 it understates the spread, whose distribution is not Gaussian (docs/uncertainty.md).
    """
    from .colorimetry import _delta_e_2000  # the checked wrapper would re-check inside grad

    lab = jnp.asarray(lab)
    reference = jnp.broadcast_to(jnp.asarray(reference, lab.dtype), lab.shape)

    def one(l1, l2):
        return _delta_e_2000(l1, l2, 1.0, 1.0, 1.0)

    flat1, flat2 = lab.reshape(-1, 3), reference.reshape(-1, 3)
    g1, g2 = jax.vmap(jax.grad(one, argnums=(0, 1)))(flat1, flat2)
    g1, g2 = g1.reshape(lab.shape), g2.reshape(lab.shape)
    variance = jnp.einsum("...i,...ij,...j->...", g1, lab_covariance, g1)
    if reference_covariance is not None:
        variance = variance + jnp.einsum("...i,...ij,...j->...", g2, jnp.asarray(reference_covariance, lab.dtype), g2)
    return jnp.sqrt(jnp.maximum(variance, 0.0))


__all__ = [
    "NoiseModel",
    "SOURCES",
    "PIXEL_SOURCES",
    "COMMON_SOURCES",
    "ESTIMATOR_SOURCE",
    "RESIDUAL_SOURCE",
    "check_noise",
    "band_problem",
    "patch_ratio_std",
    "band_tangents",
    "coefficient_variance",
    "linear_jacobians",
    "residual_variances",
    "residual_covariance",
    "lab_jacobian",
    "congruence_3x3",
    "estimator_scale",
    "pixel_uncertainty",
    "delta_e_uncertainty",
]
