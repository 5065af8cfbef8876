"""The kernel residual (E8-E10 of `spherejax.estimation.kernel_residual`) inside the Pallas GPU
kernel (`spherejax._engine.gpu_kernel`): what the kernel reads of a `KernelResidual`, what it
applies per block of pixels, and which residuals it takes (`applies_residual`).

Per pixel, with v_tilde the Stage II response (B,) of the affine kernel (0 on flagged pixels, as in
the jax.numpy path), mu the centre, S' = S / l the whitening and z'_j = z_j / l the inducing points
(the lengthscale folded in), A (31, m) the weights:

    u        = (v_tilde - mu) S'^T                       one (block, B) x (B, B) product   (E9)
    s_j      = |u|^2 - 2 u.z'_j + |z'_j|^2               one (block, B) x (B, Mc) product
    k_j      = exp(-max(s_j, 0) / 2)                     clipped at 0 against round-off,
                                                         as `kernel_residual.kernel_features` (E10)
    residual = k A^T                                     one (block, Mc) x (Mc, 32) product    (E8)
    XYZ     += residual weights                          three row sums over the 32 channels

which is `equations.pixel_outputs`'s grouping: the residual reflectance first, its XYZ from it
(`xyz + residual @ tristimulus_weights`), not folded into A as the affine XYZ is folded into W. Why
not folded: k (A^T weights) costs three row sums over Mc inducing points per chunk, the residual
reflectance's three over 32 channels once; for Mc = 64 that is 192 against 96 multiply-adds a pixel.

Chunks of inducing points. The inducing points are taken Mc at a time (`chunk_of`: at most
`INDUCING_CHUNK`, a power of two >= 16, the Triton dot's smallest side) in a loop that adds each
chunk's k A^T to a (block, 32) accumulator, as flash attention takes keys: the (block, Mc) tile
of k is what must live in registers (at 128 pixels and 4 warps, Mc floats a thread: 64), so the
register use does not grow with m and no m overflows a program's registers. The constants come
padded to a whole number of chunks: a padding inducing point has z = 0, |z|^2 = 0 and a zero row
of A^T, so its k (finite, in [0, 1]) times 0 adds exactly 0. Every array the kernel loads is a
power of two (the Triton lowering's rule, gpu_kernel's docstring): (B,), (B, B), (B, Mc), (Mc,),
(Mc, 32), (32,).

Bound. `MAX_INDUCING_POINTS` (1024): what the kernel reads of the residual per program is
(B + 1 + 32) x 4 bytes per inducing point (196 B at B = 16), re-read by every program from the
SM's L1 (256 KiB on an H100, shared with the registers' spills and the other programs' inputs):
up to 1024 points (196 KiB) it fits there, beyond that every program would stream it from L2.
The fit makes m <= 64 (`kernel_residual.INDUCING_POINT_COUNTS`); a file may hold more.

Precision: float32 products at Precision.HIGHEST (Triton's IEEE input precision, no TF32), as the
affine product; `pixel_outputs_pallas(residual_precision=...)` takes another (e.g.
`jax.lax.DotAlgorithmPreset.TF32_TF32_F32_X3`: three TF32 tensor-core products, about float32's
accuracy) for measuring on a GPU.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

#: Reflectance channels padded to a power of two (the product's and the store's width); the same
#: as gpu_kernel's.
REFLECTANCE_PAD = 32

#: Inducing points a chunk holds at most (`chunk_of`): the (block, Mc) kernel tile in registers.
INDUCING_CHUNK = 64

#: The largest number of inducing points m the kernel applies (`applies_residual`; the module
#: docstring says why).
MAX_INDUCING_POINTS = 1024

#: The Triton dot's smallest side: a chunk is never smaller.
_MIN_CHUNK = 16

_HIGHEST = jax.lax.Precision.HIGHEST


class ResidualConstants(NamedTuple):
    """What the kernel reads of a kernel residual, float32, in C chunks of Mc inducing points
    (`residual_constants`): a pytree.

    centre: mu (B,). whitening: S'^T (B, B), so that u = (v - mu) S'^T. inducing: z'^T per chunk
    (C, B, Mc). inducing_squared: |z'_j|^2 per chunk (C, Mc). weights: A^T per chunk with a zero
    32nd column (C, Mc, 32). tristimulus: the (31, 3) XYZ weights as rows with a zero 32nd column
    and a zero 4th row (4, 32).
    """

    centre: jax.Array
    whitening: jax.Array
    inducing: jax.Array
    inducing_squared: jax.Array
    weights: jax.Array
    tristimulus: jax.Array


def _is_power_of_two(n: int) -> bool:
    return n > 0 and n & (n - 1) == 0


def applies_residual(residual) -> bool:
    """True if the GPU kernel applies this kernel residual (`estimation.KernelResidual`, concrete
    or traced: only its shapes are read): B a power of two >= 16 bands (as `gpu_kernel.supports`)
    and at most `MAX_INDUCING_POINTS` inducing points; weights of any rank (A is applied whole).
    None (an affine estimator): True."""
    if residual is None:
        return True
    bands, points = int(residual.centre.shape[0]), int(residual.inducing.shape[0])
    return _is_power_of_two(bands) and bands >= 16 and points <= MAX_INDUCING_POINTS


def chunk_of(points: int, chunk: int = INDUCING_CHUNK) -> int:
    """Mc, the inducing points a chunk holds for m = `points`: m rounded up to a power of two, at
    least 16 and at most `chunk` (a power of two >= 16)."""
    if not (_is_power_of_two(chunk) and chunk >= _MIN_CHUNK):
        raise ValueError(f"inducing chunk: expected a power of two >= {_MIN_CHUNK}, got {chunk}")
    rounded = _MIN_CHUNK
    while rounded < min(points, chunk):
        rounded *= 2
    return rounded


def residual_constants(residual, tristimulus_weights, *, chunk: int = INDUCING_CHUNK) -> ResidualConstants:
    """`ResidualConstants` of a `KernelResidual` (mu (B,), S' (B, B), z' (m, B), A (31, m)) and the
    (31, 3) XYZ weights, float32, traceable: m padded to C chunks of Mc = `chunk_of(m, chunk)` with
    inducing points that add exactly 0 (the module docstring). A few small XLA operations on
    (m, B)- and (m, 31)-sized arrays; a plan makes them once (`gpu_kernel.prepare`)."""
    f32 = jnp.float32
    centre, whitening, inducing, weights = (
        jnp.asarray(x, f32) for x in (residual.centre, residual.whitening, residual.inducing, residual.weights)
    )
    points, bands = inducing.shape
    size = chunk_of(points, chunk)
    chunks = max(1, -(-points // size))
    pad = chunks * size - points
    inducing = jnp.pad(inducing, ((0, pad), (0, 0)))  # (C Mc, B)
    squared = jnp.sum(inducing * inducing, axis=1)  # as kernel_features: |z'|^2 per row
    channels = REFLECTANCE_PAD - weights.shape[0]
    weights_t = jnp.pad(weights.T, ((0, pad), (0, channels)))  # (C Mc, 32)
    tristimulus = jnp.pad(jnp.asarray(tristimulus_weights, f32).T, ((0, 1), (0, channels)))  # (4, 32)
    return ResidualConstants(
        centre=centre,
        whitening=whitening.T,
        inducing=inducing.reshape(chunks, size, bands).transpose(0, 2, 1),
        inducing_squared=squared.reshape(chunks, size),
        weights=weights_t.reshape(chunks, size, REFLECTANCE_PAD),
        tristimulus=tristimulus,
    )


def residual_of_block(v_tilde, refs: ResidualConstants, *, precision=_HIGHEST):
    """Inside the kernel: (residual (block, 32), [X, Y, Z] of it, each (block,)) for the Stage II
    responses v_tilde (block, B) of one program's pixels, from the `ResidualConstants`' refs.
    Channel 31 of the residual is 0 (A^T's zero column)."""
    chunks = refs.inducing.shape[0]
    block = v_tilde.shape[0]

    def dot(a, b):
        return jax.lax.dot(a, b, precision=precision, preferred_element_type=jnp.float32)

    u = dot(v_tilde - refs.centre[...][None, :], refs.whitening[...])  # (block, B)
    u_squared = jnp.sum(u * u, axis=1)[:, None]  # (block, 1)

    def add_chunk(j, accumulated):
        squared = u_squared - 2.0 * dot(u, refs.inducing[j]) + refs.inducing_squared[j][None, :]
        k = jnp.exp(-0.5 * jnp.maximum(squared, 0.0))  # (block, Mc), kernel_features' clip
        return accumulated + dot(k, refs.weights[j])

    zero = jnp.zeros((block, REFLECTANCE_PAD), jnp.float32)
    # One chunk (m <= 64, every fitted residual) without a loop around it.
    residual = add_chunk(0, zero) if chunks == 1 else jax.lax.fori_loop(0, chunks, add_chunk, zero)
    xyz = [jnp.sum(residual * refs.tristimulus[k, :][None, :], axis=1) for k in range(3)]
    return residual, xyz


__all__ = [
    "INDUCING_CHUNK",
    "MAX_INDUCING_POINTS",
    "ResidualConstants",
    "applies_residual",
    "chunk_of",
    "residual_constants",
    "residual_of_block",
]
