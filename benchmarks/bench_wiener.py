"""Fitting the reflectance estimators: time against numpy, and every candidate on every synthetic
family kind.

What it measures
    1. Fit time of `spherejax.fit_wiener(V, R, method=m)` for m = "training", "model" and "auto"
       on the 190 RAW-to-ACES training patches seen by the simulated camera
       (`spherejax.simulated_targets`), float64, cross-validation included. "training" and
       "model" are timed against a numpy reference of the same formulas (below); "auto" now also
       fits the kernel estimator's hyperparameters (E14) and cross-validates it and the local
       method, which the reference does not do: its affine choice is checked, its time reported
       alone. The kernel estimator's fit (`estimation.fit_kernel_estimator`, the first Kubelka-
       Munk family's 200 targets) is timed whole (first call apart), and its final fit (E11-E13:
       the residual's components, one ridge solve per component, given the hyperparameters and
       inducing points) against a numpy implementation of that final fit.
    2. Every candidate on every synthetic family kind: the four Kubelka-Munk families
       (`kubelka_munk.km_family_responses`, 20 x 20 px patch means) and every kind of
       `target_families.FAMILY_KINDS` but "km_mixing" (which is one of those four), 200 targets
       of seed S train, 200 of seed S + 1 are held out. Held-out spectral rms and mean ΔE00
       (D65) of: the published Wiener estimator (the offset-free training form at its
       leave-one-out sigma^2, `spherejax.wiener_estimation.select_wiener_noise_variance`),
       "training", "model", the best affine (the one "auto" ranks first), the kernel estimator
       (forced, `fit_kernel_estimator`), the local method (`local_regression.
       cross_validate_local` on the best affine, folds drawn at random as "auto" draws them) and
       the default ("auto", what it chose); each also as a ratio to the best affine; the cost
       per pixel of applying each in multiply-adds (affine 31 B; kernel 31 B +
       `kernel_residual.residual_multiply_adds(B, m, r)`, the m exponentials on top; local
       `local_regression.local_multiply_adds_per_pixel(n, B)`); the kernel's m, r, and its
       cross-validated gain and paired z; and on how many kinds each lowers the best affine's
       rms by 15 % or more.
    3. Across materials: the default trained on one of the 8 sets applied to the held-out
       targets of each other (56 pairs), as ratios to the best affine and to the published
       Wiener estimator trained on the same set; the pairs within 5 % of the published one.
    4. `spherejax.correct` of a 1024 x 1024 x 16 uint16 frame with a calibration carrying the
       kernel estimator and with the same calibration without its residual (--skip-correct
       leaves it out).

Against what
    A numpy implementation of the same formulas (E2-E7 of `spherejax/estimation/`, written again
    with numpy.linalg: ridge through the SVD, the sensitivity through a stacked least-squares
    solve, the Wiener step through an explicit inverse), the same candidate grids and the same
    folds (`fold_weights`); and of the kernel estimator's final fit (E9, E11-E13: whitening by
    eigendecomposition, residual components by SVD, kernel matrices by broadcast differences,
    one `numpy.linalg.solve` per component) given spherejax's hyperparameters (its report's
    "lengthscales", "ridges", "inducing_points", "rank") and inducing order
    (`kernel_residual.inducing_order`). Before timing, the affine reference's choices must equal
    spherejax's and its matrices and offsets agree within 1e-6 relative, and the kernel
    reference's residual weights A (31, m) and offset within 1e-6 relative; else exit 1.

Timing as bench_correct.py: the first call (trace + compile) apart, then spherejax and the
reference take turns for --repeats calls; median and minimum.

Run:
    python benchmarks/bench_wiener.py [--repeats 5] [--seed 0] [--skip-correct] [--json PATH]
"""

from __future__ import annotations

import argparse
import datetime
import functools
import os
import sys

import numpy as np

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from harness import machine_info, time_first_call, time_interleaved, write_record  # noqa: E402

