"""Symmetric positive-definite solves in plain jax.numpy operations, for small systems solved many
at a time (one per target or per pixel, under `jax.vmap`).

Why not `jax.scipy.linalg.cho_solve`: on the CPU, jaxlib before 0.12 runs a batch of LAPACK
calls (Cholesky, triangular solve, ...) whose work passes about 2e5 flop by sharing it out to
XLA's intra-op thread pool from a task already running on that pool, and blocks until its shares
are done. Two such calls in flight at once in one program (two independent branches, e.g. a
`jax.lax.map`'s loop and its remainder) take every thread of a 2-core machine's pool, and their
shares never run: the program never returns (seen with jaxlib 0.10.2, the newest release for
Python 3.11: `cross_validate_local` hung in 1 run in 3 on 2 cores; a jitted function with two
batched Choleskys of 128 matrices of 48 x 48 hung on every call). jaxlib 0.12's LAPACK calls do
not use the pool. The systems solved here are B x B with B the band count (16): a Cholesky
factorisation in B vector steps costs no more than the call into LAPACK would, and XLA fuses it
into its neighbours instead of waiting on the pool.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

_HIGHEST = jax.lax.Precision.HIGHEST


def cholesky_lower(G):
    """L (n, n), lower triangular with L L^T = G, of a symmetric positive-definite G (n, n);
    NaN where a pivot is not positive (G not positive definite), as LAPACK's factorisation gives
    through `jnp.linalg.cholesky`. Reads only G's lower triangle and diagonal. Differentiable;
    `jax.vmap` it for many systems."""
    G = jnp.asarray(G)
    n = G.shape[-1]
    rows = jnp.arange(n)

    def column(j, L):
        # Column j of L from G's column j less what columns 0..j-1 already account for
        # (L's columns j.. are still zero, so L @ L[j] sums over k < j only).
        s = jax.lax.dynamic_index_in_dim(G, j, axis=1, keepdims=False) - jnp.matmul(L, L[j], precision=_HIGHEST)
        pivot = s[j]
        root = jnp.sqrt(jnp.where(pivot > 0, pivot, jnp.nan))
        return L.at[:, j].set(jnp.where(rows >= j, s / root, 0.0))

    return jax.lax.fori_loop(0, n, column, jnp.zeros_like(G))


def cholesky_solve(L, b):
    """x (n,) with L L^T x = b (n,), L (n, n) from `cholesky_lower`: forward then back
    substitution, n steps each."""
    L, b = jnp.asarray(L), jnp.asarray(b)
    n = L.shape[-1]

    def forward(i, y):
        return y.at[i].set((b[i] - jnp.dot(L[i], y, precision=_HIGHEST)) / L[i, i])

    def backward(k, x):
        i = n - 1 - k
        return x.at[i].set((y[i] - jnp.dot(L[:, i], x, precision=_HIGHEST)) / L[i, i])

    y = jax.lax.fori_loop(0, n, forward, jnp.zeros_like(b))
    return jax.lax.fori_loop(0, n, backward, jnp.zeros_like(b))


def spd_solve(G, b):
    """x (n,) = G^-1 b for a symmetric positive-definite G (n, n) and b (n,) by Cholesky
    (`cholesky_lower`, `cholesky_solve`); NaN where G is not positive definite."""
    return cholesky_solve(cholesky_lower(G), b)
