"""Symmetric positive-definite solves in jax.numpy (spherejax.estimation.small_solve), and the
estimators' programs free of the batched LAPACK calls that hang jaxlib < 0.12 on 2 cores."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from spherejax.estimation import gp_hyperparameters, local_regression
from spherejax.estimation.small_solve import cholesky_lower, cholesky_solve, spd_solve


def _spd(rng, n, condition=1e3):
    """A random symmetric positive-definite (n, n) matrix with eigenvalues from 1 to `condition`."""
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return (Q * np.geomspace(1.0, condition, n)) @ Q.T


@pytest.mark.parametrize("n", [1, 3, 16, 17])
def test_the_factor_and_the_solution_are_numpys(n):
    rng = np.random.default_rng(n)
    G, b = _spd(rng, n), rng.normal(size=n)
    with jax.enable_x64(True):
        L = np.asarray(cholesky_lower(jnp.asarray(G)))
        x = np.asarray(spd_solve(jnp.asarray(G), jnp.asarray(b)))
    np.testing.assert_allclose(L, np.linalg.cholesky(G), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(x, np.linalg.solve(G, b), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(G @ x, b, rtol=1e-9, atol=1e-11)


def test_only_the_lower_triangle_is_read():
    rng = np.random.default_rng(1)
    G = _spd(rng, 6)
    scrambled = np.tril(G) + np.triu(rng.normal(size=(6, 6)), 1)
    with jax.enable_x64(True):
        np.testing.assert_array_equal(np.asarray(cholesky_lower(jnp.asarray(scrambled))),
                                      np.asarray(cholesky_lower(jnp.asarray(G))))


def test_a_matrix_that_is_not_positive_definite_gives_nan_as_lapacks_does():
    G = np.diag([1.0, -1.0, 2.0])
    with jax.enable_x64(True):
        ours = np.asarray(spd_solve(jnp.asarray(G), jnp.ones(3)))
        lapack = np.asarray(jnp.linalg.cholesky(jnp.asarray(G)))
    assert np.isnan(lapack).any()
    assert np.isnan(ours).all()


def test_vmapped_and_jitted_it_solves_every_system():
    rng = np.random.default_rng(2)
    G = np.stack([_spd(rng, 5) for _ in range(40)])
    b = rng.normal(size=(40, 5))
    with jax.enable_x64(True):
        x = np.asarray(jax.jit(jax.vmap(spd_solve))(jnp.asarray(G), jnp.asarray(b)))
    np.testing.assert_allclose(x, np.linalg.solve(G, b[..., None])[..., 0], rtol=1e-9, atol=1e-12)


def test_float32_solves_to_float32_precision():
    rng = np.random.default_rng(3)
    G, b = _spd(rng, 16, condition=100.0), rng.normal(size=16)
    x = np.asarray(spd_solve(jnp.asarray(G, jnp.float32), jnp.asarray(b, jnp.float32)))
    assert x.dtype == np.float32
    np.testing.assert_allclose(x, np.linalg.solve(G, b), rtol=0, atol=100 * 100 * np.finfo(np.float32).eps)


def test_gradients_match_finite_differences():
    rng = np.random.default_rng(4)
    G, b = _spd(rng, 4, condition=10.0), rng.normal(size=4)
    with jax.enable_x64(True):
        # Symmetrised argument: the solve reads G's lower triangle, finite differences move both.
        # First order (second order compiles the loops' second derivatives: 40 s on jaxlib 0.10).
        check_grads(lambda A, c: spd_solve(0.5 * (A + A.T), c), (jnp.asarray(G), jnp.asarray(b)), order=1,
                    modes=("fwd", "rev"))
        L = cholesky_lower(jnp.asarray(G))
        check_grads(lambda c: cholesky_solve(L, c), (jnp.asarray(b),), order=1)


# ---- the estimators' programs ------------------------------------------------------------------

_RESULT_SHAPE = re.compile(r"[a-z]\d+\[([\d,]*)\]")


def batched_lapack_calls(compiled_text: str) -> list[tuple[str, tuple[int, ...]]]:
    """(target, result shape) of every LAPACK custom call in an optimised HLO module's text whose
    first result has batch dimensions (more than the matrix's two) of more than one matrix."""
    calls = []
    for line in compiled_text.splitlines():
        target = re.search(r'custom_call_target="(lapack_\w+)"', line)
        if target is None:
            continue
        shape = _RESULT_SHAPE.search(line.split("custom-call(")[0].split("=", 1)[1])
        dims = tuple(int(d) for d in shape.group(1).split(",") if d)
        if len(dims) > 2 and int(np.prod(dims[:-2])) > 1:
            calls.append((target.group(1), dims))
    return calls


def test_the_parser_finds_a_batched_cholesky():
    """The check below is only as good as this: it must see what jnp.linalg.cholesky makes."""
    with jax.enable_x64(True):
        text = jax.jit(jnp.linalg.cholesky).lower(jnp.ones((8, 5, 5))).compile().as_text()
    calls = batched_lapack_calls(text)
    assert calls and all(dims[:1] == (8,) for _, dims in calls)


def test_local_cross_validation_makes_no_batched_lapack_call():
    """The program that hung CI (Python 3.11, jaxlib 0.10.2, 2 cores): a `lax.map` over the
    targets whose loop and remainder each factorised thousands of 16 x 16 systems in one
    Cholesky call, two in flight at once on a pool of two threads."""
    rng = np.random.default_rng(5)
    n, B, F = 70, 16, 5
    V, R = rng.normal(size=(n, B)), rng.uniform(size=(n, 31))
    folds = np.arange(n) % F
    masks = (folds[None, :] != folds[:, None]).astype(float)
    with jax.enable_x64(True):
        program = local_regression._local_cv.lower(
            jnp.asarray(V), jnp.asarray(R), jnp.asarray(masks), jnp.asarray(folds), jnp.zeros((F, 31, B)),
            jnp.zeros((F, 31)), jnp.asarray(local_regression.LOCAL_BANDWIDTH_GRID),
            jnp.asarray(local_regression.LOCAL_RIDGE_GRID))
        assert batched_lapack_calls(program.compile().as_text()) == []


def test_local_estimates_make_no_batched_lapack_call():
    rng = np.random.default_rng(6)
    V, R = rng.normal(size=(60, 16)), rng.uniform(size=(60, 31))
    queries = rng.normal(size=(500, 16))
    program = local_regression._estimate.lower(
        jnp.asarray(queries, jnp.float32), jnp.asarray(V, jnp.float32), jnp.asarray(R, jnp.float32),
        jnp.zeros((31, 16), jnp.float32), jnp.zeros(31, jnp.float32), jnp.zeros(16, jnp.float32),
        jnp.eye(16, dtype=jnp.float32), 1.0, 1e-3, neighbours=None)
    assert batched_lapack_calls(program.compile().as_text()) == []


def test_the_marginal_likelihood_and_its_gradient_make_no_batched_lapack_call():
    """r components' Choleskys of n x n in one call (n = 128, r = 8: 1.4e7 flop) were shared out
    to the thread pool; their gradient's two triangular solves could be in flight together."""
    rng = np.random.default_rng(7)
    n, d, r = 128, 16, 8
    U, C, w = rng.normal(size=(n, d)), rng.normal(size=(n, r)), np.ones(n)
    with jax.enable_x64(True):
        raw, variance = gp_hyperparameters._start(jnp.asarray(U), jnp.asarray(C), jnp.asarray(w))
        program = jax.jit(jax.value_and_grad(gp_hyperparameters.negative_log_likelihood)).lower(
            raw, (jnp.asarray(U), jnp.asarray(C), jnp.asarray(w), variance))
        assert batched_lapack_calls(program.compile().as_text()) == []