import spherejax  # noqa: E402
from spherejax import estimation as we, kubelka_munk, simulated_targets, target_families  # noqa: E402
from spherejax.estimation import kernel_residual, local_regression  # noqa: E402
from spherejax.grid import N_WAVELENGTHS  # noqa: E402
from spherejax.wiener_estimation import select_wiener_noise_variance  # noqa: E402

TOLERANCE = 1e-6


# ---------------------------------------------------------------------------------------------
# The numpy reference: the same equations, written again.


def np_training(V, R, w, sigma2):
    """(E2) on the targets with weight 1: W = Rc^T Vc (Vc^T Vc + n sigma^2 I)^-1 via the SVD."""
    keep = w > 0
    V, R = V[keep], R[keep]
    v_mean, r_mean = V.mean(0), R.mean(0)
    U, s, Qt = np.linalg.svd(V - v_mean, full_matrices=False)
    W = (Qt.T * (s / (s**2 + len(V) * sigma2))) @ U.T @ (R - r_mean)
    W = W.T
    return W, r_mean - W @ v_mean


def np_penalty(name):
    eye = np.eye(31)
    return eye if name == "ridge" else np.concatenate([eye[:-2] - 2 * eye[1:-1] + eye[2:], 1e-3 * eye])


def np_sensitivity(V, R, w, weight, penalty):
    """(E3-E4): M, b and the per-band noise variance from the targets with weight 1."""
    keep = w > 0
    V, R = V[keep], R[keep]
    v_mean, r_mean = V.mean(0), R.mean(0)
    Vc, Rc = V - v_mean, R - r_mean
    L = np_penalty(penalty)
    lam = weight * np.sum(Rc**2) / np.sum(L**2)
    A = np.concatenate([Rc, np.sqrt(lam) * L])
    M_t = np.linalg.lstsq(A, np.concatenate([Vc, np.zeros((len(L), V.shape[1]))]), rcond=None)[0]
    hat_trace = np.trace(Rc @ np.linalg.solve(A.T @ A, Rc.T))
    noise = np.sum((Vc - Rc @ M_t) ** 2, axis=0) / max(len(V) - hat_trace - 1.0, 1.0)
    return M_t.T, v_mean - M_t.T @ r_mean, noise


def np_model(V, R, w, weight, shrinkage, penalty):
    """(E3-E7)."""
    M, b, noise = np_sensitivity(V, R, w, weight, penalty)
    R_kept = R[w > 0]
    r_mean = R_kept.mean(0)
    covariance = np.cov(R_kept.T, bias=True)
    i = np.arange(31)
    K_r = (1 - shrinkage) * covariance + shrinkage * np.trace(covariance) / 31 * we.MARKOV_PRIOR_CORRELATION ** np.abs(i[:, None] - i[None])
    floor = 1e-6 * np.mean((M @ (covariance * len(R_kept)) ) * M) + np.finfo(float).tiny
    K_n = np.diag(np.maximum(noise, floor))
    W = K_r @ M.T @ np.linalg.inv(M @ K_r @ M.T + K_n)
    return W, r_mean - W @ (M @ r_mean + b)


def np_held_out(fit, V, R, weights):
    estimates = np.zeros_like(R)
    for w in weights:
        W, r0 = fit(w)
        estimates[w == 0] = V[w == 0] @ W.T + r0
    return estimates


def np_rms(a, b):
    return float(np.sqrt(np.mean((a - b) ** 2)))


