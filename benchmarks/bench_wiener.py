"""Fitting the reflectance estimators: time against numpy, and accuracy across material families.

What it measures
    1. Fit time of `spherejax.fit_wiener(V, R, method=m)` for m = "training", "model" and "auto"
       (cross-validation over the regularisers included), on the 190 RAW-to-ACES training
       patches seen by the simulated camera (`spherejax.simulated_targets`), float64.
    2. The held-out-family table: every material family of `simulated_targets.FAMILIES`
       (ColorChecker, TCS and CQS, TM-30 CES, RAW to ACES) held out in turn, the estimators
       trained on the other three: spectral rms and mean ΔE00 (D65) of the default ("auto"), of
       each method, of the first release's form (offset-free training form, leave-one-out sigma^2)
       and of the oracle (the model-based estimator built from the simulator's true sensitivity,
       offset and noise, with the training reflectances' statistics).
    3. Train on one family, apply to each (16 pairs): the shape of the acceptance protocol, as
       ratios of the default's spectral rms to the oracle's and to the first release's.

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
import os
import sys

import numpy as np

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from harness import machine_info, time_first_call, time_interleaved, write_record  # noqa: E402

import spherejax  # noqa: E402
from spherejax import estimation as we, simulated_targets  # noqa: E402
from spherejax.estimation._first_release import select_wiener_noise_variance  # noqa: E402

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
        "first release": spherejax.fit_wiener(V, R, select_wiener_noise_variance(V, R)[0], offset=False),
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
        timed = time_interleaved({
            "spherejax": lambda: jax.block_until_ready(spherejax.fit_wiener(V, R, method=method).matrix),  # noqa: B023
            "numpy": lambda: np_fit(V, R, method),  # noqa: B023
        }, args.repeats)
        timings[method] = {
            "compile_s": compile_s, "timings": timed,
            "ratio": timed["numpy"]["median_s"] / timed["spherejax"]["median_s"], "chosen": ours.method,
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
    names = ["auto", "training", "model", "first release", "oracle"]
    print("\nheld-out families (trained on the other three): spectral rms / mean ΔE00 D65")
    print(f"{'held out':14} " + " ".join(f"{n:>16}" for n in names) + "  auto chose")
    for family, row in held_out.items():
        cells = " ".join(f"{row[n]['spectral_rms']:.4f} / {row[n]['delta_e_d65']:.3f}".rjust(16) for n in names)
        print(f"{family:14} {cells}  {row['auto']['method']}")

    pairs = pairs_table(data, truth)
    print("\ntrain on one family, apply to each: spectral rms of auto, and its ratio to the oracle and to the first release")
    within = sum(p["auto"] <= 1.05 * p["oracle"] for p in pairs.values())
    for pair, p in pairs.items():
        print(f"  {pair:32} {p['auto']:.4f}  {p['auto'] / p['oracle']:.3f} x oracle  {p['auto'] / p['first release']:.3f} x first release")
    print(f"  within 5 % of the oracle or better: {within} of {len(pairs)} pairs")
    if args.json:
        write_record(args.json, {
            "benchmark": "bench_wiener", "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "targets": len(R), "repeats": args.repeats, "fit": timings, "held_out_families": held_out,
            "train_one_apply_each": pairs, "machine": info, "argv": sys.argv,
        })
    return 0


if __name__ == "__main__":
    sys.exit(main())
