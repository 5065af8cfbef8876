"""Fitting the reflectance estimators: time against numpy, and accuracy across material families.

What it measures
    1. Fit time of `spherejax.fit_wiener(V, R, method=m)` for m = "training", "model" and "auto"
       (cross-validation over the regularisers included; "auto" also cross-validates the kernel
       estimator, as its numpy reference then does), on the 190 RAW-to-ACES training patches
       seen by the simulated camera (`spherejax.simulated_targets`), float64.
    2. The held-out-family table: every material family of `simulated_targets.FAMILIES`
       (ColorChecker, TCS and CQS, TM-30 CES, RAW to ACES) held out in turn, the estimators
       trained on the other three: spectral rms and mean ΔE00 (D65) of the default ("auto"), of
       each method, of the offset-free form (offset-free training form, leave-one-out sigma^2)
       and of the oracle (the model-based estimator built from the simulator's true sensitivity,
       offset and noise, with the training reflectances' statistics).
    3. Train on one family, apply to each (16 pairs): the shape of the acceptance protocol, as
       ratios of the default's spectral rms to the oracle's and to the offset-free form's.
    4. Dyed materials (`spherejax.kubelka_munk`: four Kubelka-Munk families of six dyes, 20 x 20
       px patch means through the simulated camera): 200 targets of a family (seed 0) train the
       default ("auto": what it chose, with the kernel's cross-validated gain and paired z), its
       affine part and the residual kernel estimator (`estimation.fit_kernel_estimator`), applied
       to 200 other recipes of the same family (seed 1) and, the default, to those of the other
       three. Spectral rms, mean ΔE00, and the ratios to the affine one's (the issue asks at most
       0.8 within the family and at most 1.02 on the others). The kernel fit is timed against a
       numpy implementation of E9-E12 with the same folds (drawn at random), grids and inducing
       points, whose choices and residual weights must agree first (both given the affine means,
       per fold and on all the targets, timed in section 1); and `spherejax.correct` of a 1024 x
       1024 x 16 uint16 frame is timed with a calibration carrying the kernel estimator and with
       the same calibration without its residual (the issue bounds the ratio at 3x).

Against what
    A numpy implementation of the same formulas (E2-E7 of `spherejax/estimation/`,
    written again with numpy.linalg: ridge through the SVD, the sensitivity through a stacked
    least-squares solve, the Wiener step through an explicit inverse), the same candidate grids
    and the same folds (`fold_labels`). Before timing, its cross-validated choices must equal
    spherejax's and its matrices and offsets agree within 1e-6 relative.

Timing as bench_correct.py: the first call (trace + compile) apart, then spherejax and the
reference take turns for --repeats calls; median and minimum.

Run:
    python benchmarks/bench_wiener.py [--repeats 5] [--json PATH]
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
from spherejax import estimation as we, simulated_targets  # noqa: E402
from spherejax.estimation._offset_free import select_wiener_noise_variance  # noqa: E402

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


def np_kernel_fit(V, R, W_folds, r0_folds, weights, W, r0, inducing_points):
    """The residual kernel estimator's choice and residual weights (E9-E12), written again with
    numpy: (lengthscale, ridge, A (31, m)). The affine means (per fold and on all the targets)
    are spherejax's, checked above; the inducing points are the same deterministic k-means."""
    from spherejax.estimation.cross_validation import _kmeans_labels

    mu = V.mean(axis=0)
    eigenvalues, Q = np.linalg.eigh(np.cov((V - mu).T, bias=True))
    eigenvalues = np.maximum(eigenvalues, 1e-8 * eigenvalues.max())
    U = (V - mu) @ (Q / np.sqrt(eigenvalues))
    m = min(inducing_points, len(U))
    labels = _kmeans_labels(U, m) if len(U) > m else np.arange(len(U))
    Z = np.stack([U[labels == j].mean(axis=0) for j in np.unique(labels)])

    def gauss(A, B, ell):
        return np.exp(-np.sum((A[:, None] - B[None]) ** 2, axis=2) / (2 * ell**2))

    def solve(K_nm, K_mm, E, w, ridge):
        m = len(K_mm)
        A = np.linalg.solve(K_nm.T @ (w[:, None] * K_nm) + ridge * K_mm + 1e-8 * m * np.eye(m), K_nm.T @ (w[:, None] * E)).T
        # (E12): the best approximation of rank RESIDUAL_RANK.
        U_, singular, Vt = np.linalg.svd(A, full_matrices=False)
        r = we.kernel_residual.RESIDUAL_RANK
        return (U_[:, :r] * singular[:r]) @ Vt[:r]

    best = None
    for ell in we.KERNEL_LENGTHSCALE_GRID:
        K_nm, K_mm = gauss(U, Z, ell), gauss(Z, Z, ell)
        for ridge in we.KERNEL_RIDGE_GRID:
            estimate = np.zeros_like(R)
            for w, Wf, r0f in zip(weights, W_folds, r0_folds):
                affine = V @ Wf.T + r0f
                A = solve(K_nm, K_mm, R - affine, w, ridge)
                estimate += (1 - w)[:, None] * (affine + K_nm @ A.T)
            error = np.sqrt(np.mean((estimate - R) ** 2))
            if best is None or error < best[0]:
                best = (error, ell, ridge)
    _, ell, ridge = best
    A = solve(gauss(U, Z, ell), gauss(Z, Z, ell), R - (V @ W.T + r0), np.ones(len(V)), ridge)
    return ell, ridge, A