def np_fit(V, R, method):
    """The reference's fit_wiener(V, R, method=...) -> (W, r0, chosen settings)."""
    weights = we.fold_weights(R)  # the split, shared: only the formulas are written again
    ones = np.ones(len(R))
    out = {}
    if method in ("training", "auto"):
        power = np.mean((V - V.mean(0)) ** 2)
        grid = power * np.asarray(we.RELATIVE_NOISE_GRID)
        errors = [np_rms(np_held_out(lambda w: np_training(V, R, w, s2), V, R, weights), R) for s2 in grid]  # noqa: B023
        k = int(np.argmin(errors))
        out["training"] = (errors[k], np_training(V, R, ones, grid[k]), {"noise_variance": grid[k]})
    if method in ("model", "auto"):
        best = None
        for penalty in we.SENSITIVITY_PENALTIES:
            for weight in we.SENSITIVITY_PENALTY_GRID:
                predictions = np.zeros_like(V)
                for w in weights:
                    M, b, _ = np_sensitivity(V, R, w, weight, penalty)
                    predictions[w == 0] = R[w == 0] @ M.T + b
                score = np.sqrt(np.mean((predictions - V) ** 2))
                if best is None or score < best[0]:
                    best = (score, penalty, weight)
        _, penalty, weight = best
        errors = [
            np_rms(np_held_out(lambda w: np_model(V, R, w, weight, s, penalty), V, R, weights), R)  # noqa: B023
            for s in we.PRIOR_SHRINKAGE_GRID
        ]
        k = int(np.argmin(errors))
        out["model"] = (
            errors[k], np_model(V, R, ones, weight, we.PRIOR_SHRINKAGE_GRID[k], penalty),
            {"penalty": penalty, "penalty_weight": weight, "shrinkage": we.PRIOR_SHRINKAGE_GRID[k]},
        )
    name = min(out, key=lambda m: out[m][0])
    return (*out[name][1], name, out[name][2])


def np_kernel_final_fit(V, R, W, r0, lengthscales, ridges, noise, inducing_points: int):
    """The kernel estimator's final fit on all the targets (E9, E11-E13), written again with numpy,
    given its hyperparameters: the lengthscales (B,) of the whitened directions, one ridge per
    residual component (r,), every component's noise variance (E14; as many as the fit's largest
    rank), and m. Returns (A (31, m), the offset r0 + the residuals' mean (31,)). The affine mean
    W (31, B), r0 (31,) is spherejax's (checked against `np_fit` above); the inducing points are
    the same forward-selection order (`kernel_residual.inducing_order`, on the components in units
    of their noise)."""
    mu = V.mean(axis=0)
    eigenvalues, Q = np.linalg.eigh(np.cov((V - mu).T, bias=True))
    eigenvalues = np.maximum(eigenvalues, 1e-8 * eigenvalues.max())
    X = (V - mu) @ (Q / np.sqrt(eigenvalues)) / np.asarray(lengthscales)  # (E9), l folded in
    E = R - (V @ W.T + r0)
    mean = E.mean(axis=0)
    _, _, Vt = np.linalg.svd(E - mean, full_matrices=False)
    P = Vt[: len(noise)]  # (E13): the residual's leading principal directions (largest rank, 31)
    C = (E - mean) @ P.T
    Z = X[kernel_residual.inducing_order(X, C / np.sqrt(np.asarray(noise)), inducing_points)]
    P, C = P[: len(ridges)], C[:, : len(ridges)]
    K_nm = np.exp(-0.5 * np.sum((X[:, None, :] - Z[None]) ** 2, axis=2))  # (E10)
    K_mm = np.exp(-0.5 * np.sum((Z[:, None, :] - Z[None]) ** 2, axis=2))
    m = len(Z)
    a = np.stack([np.linalg.solve(K_nm.T @ K_nm + ridge * K_mm + 1e-8 * m * np.eye(m), K_nm.T @ C[:, j])
                  for j, ridge in enumerate(ridges)])  # (E11), one ridge per component
    return P.T @ a, r0 + mean  # (E12)


