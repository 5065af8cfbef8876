"""Correction Stage II of Zou et al. (2019): the per-band polynomial in v_s and p_s.

Stage I assumes Lambertian reflection; real samples are not Lambertian, stray light couples bright
and dark regions, and so a residual background effect remains. Section 4 models it per band with

    v_tilde = c1 p v + c2 v + c3 p + c4                                   (Eq. 18 / Eq. 23)

where v is the flat-fielded response (Eq. 10) and p the white-patch ratio (Eq. 15). Coefficients
are ordered (c1, c2, c3, c4) on the last axis of a (B, 4) array. Identity coefficients
(c1, c2, c3, c4) = (1, 0, 0, 0) reduce Stage II to Stage I (v_tilde = p v).

`fit_stage2` with loss "l2" is the least-squares problem of Eq. 19-22, solved per band.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from . import _checks

#: Stage II coefficients that make Stage II equal Stage I, per band: c1 = 1, c2 = c3 = c4 = 0.
IDENTITY_COEFFS = (1.0, 0.0, 0.0, 0.0)

#: Zou et al. (2019), Table 2: the coefficients fitted on the authors' instrument, (16, 4) ordered
#: c1..c4 for bands 1..16 (400..700 nm step 20). The paper prints one row per coefficient; here
#: they are columns, as `stage2` expects. A reference value, not a calibration for another system.
PAPER_TABLE_2 = np.array(
    [
        [0.8966, 0.8787, 0.9083, 0.9168, 0.9240, 0.9438, 0.9155, 0.9293,
         0.9445, 0.9123, 0.9155, 0.9249, 0.9118, 0.9309, 0.9276, 0.9452],
        [0.1158, 0.1337, 0.1000, 0.0901, 0.0824, 0.0613, 0.0934, 0.0792,
         0.0608, 0.0979, 0.0931, 0.0837, 0.0972, 0.0751, 0.0778, 0.0562],
        [0.2062, 0.2034, 0.2169, 0.1507, 0.1354, 0.0837, 0.1243, 0.0849,
         0.0782, 0.1105, 0.1059, 0.0793, 0.1000, 0.0803, 0.0951, 0.1040],
        [-0.2229, -0.2193, -0.2329, -0.1617, -0.1468, -0.0913, -0.1374, -0.0943,
         -0.0868, -0.1228, -0.1172, -0.0878, -0.1097, -0.0868, -0.1009, -0.1085],
    ]
).T
PAPER_TABLE_2.setflags(write=False)


#: The polynomial has four coefficients, so a band needs at least this many usable samples.
MIN_SAMPLES = 4


def identity_coeffs(bands: int = 16, dtype=jnp.float32):
    """Stage II coefficients that leave Stage I untouched: c1 = 1, c2 = c3 = c4 = 0.

    Returns shape (bands, 4) in `dtype`; `stage2(v, p, identity_coeffs())` equals `stage1(v, p)`.
    """
    return jnp.tile(jnp.asarray(IDENTITY_COEFFS, dtype=dtype), (bands, 1))


def stage2_unchecked(v, p, coeffs):
    """Eq. 23 on validated float arrays of one dtype; see `stage2`."""
    c_1, c_2, c_3, c_4 = coeffs[:, 0], coeffs[:, 1], coeffs[:, 2], coeffs[:, 3]
    return (c_1 * p + c_2) * v + c_3 * p + c_4


def stage2(v, p, coeffs):
    """Stage II corrected response v_tilde = (c1 p + c2) v + c3 p + c4 (Eq. 23).

    Args:
      v: flat-fielded response v_s (Eq. 10), shape (..., B).
      p: white-patch ratio p_s (Eq. 15), shape (B,) or broadcastable to `v`.
      coeffs: shape (B, 4), ordered c1, c2, c3, c4 (the paper's Table 2, transposed).

    Returns:
      v_tilde, shape of `v`.
    """
    v, p = _checks.response_and_ratio(v, p)
    coeffs = _checks.as_array("coeffs", coeffs)
    bands = v.shape[-1]
    _checks.require_shape("coeffs", coeffs, (bands, 4), f"c1..c4 for each of the {bands} bands")
    dtype = _checks.float_dtype(v, p, coeffs)
    return stage2_unchecked(v.astype(dtype), p.astype(dtype), coeffs.astype(dtype))


def _design_matrix(v, p):
    """M = (p ⊙ v, v, p, 1) of Eq. 20 for one band; v, p shape (n,) -> (n, 4)."""
    return jnp.stack([p * v, v, p, jnp.ones_like(v)], axis=-1)


# --------------------------------------------------------------------------------------------
# Robust losses. Residuals are scaled, u = e / s; each loss is defined by its IRLS weight
# w(u) = psi(u) / u. Tuning constants give 95 % efficiency at the Gaussian (Holland & Welsch
# 1977; Huber 1981): a robust fit of clean Gaussian data is nearly as precise as least squares.

#: Tuning constant c of each robust loss, in units of the residual scale s.
ROBUST_TUNING = {"huber": 1.345, "cauchy": 2.385, "tukey": 4.685}

#: Accepted values of `fit_stage2`'s `loss`.
LOSSES = ("l2", *ROBUST_TUNING)

#: Consistency factor of the median absolute deviation for Gaussian residuals: s = 1.4826 MAD.
MAD_TO_SIGMA = 1.4826

#: Per-band status codes of `Stage2Fit.status`. UNDETERMINED: the band's usable samples cannot
#: determine c1..c4 (fewer than 4, or a design matrix of rank < 4: every sample alike, or p the
#: same in every sample, i.e. one background); NONFINITE: determined, but the fit is not finite.
CONVERGED, MAX_STEPS, NONFINITE, UNDETERMINED = 0, 1, 2, 3
STATUS_NAMES = {
    CONVERGED: "converged", MAX_STEPS: "max steps reached", NONFINITE: "non-finite",
    UNDETERMINED: "undetermined (the samples cannot determine c1..c4)",
}


def _irls_weights(loss: str, u):
    """w(u) for scaled residuals u (safe where u = 0 and for u beyond Tukey's cut-off)."""
    c = ROBUST_TUNING[loss]
    a = jnp.abs(u)
    if loss == "huber":  # quadratic within c, linear beyond
        return c / jnp.maximum(a, c)
    if loss == "cauchy":  # log(1 + (u/c)^2): weights decay as 1 / u^2
        return 1.0 / (1.0 + (u / c) ** 2)
    # tukey biweight: redescending, residuals beyond c get weight 0
    return jnp.where(a < c, (1.0 - (u / c) ** 2) ** 2, 0.0)


def _weighted_solve(rows, target, weights):
    """argmin_c Σ w_i (target_i - rows_i c)² for one band; returns (coeffs (4,), rank).

    Eq. 22 writes the normal equations (MᵀM)⁻¹Mᵀv_tilde; they square the condition number, and
    the columns p⊙v and v are nearly collinear because p stays close to 1, so the same minimiser
    is computed with an SVD-based least-squares solve of the √w-scaled system instead.
    """
    root = jnp.sqrt(weights)
    coeffs, _, rank, _ = jnp.linalg.lstsq(rows * root[:, None], target * root)
    return coeffs, rank


def _robust_scale(residuals, usable, floor):
    """s = 1.4826 MAD of the usable residuals (jnp.nanmedian ignores the rest), at least floor."""
    r = jnp.where(usable, residuals, jnp.nan)
    mad = jnp.nanmedian(jnp.abs(r - jnp.nanmedian(r)))
    return jnp.maximum(MAD_TO_SIGMA * mad, floor)


def _inverse_normal_matrix(rows):
    """(MᵀM)⁻¹ (4, 4) of one band's design M (n, 4), zero rows for dropped samples.

    From the SVD M = U diag(s) Vᵀ as V diag(1/s²) Vᵀ: forming and inverting MᵀM would square the
    condition number of M, whose columns p⊙v and v are nearly collinear (p ~ 1). A zero singular
    value (an undetermined band, whose covariance is NaN anyway) gets a zero weight, as in a
    pseudo-inverse, so that it cannot turn into inf inside vmap.
    """
    _, s, v_t = jnp.linalg.svd(rows, full_matrices=False)
    cutoff = jnp.max(s) * jnp.finfo(rows.dtype).eps * max(rows.shape)
    inverse_square = jnp.where(s > cutoff, 1.0 / jnp.where(s > cutoff, s, 1.0) ** 2, 0.0)
    return (v_t.T * inverse_square) @ v_t


def _psi(loss: str, u):
    """The M-estimator's psi(u) = u w(u) for a scalar scaled residual u (u for "l2")."""
    return u if loss == "l2" else u * _irls_weights(loss, u)


def _coefficient_covariance(rows, residuals, usable, scale, loss: str):
    """Estimated covariance (4, 4) of one band's c1..c4 at the solution; see `Stage2Fit`.

    rows (n, 4) and residuals (n,) are zero where a sample is not usable; scale is the s of the
    robust loss (ignored for "l2"). NaN when no degree of freedom is left (n_usable = 4).
    """
    n = jnp.sum(usable).astype(rows.dtype)
    dof = n - MIN_SAMPLES
    inverse = _inverse_normal_matrix(rows)
    if loss == "l2":
        factor = jnp.sum(residuals**2) / dof  # sigma^2 = RSS / (n - 4)
    else:
        u = jnp.where(usable, residuals / scale, 0.0)
        # psi' by automatic differentiation of psi itself: one definition serves both, and the
        # derivative follows any change of the weights (Huber's is 1 inside c and 0 beyond).
        psi = jnp.where(usable, _psi(loss, u), 0.0)
        dpsi = jnp.where(usable, jax.vmap(jax.grad(lambda x: _psi(loss, x)))(u), 0.0)
        mean_dpsi = jnp.sum(dpsi) / n
        var_dpsi = jnp.sum(jnp.where(usable, (dpsi - mean_dpsi) ** 2, 0.0)) / n
        # Huber (1981), Sec. 7.6: K corrects the asymptotic formula for the p = 4 parameters
        # at finite n; K = 1 for least squares, where psi' = 1.
        k = 1.0 + (MIN_SAMPLES / n) * var_dpsi / mean_dpsi**2
        factor = k**2 * (jnp.sum(psi**2) / dof) / mean_dpsi**2 * scale**2
    covariance = factor * inverse
    return jnp.where(dof > 0, covariance, jnp.nan)


def _fit_band(v, p, target, scale, loss: str, max_steps: int):
    """One band: closed form, then (robust losses) IRLS as an optimistix fixed point.

    Returns (coeffs (4,), status, steps, scale used, dropped samples, covariance (4, 4)).
    """
    usable = jnp.isfinite(v) & jnp.isfinite(p) & jnp.isfinite(target)
    dropped = jnp.sum(~usable).astype(jnp.int32)
    rows = jnp.where(usable[:, None], _design_matrix(jnp.where(usable, v, 0.0), jnp.where(usable, p, 0.0)), 0.0)
    target = jnp.where(usable, target, 0.0)
    # A zero row leaves the minimiser unchanged: this is how non-finite samples are dropped.
    l2, rank = _weighted_solve(rows, target, usable.astype(v.dtype))
    determined = (jnp.sum(usable) >= MIN_SAMPLES) & (rank == 4)
    eps = jnp.finfo(v.dtype).eps
    # With exact data the MAD is 0; the floor keeps u finite (and all weights ~1, i.e. l2).
    count = jnp.maximum(jnp.sum(usable), 1).astype(v.dtype)
    floor = jnp.sqrt(eps) * (jnp.sqrt(jnp.sum(target**2) / count) + eps)
    steps = jnp.zeros((), jnp.int32)
    if loss == "l2":
        coeffs, status, used_scale = l2, jnp.full((), CONVERGED, jnp.int32), jnp.full((), jnp.nan, v.dtype)
    else:
        fixed_scale = jnp.isfinite(scale)

        def scale_for(c):
            estimated = _robust_scale(target - rows @ c, usable, floor)
            return jnp.where(fixed_scale, scale, estimated)

        def irls_step(c, loss_name):
            u = (target - rows @ c) / scale_for(c)
            weights = jnp.where(usable, _irls_weights(loss_name, u), 0.0)
            return _weighted_solve(rows, target, weights)[0]

        # Looser in float32, where a 4-coefficient solve resolves ~1e-6 relative at best.
        tolerance = 1e-10 if v.dtype == jnp.float64 else 1e-5
        solver = optx.FixedPointIteration(rtol=tolerance, atol=tolerance)
        # optimistix 0.1.0 keeps its convergence state in JAX's default float, so float32
        # iterates with x64 switched on break its while_loop; iterate in the default float.
        work = jnp.asarray(0.0).dtype

        def solve(start, loss_name):
            step = lambda c, _: irls_step(c.astype(v.dtype), loss_name).astype(work)  # noqa: E731
            return optx.fixed_point(step, solver, start.astype(work), max_steps=max_steps, throw=False)

        start = l2
        if loss == "tukey":
            # Redescending: from the least-squares start an outlier-dragged fit can settle in a
            # poor local minimum, so Tukey starts from the (convex) Huber fit.
            start = solve(l2, "huber").value
        solution = solve(start, loss)
        coeffs = solution.value.astype(v.dtype)
        steps = jnp.asarray(solution.stats["num_steps"], jnp.int32)
        status = jnp.where(solution.result == optx.RESULTS.successful, CONVERGED, MAX_STEPS).astype(jnp.int32)
        used_scale = scale_for(coeffs)
    finite = determined & jnp.all(jnp.isfinite(coeffs))
    status = jnp.where(finite, status, jnp.where(determined, NONFINITE, UNDETERMINED))
    coeffs = jnp.where(finite, coeffs, jnp.nan)
    # Residuals of the usable samples at the solution (zero rows give zero residuals).
    residuals = jnp.where(usable, target - rows @ jnp.where(finite, coeffs, 0.0), 0.0)
    covariance = _coefficient_covariance(rows, residuals, usable, used_scale, loss)
    covariance = jnp.where(finite, covariance, jnp.nan)
    return coeffs, status, steps, used_scale, dropped, covariance


class Stage2Fit(eqx.Module):
    """Result of `fit_stage2_detailed`, one entry per band, in the style of optimistix's
    `throw=False`: a batch of fits never fails on one bad band; inspect `status` instead.

    Fields:
      coeffs: (B, 4), c1..c4 (NaN for a band whose status is NONFINITE or UNDETERMINED).
      status: (B,) int32: CONVERGED (0), MAX_STEPS (1), NONFINITE (2), UNDETERMINED (3)
        (`STATUS_NAMES`).
      steps: (B,) IRLS iterations taken (0 for "l2").
      scale: (B,) residual scale s used by the robust loss (NaN for "l2").
      dropped: (B,) number of non-finite samples left out.
      loss: the loss name.
      covariance: (B, 4, 4), the estimated covariance of each band's (c1, c2, c3, c4), in the
        fit's dtype and in coefficient units (c1, c2 dimensionless; c3, c4 in response units,
        so the entries are in the products of those units); NaN for a band whose status is
        NONFINITE or UNDETERMINED, or that has exactly 4 usable samples (no degree of freedom
        left to estimate the noise). For first-order (GUM, JCGM 100:2008) propagation of the
        fit's uncertainty into the Stage II response. With M (n, 4) the design (p v, v, p, 1)
        of Eq. 20 over the n usable samples and r_i their residuals at the solution:

        "l2" (Eq. 22, ordinary least squares):
            Cov = sigma^2 (MᵀM)⁻¹,  sigma^2 = Σ r_i² / (n - 4).
        "huber", "cauchy", "tukey" (M-estimator asymptotic covariance with Huber's finite-n
        correction; Huber, Robust Statistics, Wiley 1981, Sec. 7.6):
            Cov = K² [Σ psi(u_i)² / (n - 4)] / [mean psi'(u_i)]² s² (MᵀM)⁻¹,
            K = 1 + (4 / n) Var(psi') / mean(psi')²,
        with u_i = r_i / s, s = `scale`, psi(u) = u w(u) (w the IRLS weight of the loss) and
        psi' its derivative (by automatic differentiation). Both assume independent errors of
        one variance across the samples. The robust form is asymptotic (checked by Monte Carlo
        against refits at n = 90 to within a few per cent for Gaussian noise); it is not
        finite where mean psi' = 0 (Tukey with every residual beyond c s).
        (MᵀM)⁻¹ comes from the SVD of M, never by inverting MᵀM.
    """

    coeffs: jax.Array
    status: jax.Array
    steps: jax.Array
    scale: jax.Array
    dropped: jax.Array
    loss: str = eqx.field(static=True)
    covariance: jax.Array

    @property
    def converged(self) -> jax.Array:
        return self.status == CONVERGED

    def problems(self) -> dict[int, str]:
        """{band index: status name} for every band that did not converge (concrete results)."""
        status = np.asarray(self.status)
        return {int(b): STATUS_NAMES[int(status[b])] for b in np.flatnonzero(status != CONVERGED)}


@eqx.filter_jit
def _fit_all_bands(v, p, target, scale, loss: str, max_steps: int):
    fit = jax.vmap(lambda vb, pb, tb, sb: _fit_band(vb, pb, tb, sb, loss, max_steps), in_axes=(1, 1, 1, 0))
    coeffs, status, steps, used_scale, dropped, covariance = fit(v, p, target, scale)
    return Stage2Fit(coeffs, status, steps, used_scale, dropped, loss, covariance)


def fit_stage2_detailed(v, p, target, loss: str = "l2", *, scale=None, max_steps: int = 1000) -> Stage2Fit:
    """Fit the Stage II coefficients of every band and report how each fit went.

    The training set of Section 4: small patches i on backgrounds j give v^{ij} (Eq. 10) and
    p^{ij} (Eq. 15); the target is the Stage I response of the same patch on the reference
    background, p^{i,jref} v^{i,jref}, repeated for every j (Eq. 19).

    Losses:
      "l2": the closed form of Eq. 21-22 (least squares).
      "huber", "cauchy", "tukey": M-estimators that bound (Huber), shrink (Cauchy) or cut off
        (Tukey's biweight) the influence of residuals beyond c s, with c = `ROBUST_TUNING`
        (95 % Gaussian efficiency) and s the residual scale. Solved by iteratively reweighted
        least squares: each step is the closed form of Eq. 22 with weights w(e/s), iterated to
        its fixed point by optimistix's FixedPointIteration, from the least-squares solution
        (Tukey from the Huber solution). IRLS rather than Gauss-Newton / Levenberg-Marquardt on
        transformed residuals because each step is an exact weighted closed-form solve, it
        decreases these losses monotonically for a fixed scale (majorise-minimise), needs no
        step-size control, and treats Tukey's zero-weight residuals exactly, where a
        Gauss-Newton Jacobian would be singular.

    Args:
      v: normalised responses, shape (n, B), n = n_p * n_b samples (35 x 35 px averages).
      p: white-patch ratios, shape (n, B).
      target: target responses v_tilde, shape (n, B).
      loss: "l2", "huber", "cauchy" or "tukey".
      scale: residual scale s (> 0, response units), a number or (B,); None (default)
        re-estimates it at every IRLS step as 1.4826 x the median absolute deviation of the
        residuals (a consistent estimate of the Gaussian sigma that outliers cannot inflate).
      max_steps: IRLS iterations before a band is reported as MAX_STEPS. 1000: with the scale
        re-estimated at each step IRLS contracts linearly, sometimes slowly; a band of nine
        samples (seed 5 of the tests' small design, 640 nm, Huber) needed over 100 steps to
        reach float64's 1e-10 (at 100 the coefficients already agreed to 8 digits, but the
        band was reported as not converged). The steps are 4 x 4 solves: 1000 cost nothing.

    Returns:
      `Stage2Fit`. Non-finite samples are dropped per band and counted in `dropped`; its
      `covariance` (B, 4, 4) is the estimated covariance of each band's c1..c4.
    """
    if not isinstance(loss, str) or loss not in LOSSES:
        raise ValueError(f"loss: unknown loss {loss!r}; expected one of {list(LOSSES)}")
    v = _checks.as_array("v", v)
    p = _checks.as_array("p", p)
    target = _checks.as_array("target", target)
    if v.ndim != 2:
        raise ValueError(f"v: expected shape (n, B) (samples, bands), got {tuple(v.shape)}")
    _checks.require_shape("p", p, v.shape, "one white-patch ratio per sample and band, like v")
    _checks.require_shape("target", target, v.shape, "one target per sample and band, like v")
    samples, bands = v.shape
    if samples < MIN_SAMPLES:
        raise ValueError(
            f"v: {samples} samples cannot determine the 4 coefficients c1..c4; expected at "
            f"least {MIN_SAMPLES} rows"
        )
    if not (isinstance(max_steps, int) and max_steps >= 1):
        raise ValueError(f"max_steps: expected a positive integer, got {max_steps!r}")
    dtype = _checks.float_dtype(v, p, target)
    if scale is None:
        scale = jnp.full((bands,), jnp.nan, dtype)
    else:
        scale = _checks.as_array("scale", scale)
        if scale.ndim > 1 or (scale.ndim == 1 and scale.shape[0] != bands):
            raise ValueError(f"scale: expected a number or shape ({bands},) (one per band), got shape {tuple(scale.shape)}")
        if _checks.is_concrete(scale) and not bool(np.all(np.asarray(scale) > 0)):
            raise ValueError(f"scale: expected a residual scale > 0, got {np.asarray(scale).tolist()}")
        scale = jnp.broadcast_to(scale.astype(dtype), (bands,))
    if all(_checks.is_concrete(x) for x in (v, p, target)):
        finite = np.isfinite(np.asarray(v)) & np.isfinite(np.asarray(p)) & np.isfinite(np.asarray(target))
        empty = np.flatnonzero(~finite.any(axis=0))
        if empty.size:
            raise ValueError(
                f"v, p, target: band(s) {empty.tolist()} have no finite sample (all NaN or "
                f"infinite); expected at least {MIN_SAMPLES} finite rows per band"
            )
    return _fit_all_bands(v.astype(dtype), p.astype(dtype), target.astype(dtype), scale, loss, max_steps)


def why_undetermined(v, p, target) -> str:
    """What keeps one band's samples v, p, target (n,) from determining c1..c4, in words."""
    usable = np.isfinite(v) & np.isfinite(p) & np.isfinite(target)
    v, p = np.asarray(v)[usable], np.asarray(p)[usable]
    if usable.sum() < MIN_SAMPLES:
        return f"only {int(usable.sum())} finite samples (4 coefficients need at least {MIN_SAMPLES})"
    if np.ptp(p) == 0:
        return (
            f"p is {p[0]:.6g} in every sample (one background only?): c1 p v + c2 v and c3 p + c4 "
            "cannot be told apart; expected samples on several backgrounds"
        )
    if np.ptp(v) == 0:
        return f"v is {v[0]:.6g} in every sample: expected patches of different lightness"
    rank = np.linalg.matrix_rank(np.stack([p * v, v, p, np.ones_like(v)], axis=-1))
    return f"the design (p v, v, p, 1) of Eq. 20 has rank {rank} of 4 (samples too alike)"


def fit_stage2(v, p, target, loss: str = "l2", *, scale=None, max_steps: int = 100):
    """Fit the Stage II coefficients of every band (Eq. 19-22, or a robust loss).

    Args and losses as `fit_stage2_detailed`.

    Returns:
      coeffs, shape (B, 4), ordered c1..c4. A band whose fit is not finite is NaN;
      `fit_stage2_detailed` also returns per-band status, scale and dropped-sample counts.

    Raises:
      ValueError: (concrete data) a band whose samples cannot determine c1..c4: fewer than 4
        finite samples, every sample alike, or p the same in every sample (one background).
        Under jit such a band comes out NaN with status UNDETERMINED in `fit_stage2_detailed`.
    """
    fit = fit_stage2_detailed(v, p, target, loss, scale=scale, max_steps=max_steps)
    if _checks.is_concrete(fit.status):
        undetermined = np.flatnonzero(np.asarray(fit.status) == UNDETERMINED)
        if undetermined.size:
            band = int(undetermined[0])
            v_b, p_b, t_b = (np.asarray(x, np.float64)[:, band] for x in (v, p, target))
            raise ValueError(
                f"v, p, target: band(s) {undetermined.tolist()} cannot be fitted: band {band} has "
                f"{why_undetermined(v_b, p_b, t_b)}"
            )
    return fit.coeffs


__all__ = [
    "IDENTITY_COEFFS",
    "LOSSES",
    "ROBUST_TUNING",
    "PAPER_TABLE_2",
    "CONVERGED",
    "MAX_STEPS",
    "NONFINITE",
    "UNDETERMINED",
    "STATUS_NAMES",
    "Stage2Fit",
    "identity_coeffs",
    "stage2",
    "fit_stage2",
    "fit_stage2_detailed",
    "why_undetermined",
]