def np_auto_with_kernel(V, R):
    """The numpy reference of "auto" from KERNEL_MIN_TARGETS targets on: the affine choice
    (`np_fit`), then the kernel estimator on it over folds drawn at random (`np_kernel_fit`,
    given spherejax's per-fold affine means as in section 4), then its gain and paired z."""
    W, r0, name, settings = np_fit(V, R, "auto")
    labels, _ = we.random_fold_labels(len(V))
    weights = (labels[None, :] != np.unique(labels)[:, None]).astype(np.float64)
    affine_labels, _ = we.fold_labels(R)
    affine_weights = (affine_labels[None, :] != np.unique(affine_labels)[:, None]).astype(np.float64)
    mean = next(c for c in (we.METHODS[m](V, R, affine_weights, "") for m in we.METHODS) if c.cross_validation.method == name)
    W_folds, r0_folds = (np.asarray(x) for x in mean.fit_folds(weights))
    ell, ridge, A = np_kernel_fit(V, R, W_folds, r0_folds, weights, W, r0, we.INDUCING_POINTS)
    return W, r0, ell, ridge, A


def kubelka_munk_tables(seed: int, repeats: int) -> tuple[dict, list[str]]:
    """Section 4 of the module docstring: the tables, the fit's timing against numpy, the cost of
    each estimator in `correct`; and any disagreement with the numpy reference."""
    from spherejax import kubelka_munk

    train = kubelka_munk.km_family_responses(seed=seed, n=200)
    test = kubelka_munk.km_family_responses(seed=seed + 1, n=200)
    fitted = {}
    for name, (V, R, _) in train.items():
        default = spherejax.fit_wiener(V, R)
        kernel = default if default.method == "kernel" else we.fit_kernel_estimator(V, R)
        fitted[name] = {"default": default, "affine": kernel.affine, "kernel": kernel}
    within = {}
    for name, models in fitted.items():
        Vt, Rt, _ = test[name]
        within[name] = {label: {"spectral_rms": rms(e, Vt, Rt), "delta_e_d65": mean_delta_e(e, Vt, Rt)} for label, e in models.items()}
        within[name]["default"]["method"] = models["default"].method
        within[name]["kernel_settings"] = dict(models["kernel"].cross_validation[0].settings)
    pairs = {f"{a} -> {b}": rms(fitted[a]["default"], *test[b][:2]) / rms(fitted[a]["affine"], *test[b][:2]) for a in train for b in train}

    # The fit against numpy, on the first family: the kernel's folds are drawn at random.
    failures = []
    name = next(iter(train))
    V, R, _ = train[name]
    ours = fitted[name]["kernel"]
    labels, _ = we.random_fold_labels(len(V))
    weights = (labels[None, :] != np.unique(labels)[:, None]).astype(np.float64)
    affine_labels, _ = we.fold_labels(R)
    affine_weights = (affine_labels[None, :] != np.unique(affine_labels)[:, None]).astype(np.float64)
    ranked = we.rank_candidates(we.METHODS[m](V, R, affine_weights, "") for m in we.METHODS)
    W_folds, r0_folds = ranked[0].fit_folds(weights)
    ell, ridge, A = np_kernel_fit(V, R, np.asarray(W_folds), np.asarray(r0_folds), weights,
                                  np.asarray(ours.affine.matrix), np.asarray(ours.affine.offset), we.INDUCING_POINTS)
    settings = within[name]["kernel_settings"]
    if (settings["lengthscale"], settings["ridge"]) != (ell, ridge):
        failures.append(f"kernel: spherejax chose l {settings['lengthscale']} ridge {settings['ridge']}, numpy l {ell} ridge {ridge}")
    else:
        error = float(np.max(np.abs(np.asarray(ours.kernel.weights) - A)) / np.max(np.abs(A)))
        if error > 1e-5:  # a 64 x 64 solve in two orders of summation
            failures.append(f"kernel: the residual weights differ from numpy's by {error:.2e} (relative)")
    # The same work both ways: the kernel's cross-validation and fit on the chosen affine mean
    # (fit_wiener also cross-validates the affine methods, timed in section 1).
    def kernel_fit():
        return jax.block_until_ready(we.cross_validate_kernel(V, R, weights, "", ranked[0]).fit())

    compile_s, _ = time_first_call(kernel_fit)
    timed = time_interleaved({
        "spherejax": kernel_fit,
        "numpy": lambda: np_kernel_fit(V, R, np.asarray(W_folds), np.asarray(r0_folds), weights, np.asarray(ours.affine.matrix),
                                       np.asarray(ours.affine.offset), we.INDUCING_POINTS),
    }, repeats)
    return {
        "within_family": within, "default_over_affine_pairs": pairs,
        "fit": {"family": name, "compile_s": compile_s, "timings": timed, "ratio": timed["numpy"]["median_s"] / timed["spherejax"]["median_s"]},
        "correct_megapixel": correct_megapixel(fitted[name]["kernel"], test[name][0], repeats),
    }, failures


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