def kernel_fit_timing(V, R, repeats: int) -> tuple[dict, list[str]]:
    """Section 1's kernel part: `fit_kernel_estimator` timed whole (first call apart); its final fit
    (`Candidate.fit` of `cross_validate_kernel`, which also computes the predictive variance E15)
    against `np_kernel_final_fit`, after their residual weights agree."""
    compile_s, ours = time_first_call(lambda: we.fit_kernel_estimator(V, R))
    settings = dict(ours.cross_validation[0].settings)
    m, ridges = settings["inducing_points"], settings["ridges"]
    W, r0 = np.asarray(ours.affine.matrix), np.asarray(ours.affine.offset)
    A, offset = np_kernel_final_fit(V, R, W, r0, settings["lengthscales"], ridges, settings["noise"], m)
    failures = []
    for label, a, b in (("weights A", ours.kernel.weights, A), ("offset", ours.affine.offset, offset)):
        a = np.asarray(a)
        error = float(np.max(np.abs(a - b)) / np.max(np.abs(b))) if a.shape == b.shape else np.inf
        if not error <= TOLERANCE:
            failures.append(f"kernel final fit: {label} differs from numpy's by {error:.2e} (relative) > {TOLERANCE}")
    # ours.affine.offset is the affine r0 plus the residuals' mean (E11), as numpy's offset.
    if failures:
        return {}, failures
    labels, folds_text = we.fold_labels(R)
    ranked = we.rank_candidates(we.METHODS[name](V, R, weights_of(labels), folds_text) for name in we.METHODS)
    random_labels, random_text = we.random_fold_labels(len(V))
    candidate = we.cross_validate_kernel(V, R, weights_of(random_labels), random_text, ranked[0])
    whole = time_interleaved({"fit_kernel_estimator": lambda: jax.block_until_ready(we.fit_kernel_estimator(V, R).kernel.weights)},
                             repeats)
    final = time_interleaved({
        "spherejax": lambda: jax.block_until_ready(candidate.fit()[5]),
        "numpy": lambda: np_kernel_final_fit(V, R, W, r0, settings["lengthscales"], ridges, settings["noise"], m),
    }, repeats)
    return {
        "targets": len(V), "compile_s": compile_s, "fit_kernel_estimator": whole["fit_kernel_estimator"],
        "final_fit": final, "final_fit_ratio": final["numpy"]["median_s"] / final["spherejax"]["median_s"],
        "inducing_points": m, "rank": settings["rank"],
    }, failures


# ---------------------------------------------------------------------------------------------
# Every candidate on every family kind (section 2) and across materials (section 3).

#: The candidates of section 2, in table order.
CANDIDATES = ("published", "training", "model", "best affine", "kernel", "local", "default")

#: A gain "counts" where the held-out spectral rms is at most this fraction of the best affine's
#: (the acceptance checks' 15 %).
GAIN_RATIO = 0.85

#: Across materials, the default must stay within this factor of the published Wiener estimator.
PUBLISHED_WITHIN = 1.05


def weights_of(labels) -> np.ndarray:
    """0/1 fold weights (F, n) from fold labels (n,): row f is 0 where target i is held out."""
    labels = np.asarray(labels)
    return (labels[None, :] != np.unique(labels)[:, None]).astype(np.float64)


def family_sets(seed: int, n: int = 200) -> dict:
    """{set name: ((V, R) of seed `seed`, (V, R) of seed `seed` + 1)}: the four Kubelka-Munk
    families and every `target_families.FAMILY_KINDS` kind but km_mixing, n targets each."""
    train = kubelka_munk.km_family_responses(seed=seed, n=n)
    test = kubelka_munk.km_family_responses(seed=seed + 1, n=n)
    sets = {name: (train[name][:2], test[name][:2]) for name in train}
    for kind in target_families.FAMILY_KINDS:
        if kind != "km_mixing":
            sets[kind] = (target_families.target_family(kind, n, seed), target_families.target_family(kind, n, seed + 1))
    return sets


