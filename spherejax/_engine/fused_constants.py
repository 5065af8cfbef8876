"""The calibration's arrays as the fused CPU kernel takes them: the estimator and illuminant
folded into one projection (`kernel_constants`), and the kernel residual's whitening, inducing
points and rank-8 weights (`residual_constants`, E8-E12 of `spherejax.estimation.kernel_residual`).
Traceable: a plan computes them once; the XLA call computes them inside its program.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .fused_extension import capabilities


def kernel_constants(wiener, wiener_offset, weights):
    """What the kernel takes of the estimator and the illuminant: projection (B, 34) = [W^T | W^T
    weights], bias (34,) = [r0 | r0 weights] and white_xyz (3,), the column sums of weights.

    XYZ = reflectance weights = v_tilde (W^T weights) + r0 weights: the (31, 3) weights folded
    into the Wiener matrix, so that one (B, 34) product gives reflectance and XYZ.
    """
    hi = jax.lax.Precision.HIGHEST
    projection = jnp.concatenate([wiener.T, jnp.matmul(wiener.T, weights, precision=hi)], axis=1)
    bias = jnp.concatenate([wiener_offset, jnp.matmul(wiener_offset, weights, precision=hi)])
    return projection, bias, jnp.sum(weights, axis=0)


#: The rank of a kernel residual's weights A (31, m) the kernel applies, as the compiled kernel
#: declares it (`fused_extension.capabilities`, kResidualRank of kernel/fused_correct.h; 8 where
#: it was not built, the layout the sources define): A = P G with P (31, 8) and G (8, m), eight
#: multiply-adds per inducing point and pixel. The fit keeps A at this rank or less
#: (`estimation.kernel_residual.RESIDUAL_RANK`); a residual of higher rank (a file not made by the
#: fit) takes the jax.numpy path (`residual_fits`).
RESIDUAL_RANK = int(capabilities().get("residual_rank", 8))

#: The kernel takes the residual's whitening and inducing rows in groups of this many (zero rows
#: pad them), as it declares (`capabilities`, "residual_rows").
RESIDUAL_ROWS = int(capabilities().get("residual_rows", 8))


def _padded_rows(x, multiple: int):
    """x (n, ...) with zero rows appended up to a multiple of `multiple` rows."""
    return jnp.pad(x, [(0, -x.shape[0] % multiple)] + [(0, 0)] * (x.ndim - 1))


def residual_fits(residual) -> bool:
    """True if the kernel applies this kernel residual (`estimation.KernelResidual`, concrete)
    exactly: weights of rank RESIDUAL_RANK or less (the singular values beyond it below 1e-5 of
    the largest: float32 round-off of a rank-8 A). None (an affine estimator): True."""
    if residual is None:
        return True
    A = np.asarray(residual.weights, np.float64)
    singular = np.linalg.svd(A, compute_uv=False)
    return len(singular) <= RESIDUAL_RANK or not singular[0] > 0 or singular[RESIDUAL_RANK] <= 1e-5 * singular[0]


def residual_constants(residual, weights, bands: int):
    """What the kernel takes of a kernel residual (E8-E10, `estimation.KernelResidual`: centre mu,
    whitening S (d, B), inducing z (m, d), weights A (31, m)), float32, traceable:

    whitening (D, B + 1): row i [S_i | -(S mu)_i] (u = S (v - mu));
    inducing (M, B + 1): row j [Y_j | c_j] with Y = S^T z^T and c = -mu . Y - |z|^2 / 2, so that
      -|u - z_j|^2 / 2 = Y_j . v + c_j - |u|^2 / 2;
    factor (M, 8): G^T, basis (8, 34): [P | P^T weights]^T, from A's singular value
      decomposition at rank RESIDUAL_RANK (A = P G, P = U Sigma, G = V^T): exact for the fit's A
      (`residual_fits`); components below A's round-off zero in both (the kernel counts G's
      columns in use: rank 4 or less takes half the multiply-adds);
    D and M: d and m rounded up to multiples of 8 (the kernel takes rows in eights), the padding
    zero (a padding inducing point has factor 0). None (an affine estimator): no rows, nothing
    applied.
    """
    if residual is None:
        return (jnp.zeros((0, bands + 1), jnp.float32), jnp.zeros((0, bands + 1), jnp.float32),
                jnp.zeros((0, RESIDUAL_RANK), jnp.float32), jnp.zeros((RESIDUAL_RANK, 34), jnp.float32))
    hi = jax.lax.Precision.HIGHEST
    f32 = functools.partial(jnp.asarray, dtype=jnp.float32)
    mu, S, Z, A = (f32(x) for x in (residual.centre, residual.whitening, residual.inducing, residual.weights))
    whitening = _padded_rows(jnp.concatenate([S, -jnp.matmul(S, mu, precision=hi)[:, None]], axis=1), RESIDUAL_ROWS)
    Y = jnp.matmul(Z, S, precision=hi)  # (m, B): row j is S^T z_j
    c = -jnp.matmul(Y, mu, precision=hi) - 0.5 * jnp.sum(Z * Z, axis=1)
    inducing = _padded_rows(jnp.concatenate([Y, c[:, None]], axis=1), RESIDUAL_ROWS)
    U, singular, Vt = jnp.linalg.svd(A, full_matrices=False)
    rank = min(RESIDUAL_RANK, singular.shape[0])
    # Components below A's float32 round-off (numpy's matrix_rank tolerance) are zeroed: weights
    # of rank r (the fit's A has rank r by construction, E12) keep only r, and the kernel runs
    # its half-rank code where r <= 4 (call.cc counts G's columns in use).
    # A that overflows float32 (weights near 3e38, which only an unchecked tree_map can bring)
    # keeps every component, so that its non-finite values reach the outputs and are flagged
    # rather than dropped.
    tolerance = singular[0] * max(A.shape) * jnp.finfo(jnp.float32).eps
    kept = (singular[:rank] > tolerance) | ~jnp.isfinite(tolerance)
    P = jnp.pad(jnp.where(kept, U[:, :rank] * singular[:rank], 0.0), ((0, 0), (0, RESIDUAL_RANK - rank)))  # (31, 8)
    G = jnp.pad(jnp.where(kept[:, None], Vt[:rank], 0.0), ((0, RESIDUAL_RANK - rank), (0, 0)))  # (8, m)
    factor = _padded_rows(G.T, RESIDUAL_ROWS)
    basis = jnp.concatenate([P.T, jnp.matmul(P.T, f32(weights), precision=hi)], axis=1)
    return whitening, inducing, factor, basis


__all__ = ["RESIDUAL_RANK", "kernel_constants", "residual_constants", "residual_fits"]