def rms(estimator, V, R) -> float:
    return float(np.sqrt(np.mean((np.asarray(spherejax.wiener(V, estimator)) - R) ** 2)))


def mean_delta_e(estimator, V, R) -> float:
    estimate = spherejax.wiener(V, estimator)
    return float(np.mean(np.asarray(spherejax.delta_e_2000(spherejax.reflectance_to_lab(estimate), spherejax.reflectance_to_lab(R)))))


def estimators(V, R, truth) -> dict:
    return {
        "auto": spherejax.fit_wiener(V, R),
        "training": spherejax.fit_wiener(V, R, method="training"),
        "model": spherejax.fit_wiener(V, R, method="model"),
        "offset-free": spherejax.fit_wiener(V, R, select_wiener_noise_variance(V, R)[0], offset=False),
        "oracle": spherejax.wiener_from_system(
            truth.sensitivity, truth.offset, truth.noise_variance(R), R.mean(0), np.cov(R.T, bias=True)
        ),
    }


def held_out_table(data, truth) -> dict:
    table = {}
    for family in data:
        V = np.concatenate([data[f][0] for f in data if f != family])
        R = np.concatenate([data[f][1] for f in data if f != family])
        V_test, R_test = data[family]
        fitted = estimators(V, R, truth)
        table[family] = {
            name: {"spectral_rms": rms(e, V_test, R_test), "delta_e_d65": mean_delta_e(e, V_test, R_test)}
            for name, e in fitted.items()
        }
        table[family]["auto"]["method"] = fitted["auto"].method
    return table