def fit_candidates(V, R) -> tuple[dict, dict]:
    """({candidate: (estimate function responses (k, B) -> (k, 31), multiply-adds per pixel)},
    details: the methods chosen, the kernel's m, r, gain, z, the local method's settings and the
    default's cross-validation reports) of targets V (n, B), R (n, 31)."""
    n, bands = V.shape
    affine_cost = N_WAVELENGTHS * bands
    default = spherejax.fit_wiener(V, R)
    kernel = default if default.method == "kernel" else we.fit_kernel_estimator(V, R)
    fitted = {
        "published": spherejax.fit_wiener(V, R, select_wiener_noise_variance(V, R)[0], offset=False),
        "training": spherejax.fit_wiener(V, R, method="training"),
        "model": spherejax.fit_wiener(V, R, method="model"),
        "best affine": kernel.affine, "kernel": kernel, "default": default,
    }
    kernel_settings = dict(kernel.cross_validation[0].settings)
    m, r = kernel_settings["inducing_points"], kernel_settings["rank"]
    kernel_cost = affine_cost + kernel_residual.residual_multiply_adds(bands, m, r)
    costs = {"published": affine_cost, "training": affine_cost, "model": affine_cost, "best affine": affine_cost,
             "kernel": kernel_cost, "default": kernel_cost if default.method == "kernel" else affine_cost}
    candidates = {name: (applier(estimator), costs[name]) for name, estimator in fitted.items()}

    # The local method as "auto" cross-validates it: on the best affine, over folds drawn at random.
    labels, folds_text = we.fold_labels(R)
    ranked = we.rank_candidates(we.METHODS[name](V, R, weights_of(labels), folds_text) for name in we.METHODS)
    random_labels, random_text = we.random_fold_labels(n)
    local = local_regression.cross_validate_local(V, R, weights_of(random_labels), random_text, mean=ranked[0])
    local_fit = local.fit()
    local_cost = local_regression.local_multiply_adds_per_pixel(n, bands)
    candidates["local"] = (lambda v: np.asarray(local_fit.estimate(v)), local_cost)
    local_settings = dict(local.cross_validation.settings)
    details = {
        "default_chose": default.method, "best_affine": kernel.affine.method, "local_mean": ranked[0].cross_validation.method,
        "kernel": {key: kernel_settings[key] for key in ("inducing_points", "rank", "gain", "paired_z", "lengthscales", "ridges",
                                                         "hyperparameters_converged", "tried") if key in kernel_settings},
        "kernel_report_cost_per_pixel": kernel_settings.get("cost_per_pixel"),
        "local": {key: local_settings[key] for key in ("bandwidth", "ridge", "bandwidth_index", "ridge_index", "neighbours")},
        "local_cv_spectral_rms": local.cross_validation.spectral_rms,
        "default_reports": [{"method": c.method, "spectral_rms": c.spectral_rms, "delta_e_d65": c.delta_e_d65,
                             "cost_per_pixel": dict(c.settings).get("cost_per_pixel"), "folds": c.folds}
                            for c in default.cross_validation],
    }
    return candidates, details


def applier(estimator):
    """responses (k, B) -> the estimator's reflectances (k, 31) as numpy (`spherejax.wiener`)."""
    return lambda v: np.asarray(spherejax.wiener(v, estimator))


def held_out_errors(estimate, R) -> dict:
    """Spectral rms over targets and wavelengths, and mean ΔE00 (D65), of estimates (k, 31) of R."""
    lab = spherejax.reflectance_to_lab
    return {"spectral_rms": float(np.sqrt(np.mean((estimate - R) ** 2))),
            "delta_e_d65": float(np.mean(np.asarray(spherejax.delta_e_2000(lab(estimate), lab(R)))))}


def family_tables(seed: int) -> tuple[dict, dict, dict]:
    """(per set: every candidate's held-out errors, ratio and cost, with `fit_candidates`'
    details; the 56 cross-material pairs; the counts)."""
    sets = family_sets(seed)
    fitted, within = {}, {}
    for name, ((V, R), (Vt, Rt)) in sets.items():
        candidates, details = fit_candidates(V, R)
        fitted[name] = candidates
        rows = {label: {**held_out_errors(candidates[label][0](Vt), Rt), "cost_per_pixel": candidates[label][1]}
                for label in CANDIDATES}
        for row in rows.values():
            row["ratio_to_best_affine"] = row["spectral_rms"] / rows["best affine"]["spectral_rms"]
        within[name] = {"candidates": rows, **details}
        print(f"  {name}: default chose {details['default_chose']}, default/best affine "
              f"{rows['default']['ratio_to_best_affine']:.3f}", flush=True)
    pairs = {}
    for a in sets:
        for b, (_, (Vt, Rt)) in sets.items():
            if a == b:
                continue
            errors = {label: float(np.sqrt(np.mean((fitted[a][label][0](Vt) - Rt) ** 2))) for label in ("default", "best affine", "published")}
            pairs[f"{a} -> {b}"] = {**errors, "default_over_best_affine": errors["default"] / errors["best affine"],
                                    "default_over_published": errors["default"] / errors["published"]}
    counts = {
        f"{label} <= {GAIN_RATIO} x best affine": sum(row["candidates"][label]["ratio_to_best_affine"] <= GAIN_RATIO for row in within.values())
        for label in ("kernel", "local", "default")
    }
    counts["kinds"] = len(within)
    counts[f"pairs default <= {PUBLISHED_WITHIN} x published"] = sum(p["default_over_published"] <= PUBLISHED_WITHIN for p in pairs.values())
    counts["pairs"] = len(pairs)
    return within, pairs, counts


def print_family_tables(within, pairs, counts) -> None:
    print("\nevery candidate, trained on 200 targets (seed S), held out on 200 others (seed S + 1): spectral rms / mean ΔE00 D65")
    print(f"{'set':20} " + " ".join(f"{c:>16}" for c in CANDIDATES) + "  default chose")
    for name, row in within.items():
        cells = " ".join(f"{row['candidates'][c]['spectral_rms']:.5f} / {row['candidates'][c]['delta_e_d65']:.3f}".rjust(16) for c in CANDIDATES)
        print(f"{name:20} {cells}  {row['default_chose']}")
    print("\nratio of spectral rms to the best affine's; multiply-adds per pixel of applying (affine 31 B = "
          f"{next(iter(within.values()))['candidates']['best affine']['cost_per_pixel']}, the exponentials apart)")
    print(f"{'set':20} " + " ".join(f"{c:>11}" for c in CANDIDATES)
          + "  best affine  kernel m, r, CV gain, z  cost: kernel, local, default")
    for name, row in within.items():
        cells = " ".join(f"{row['candidates'][c]['ratio_to_best_affine']:11.3f}" for c in CANDIDATES)
        k, cost = row["kernel"], {c: row["candidates"][c]["cost_per_pixel"] for c in ("kernel", "local", "default")}
        print(f"{name:20} {cells}  {row['best_affine']:>11}  {k['inducing_points']:>3}, {k['rank']}, {k['gain']:.3f}, {k['paired_z']:5.1f}"
              f"      {cost['kernel']}, {cost['local']}, {cost['default']}")
    for key, value in counts.items():
        print(f"  {key}: {value}")
    others = [p["default_over_best_affine"] for p in pairs.values()]
    published = [p["default_over_published"] for p in pairs.values()]
    print(f"\nacross materials (default trained on one set, applied to each other's held-out targets, {len(pairs)} pairs): "
          f"default / best affine {min(others):.3f}..{max(others):.3f}, default / published {min(published):.3f}..{max(published):.3f}")
    names = list(within)
    short = {name: name[:9] for name in names}
    for key, title in (("default_over_best_affine", "default / best affine"), ("default_over_published", "default / published")):
        print(f"\n{title}, trained on the row's set, applied to the column's held-out targets")
        print(f"{'trained on':20} " + " ".join(f"{short[b]:>9}" for b in names))
        for a in names:
            print(f"{a:20} " + " ".join(f"{'-':>9}" if a == b else f"{pairs[f'{a} -> {b}'][key]:9.3f}" for b in names))