def pairs_table(data, truth) -> dict:
    table = {}
    for train in data:
        fitted = estimators(*data[train], truth)
        for test in data:
            errors = {name: rms(e, *data[test]) for name, e in fitted.items()}
            table[f"{train} -> {test}"] = errors
    return table


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", metavar="PATH")
    args = parser.parse_args(argv)
    info = machine_info()
    data = simulated_targets.family_responses(seed=args.seed)
    truth = simulated_targets.target_system()
    V, R = data["RAW to ACES"]

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
        reference = functools.partial(np_fit, V, R, method)
        if method == "auto" and len(V) >= we.KERNEL_MIN_TARGETS:
            reference = functools.partial(np_auto_with_kernel, V, R)  # "auto" tries the kernel estimator too
        timed = time_interleaved({
            "spherejax": lambda: jax.block_until_ready(spherejax.fit_wiener(V, R, method=method).matrix),  # noqa: B023
            "numpy": reference,
        }, args.repeats)
        timings[method] = {
            "compile_s": compile_s, "timings": timed,
            "ratio": timed["numpy"]["median_s"] / timed["spherejax"]["median_s"], "chosen": chosen_method,
        }
    if failures:
        print("agreement FAILED: " + "; ".join(failures))
        return 1

    print(f"fit_wiener on {len(R)} targets (RAW to ACES through the simulated camera), float64, median of "
          f"{args.repeats} ({info['cpu_model']}, {info['nproc']} CPUs)")
    print(f"{'method':9} {'chosen':>8} {'spherejax ms':>13} {'numpy ms':>9} {'ratio':>7} {'first call s':>13}")
    for method, r in timings.items():
        t = r["timings"]
        print(f"{method:9} {r['chosen']:>8} {t['spherejax']['median_s'] * 1e3:13.1f} {t['numpy']['median_s'] * 1e3:9.1f} "
              f"{r['ratio']:6.1f}x {r['compile_s']:13.2f}")

    held_out = held_out_table(data, truth)
    names = ["auto", "training", "model", "offset-free", "oracle"]
    print("\nheld-out families (trained on the other three): spectral rms / mean ΔE00 D65")
    print(f"{'held out':14} " + " ".join(f"{n:>16}" for n in names) + "  auto chose")
    for family, row in held_out.items():
        cells = " ".join(f"{row[n]['spectral_rms']:.4f} / {row[n]['delta_e_d65']:.3f}".rjust(16) for n in names)
        print(f"{family:14} {cells}  {row['auto']['method']}")

    pairs = pairs_table(data, truth)
    print("\ntrain on one family, apply to each: spectral rms of auto, and its ratio to the oracle and to the offset-free form")
    within = sum(p["auto"] <= 1.05 * p["oracle"] for p in pairs.values())
    for pair, p in pairs.items():
        print(f"  {pair:32} {p['auto']:.4f}  {p['auto'] / p['oracle']:.3f} x oracle  {p['auto'] / p['offset-free']:.3f} x offset-free")
    print(f"  within 5 % of the oracle or better: {within} of {len(pairs)} pairs")

    km, km_failures = kubelka_munk_tables(args.seed, args.repeats)
    if km_failures:
        print("agreement FAILED: " + "; ".join(km_failures))
        return 1
    print("\ndyed materials (Kubelka-Munk families, 200 targets, 200 other recipes held out): spectral rms / mean ΔE00 D65")
    print(f"{'family':20} {'default chose':>13} {'affine':>18} {'kernel':>18} {'kernel / affine':>16}  kernel gain, z in CV")
    for family, row in km["within_family"].items():
        cells = " ".join(f"{row[n]['spectral_rms']:.5f} / {row[n]['delta_e_d65']:.3f}".rjust(18) for n in ("affine", "kernel"))
        k = row["kernel_settings"]
        print(f"{family:20} {row['default']['method']:>13} {cells} {row['kernel']['spectral_rms'] / row['affine']['spectral_rms']:16.3f}"
              f"  {k['gain']:.3f}, {k['paired_z']:.1f} (l {k['lengthscale']}, ridge {k['ridge']})")
    others = [ratio for pair, ratio in km["default_over_affine_pairs"].items() if pair.split(" -> ")[0] != pair.split(" -> ")[1]]
    print(f"  the default on the other families (12 pairs): over the affine from {min(others):.3f} to {max(others):.3f}; "
          f"above 1.02 on {sum(r > 1.02 for r in others)}")
    f, c = km["fit"], km["correct_megapixel"]
    print(f"  the kernel's cross-validation and fit on {f['family']}: {f['timings']['spherejax']['median_s'] * 1e3:.0f} ms, numpy "
          f"{f['timings']['numpy']['median_s'] * 1e3:.0f} ms ({f['ratio']:.1f}x), first call {f['compile_s']:.2f} s")
    print(f"  correct, {c['size']} x {c['size']} x 16 uint16 (median of {max(args.repeats, 7)}): affine "
          f"{c['timings']['affine']['median_s'] * 1e3:.1f} ms, kernel {c['timings']['kernel']['median_s'] * 1e3:.1f} ms "
          f"({c['ratio']:.2f}x; the issue's bound 3x), per-pixel step {c['kernel_modes']}")
    if args.json:
        write_record(args.json, {
            "benchmark": "bench_wiener", "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "targets": len(R), "repeats": args.repeats, "fit": timings, "held_out_families": held_out,
            "train_one_apply_each": pairs, "kubelka_munk": km, "machine": info, "argv": sys.argv,
        })
    return 0


if __name__ == "__main__":
    sys.exit(main())