def correct_megapixel(kernel, responses, repeats: int, size: int = 1024) -> dict:
    """`spherejax.correct` of a size x size x 16 uint16 frame (NumPy, as an archive reads it)
    with a calibration whose estimator is `kernel` (a ResidualKernelEstimator) and with the same
    calibration without its residual (the affine estimator): what the issue bounds at 3x. The
    frame's Stage II responses are `responses` (the family's), resampled per pixel, so that the
    kernel sees the distances of real samples; flat field 1 % to 100 % counts of white, no Stage
    II change (c2 = 1), the white patch a 32 x 32 corner."""
    rng = np.random.default_rng(0)
    bands = responses.shape[1]
    dark = rng.uniform(95.0, 105.0, (size, size, bands)).astype(np.float32)
    white = (dark + rng.uniform(40000.0, 50000.0, (size, size, bands))).astype(np.float32)
    patch = np.zeros((size, size), bool)
    patch[:32, :32] = True
    v = np.asarray(responses, np.float64)[rng.integers(0, len(responses), size * size)].reshape(size, size, bands)
    raw = np.clip(np.rint(dark + np.clip(v, 0.0, 1.2) * (white - dark)), 0, 65535).astype(np.uint16)
    raw[:32, :32] = np.rint(white[:32, :32]).astype(np.uint16)
    coeffs = np.tile(np.float32([0.0, 1.0, 0.0, 0.0]), (bands, 1))
    as32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    affine = spherejax.Calibration(dark=dark, white=white, patch=patch, coeffs=coeffs, wiener=as32(kernel.matrix),
                                   wiener_offset=as32(kernel.offset))
    with_kernel = spherejax.Calibration(dark=dark, white=white, patch=patch, coeffs=coeffs, wiener=as32(kernel.matrix),
                                        wiener_offset=as32(kernel.offset), wiener_residual=kernel.kernel.astype(np.float32))
    modes = {label: spherejax.plan(c, raw.shape, dtype=raw.dtype).kernel_mode for label, c in (("affine", affine), ("kernel", with_kernel))}
    timed = time_interleaved({
        "affine": lambda: jax.block_until_ready(spherejax.correct(raw, affine).lab),
        "kernel": lambda: jax.block_until_ready(spherejax.correct(raw, with_kernel).lab),
    }, max(repeats, 7))
    return {"size": size, "kernel_modes": modes, "timings": timed,
            "ratio": timed["kernel"]["median_s"] / timed["affine"]["median_s"]}


# ---------------------------------------------------------------------------------------------


def fit_timings(V, R, repeats: int) -> tuple[dict, list[str]]:
    """Section 1's affine part: each method's fit against `np_fit`, after their choices and
    matrices agree; "auto" (affine choice checked) timed alone."""
    timings, failures = {}, []
    for method in ("training", "model", "auto"):
        compile_s, ours = time_first_call(lambda: spherejax.fit_wiener(V, R, method=method))  # noqa: B023
        W, r0, name, settings = np_fit(V, R, method)
        chosen_method = ours.method
        if chosen_method == "kernel":  # the reference is of the affine choice, the kernel's mean
            ours = ours.affine
        chosen = dict(ours.cross_validation[0].settings)
        if ours.method != name or any(
            not (chosen[k] == v if isinstance(v, str) else np.isclose(chosen[k], v, rtol=1e-9)) for k, v in settings.items()
        ):
            failures.append(f"{method}: spherejax chose {ours.method} {chosen}, the reference {name} {settings}")
            continue
        for label, a, b in (("matrix", ours.matrix, W), ("offset", ours.offset, r0)):
            error = float(np.max(np.abs(np.asarray(a) - b)) / np.max(np.abs(b)))
            if error > TOLERANCE:
                failures.append(f"{method}: {label} differs from the reference by {error:.2e} (relative) > {TOLERANCE}")
        fns = {"spherejax": lambda: jax.block_until_ready(spherejax.fit_wiener(V, R, method=method).matrix)}  # noqa: B023
        if method != "auto":  # auto's kernel and local cross-validation have no numpy reference here
            fns["numpy"] = functools.partial(np_fit, V, R, method)
        timed = time_interleaved(fns, repeats)
        timings[method] = {"compile_s": compile_s, "timings": timed, "chosen": chosen_method,
                           "ratio": timed["numpy"]["median_s"] / timed["spherejax"]["median_s"] if "numpy" in timed else None}
    return timings, failures


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip-correct", action="store_true", help="leave out section 4 (correct of a 1024^2 frame)")
    parser.add_argument("--json", metavar="PATH")
    args = parser.parse_args(argv)
    info = machine_info()
    V, R = simulated_targets.family_responses(seed=args.seed)["RAW to ACES"]

    timings, failures = fit_timings(V, R, args.repeats)
    km_name = next(iter(kubelka_munk.MATERIAL_FAMILIES))
    V_km, R_km, _ = kubelka_munk.km_family_responses(seed=args.seed, n=200)[km_name]
    kernel_timing, kernel_failures = kernel_fit_timing(V_km, R_km, args.repeats)
    failures += kernel_failures
    if failures:
        print("agreement FAILED: " + "; ".join(failures))
        return 1

    print(f"fit_wiener on {len(R)} targets (RAW to ACES through the simulated camera), float64, median of "
          f"{args.repeats} ({info['cpu_model']}, {info['nproc']} CPUs)")
    print(f"{'method':9} {'chosen':>8} {'spherejax ms':>13} {'numpy ms':>9} {'ratio':>7} {'first call s':>13}")
    for method, r in timings.items():
        t = r["timings"]
        numpy_ms = f"{t['numpy']['median_s'] * 1e3:9.1f}" if "numpy" in t else f"{'-':>9}"
        ratio = f"{r['ratio']:6.1f}x" if r["ratio"] is not None else f"{'-':>7}"
        print(f"{method:9} {r['chosen']:>8} {t['spherejax']['median_s'] * 1e3:13.1f} {numpy_ms} {ratio} {r['compile_s']:13.2f}")
    k = kernel_timing
    print(f"fit_kernel_estimator on {k['targets']} targets ({km_name}): {k['fit_kernel_estimator']['median_s']:.2f} s "
          f"(first call {k['compile_s']:.1f} s); its final fit (E11-E13, m {k['inducing_points']}, r {k['rank']}, with E15): "
          f"{k['final_fit']['spherejax']['median_s'] * 1e3:.1f} ms, numpy's (E11-E13) {k['final_fit']['numpy']['median_s'] * 1e3:.1f} ms "
          f"({k['final_fit_ratio']:.2f}x); residual weights agree within {TOLERANCE:g}")

    within, pairs, counts = family_tables(args.seed)
    print_family_tables(within, pairs, counts)

    correct = None
    if not args.skip_correct:
        (V_train, R_train), (V_test, _) = next(iter(family_sets(args.seed).values()))
        correct = correct_megapixel(we.fit_kernel_estimator(V_train, R_train), V_test, args.repeats)
        c = correct
        print(f"\ncorrect, {c['size']} x {c['size']} x 16 uint16 (median of {max(args.repeats, 7)}): affine "
              f"{c['timings']['affine']['median_s'] * 1e3:.1f} ms, kernel {c['timings']['kernel']['median_s'] * 1e3:.1f} ms "
              f"({c['ratio']:.2f}x; the bound 3x), per-pixel step {c['kernel_modes']}")
    if args.json:
        write_record(args.json, {
            "benchmark": "bench_wiener", "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "seed": args.seed, "repeats": args.repeats, "fit": timings, "kernel_fit": kernel_timing,
            "families": within, "cross_material_pairs": pairs, "counts": counts, "correct_megapixel": correct,
            "machine": info, "argv": sys.argv,
        })
    return 0


if __name__ == "__main__":
    sys.exit(main())
