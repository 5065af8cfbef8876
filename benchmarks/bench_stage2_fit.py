"""Stage II fit: spherejax's closed form and robust fits against numpy / scipy, with 10 % outliers.

What it measures
    `spherejax.polynomial.fit_stage2_detailed` on the Stage II training set of Section 4
    (v, p, target, each (90, 16): 9 patches x 10 backgrounds, 16 bands) with the closed form
    ("l2", Eq. 19-22) and each robust loss ("huber", "cauchy", "tukey": IRLS through optimistix),
    after 10 % of the samples were given gross errors. For each fit: time (first call, i.e. trace
    + compile + run, apart from the median and minimum of warm calls), how far its coefficients
    land from the clean-data closed-form fit, per-band status and IRLS steps.

Against what
    The same fits written the way a lab would write them without JAX: per band (16 calls)
    `np.linalg.lstsq` for the closed form and `scipy.optimize.least_squares(loss="huber" or
    "cauchy")` from the closed-form start for the robust ones (scipy has no Tukey biweight, so
    Tukey has no reference). scipy's robust losses need a fixed residual scale: s = 1.4826 MAD of
    the closed-form residuals of each band; spherejax re-estimates s at every IRLS step by
    default, which scipy cannot, so spherejax is also run with the same fixed s ("fixed s" rows)
    and those rows are checked to agree with scipy before anything is timed, as the closed form
    is with numpy.

Data
    Real training data from spherejax's physical simulator (`io.write_simulated_session`, the
    paper's default design), measured with `calibrate` exactly as `spherejax calibrate` does.
    The closed-form fit on it is the clean-data fit c_clean. Then, as tests/test_stage2.py's
    `with_gross_outliers` does, 10 % of the samples get errors of 0.1-0.3 in every band.

Checks (the issue's acceptance criteria; exit status 1 if one fails)
    1. With 10 % gross outliers every robust spherejax fit lands at least 5 times closer to
       c_clean than the closed form does (Frobenius norm over the 16 x 4 coefficients).
    2. On clean data every loss agrees with the closed form to 1e-4 in the coefficients. This
       holds exactly only on data the model fits exactly, so it is checked on
       target = stage2(v, p, c_clean). On the real clean data the robust fits weight the
       samples differently from least squares, so their coefficients differ from it by an
       amount set by the measurement noise; that is reported, not checked.

Timing as bench_correct.py (whose helpers it imports): the first call of each spherejax loss is
reported on its own, then all implementations take turns for `--repeats` warm calls, with
`jax.block_until_ready` on the coefficients.

Run:
    python benchmarks/bench_stage2_fit.py [--repeats 7] [--json PATH] [--dtype float64]
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import tempfile
import time
from importlib import metadata

import jax

# Before spherejax creates any array: the acceptance criteria (1e-4 on the coefficients) and the
# scipy reference are float64, as in the tests. --dtype float32 casts the data instead.
jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from harness import OtherProcessesLoad, machine_info, time_first_call, time_interleaved, write_record  # noqa: E402

from spherejax import calibrate, io  # noqa: E402
from spherejax.polynomial import (  # noqa: E402
    CONVERGED,
    MAD_TO_SIGMA,
    ROBUST_TUNING,
    fit_stage2_detailed,
    stage2,
)

ROBUST = ("huber", "cauchy", "tukey")
SCIPY_LOSSES = ("huber", "cauchy")  # scipy.optimize.least_squares has no Tukey biweight
OUTLIER_FRACTION = 0.1
OUTLIER_SEED = 0

#: Criterion 1: closed-form distance / robust distance must reach this.
MIN_ROBUSTNESS_RATIO = 5.0
#: Criterion 2: max |c_loss - c_l2| on exact model data.
CLEAN_TOLERANCE = 1e-4
#: spherejax and its reference must agree this well in prediction (response units) before
#: timing. In prediction, not coefficients: the columns p*v and v are nearly collinear (p ~ 1),
#: so equally good fits can differ more in c than in what c predicts.
AGREEMENT_TOLERANCE = 1e-5


# --------------------------------------------------------------------------------------------
# Data


def training_data(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(v, p, target), (90, 16) float64 each: a simulated session measured as `calibrate_session`
    does (training captures, region averages, reference background of median brightness)."""
    with tempfile.TemporaryDirectory() as tmp:
        session = io.write_simulated_session(os.path.join(tmp, "session"), seed=seed)
        base = calibrate.base_calibration(session)
        training = session.frames_with(role="sample", set="training")
        measurements = calibrate.measure_frames(session, training, base)
        reference = calibrate.reference_background(measurements)
        return calibrate.stage2_training_data(measurements, reference)


def with_gross_outliers(target: np.ndarray, fraction: float = OUTLIER_FRACTION, seed: int = OUTLIER_SEED) -> np.ndarray:
    """`fraction` of the samples get errors of +-(0.1..0.3) in every band: a patch over a crease,
    a mislabelled capture. The same construction as tests/test_stage2.py's helper."""
    rng = np.random.default_rng(seed)
    dirty = target.copy()
    rows = rng.choice(len(target), int(round(fraction * len(target))), replace=False)
    signs = rng.choice([-1.0, 1.0], (len(rows), target.shape[1]))
    dirty[rows] += signs * rng.uniform(0.1, 0.3, (len(rows), target.shape[1]))
    return dirty


# --------------------------------------------------------------------------------------------
# The reference: numpy / scipy, one band at a time


def design_matrix(v: np.ndarray, p: np.ndarray) -> np.ndarray:
    """M = (p v, v, p, 1) of Eq. 20 for one band: (n,) -> (n, 4)."""
    return np.column_stack([p * v, v, p, np.ones_like(v)])


def reference_l2(v, p, target) -> np.ndarray:
    """Closed form per band with `np.linalg.lstsq` (SVD, as spherejax): (B, 4)."""
    return np.stack([
        np.linalg.lstsq(design_matrix(v[:, b], p[:, b]), target[:, b], rcond=None)[0]
        for b in range(v.shape[1])
    ])


def residual_scale(v, p, target) -> np.ndarray:
    """s = 1.4826 MAD of each band's closed-form residuals, (B,): the scale scipy's robust losses
    are given (and spherejax's "fixed s" rows)."""
    coeffs = reference_l2(v, p, target)
    residuals = target - np.asarray(stage2(v, p, coeffs))
    mad = np.median(np.abs(residuals - np.median(residuals, axis=0)), axis=0)
    return MAD_TO_SIGMA * mad


def reference_robust(v, p, target, loss: str, scale: np.ndarray) -> tuple[np.ndarray, dict]:
    """`scipy.optimize.least_squares` per band from the closed-form start: (B, 4) and statistics.

    scipy's f_scale is where the loss turns from quadratic: rho(f^2 / f_scale^2) with
    rho(z) = z below 1 (huber), log(1 + z) (cauchy). spherejax's loss with scale s is rho(e / s)
    with the 95 %-efficiency constant c (ROBUST_TUNING), so the same estimator needs
    f_scale = c s. The Jacobian is the constant design matrix, given exactly rather than by
    finite differences, so scipy is not charged for work a lab would not do.
    """
    tuning = ROBUST_TUNING[loss]
    coeffs, evaluations, converged = [], [], []
    for b in range(v.shape[1]):
        rows, y = design_matrix(v[:, b], p[:, b]), target[:, b]
        start = np.linalg.lstsq(rows, y, rcond=None)[0]
        fit = least_squares(
            lambda c: rows @ c - y, start, jac=lambda c: rows,
            loss=loss, f_scale=tuning * scale[b],
        )
        coeffs.append(fit.x)
        evaluations.append(fit.nfev)
        converged.append(fit.status > 0)  # 0: max_nfev reached; < 0: bad input
    return np.stack(coeffs), {"steps": evaluations, "converged": converged}


# --------------------------------------------------------------------------------------------
# The runs


def implementations(v, p, dirty, scale) -> dict:
    """name -> (loss, kind, function returning ready results). Every function fits `dirty`."""
    def spherejax_fit(loss, fixed_scale=None):
        return lambda: jax.block_until_ready(fit_stage2_detailed(v, p, dirty, loss, scale=fixed_scale))

    def v64(x):  # the reference always runs in float64, as a lab's numpy code would
        return np.asarray(x, np.float64)

    out = {
        "l2 spherejax": ("l2", "spherejax", spherejax_fit("l2")),
        "l2 numpy lstsq": ("l2", "reference", lambda: reference_l2(v64(v), v64(p), v64(dirty))),
    }
    for loss in ROBUST:
        out[f"{loss} spherejax"] = (loss, "spherejax", spherejax_fit(loss))
        out[f"{loss} spherejax fixed s"] = (loss, "spherejax fixed s", spherejax_fit(loss, scale))
        if loss in SCIPY_LOSSES:
            out[f"{loss} scipy"] = (
                loss, "reference", lambda loss=loss: reference_robust(v64(v), v64(p), v64(dirty), loss, scale)
            )
    return out


def describe(result, kind: str) -> dict:
    """Coefficients (float64), all-converged flag, problems and max steps of one result."""
    if kind == "reference":
        coeffs, stats = (result, None) if isinstance(result, np.ndarray) else result
        if stats is None:  # lstsq: a direct solve, nothing to converge
            return {"coeffs": coeffs, "all_converged": True, "problems": {}, "max_steps": 0}
        problems = {b: "not converged" for b, ok in enumerate(stats["converged"]) if not ok}
        return {"coeffs": coeffs, "all_converged": not problems, "problems": problems,
                "max_steps": int(max(stats["steps"]))}
    status = np.asarray(result.status)
    return {
        "coeffs": np.asarray(result.coeffs, np.float64),
        "all_converged": bool(np.all(status == CONVERGED)),
        "problems": result.problems(),
        "max_steps": int(np.max(np.asarray(result.steps))),
    }


def check_agreement(v, p, fits: dict) -> dict:
    """Max |prediction difference| of each spherejax result against its reference; raises
    AssertionError beyond AGREEMENT_TOLERANCE (a timing of a wrong answer is worthless)."""
    pairs = {"l2": ("l2 spherejax", "l2 numpy lstsq")}
    pairs.update({loss: (f"{loss} spherejax fixed s", f"{loss} scipy") for loss in SCIPY_LOSSES})
    out, bad = {}, []
    for loss, (ours, theirs) in pairs.items():
        prediction = [np.asarray(stage2(v, p, fits[name]["coeffs"])) for name in (ours, theirs)]
        diff = float(np.max(np.abs(prediction[0] - prediction[1])))
        coeff_diff = float(np.max(np.abs(fits[ours]["coeffs"] - fits[theirs]["coeffs"])))
        out[loss] = {"spherejax": ours, "reference": theirs, "prediction_max_abs_diff": diff,
                     "coeffs_max_abs_diff": coeff_diff}
        if not diff <= AGREEMENT_TOLERANCE:  # `not <=` so NaN fails too
            bad.append(f"{ours} vs {theirs}: prediction max |diff| {diff:.3g} > {AGREEMENT_TOLERANCE:g}")
    if bad:
        raise AssertionError("spherejax and the reference disagree: " + "; ".join(bad))
    return out


def clean_agreement(v, p, target) -> dict:
    """Every loss against the closed form on `target`: max |c_loss - c_l2| and max |prediction
    difference|, with each robust fit's status."""
    l2 = np.asarray(fit_stage2_detailed(v, p, target).coeffs, np.float64)
    out = {}
    for loss in ROBUST:
        fit = fit_stage2_detailed(v, p, target, loss)
        coeffs = np.asarray(fit.coeffs, np.float64)
        out[loss] = {
            "coeffs_max_abs_diff": float(np.max(np.abs(coeffs - l2))),
            "prediction_max_abs_diff": float(np.max(np.abs(
                np.asarray(stage2(v, p, coeffs)) - np.asarray(stage2(v, p, l2))))),
            "all_converged": bool(np.all(np.asarray(fit.status) == CONVERGED)),
            "max_steps": int(np.max(np.asarray(fit.steps))),
        }
    return out


def summarise(timings: dict, compile_s: dict, fits: dict, kinds: dict, c_clean: np.ndarray) -> dict:
    """Per implementation: times, speed ratios, distance to c_clean and the robustness ratio."""
    l2_distance = float(np.linalg.norm(fits["l2 spherejax"]["coeffs"] - c_clean))
    l2_median = timings["l2 spherejax"]["median_s"]
    out = {}
    for name, (loss, kind) in kinds.items():
        fit, t = fits[name], timings[name]
        distance = float(np.linalg.norm(fit["coeffs"] - c_clean))
        reference = "l2 numpy lstsq" if loss == "l2" else f"{loss} scipy"
        row = {
            "loss": loss,
            "implementation": kind,
            **t,
            "first_call_s": compile_s.get(name),
            # reference median / this median: > 1 means this one is faster.
            "speed_ratio_vs_reference": (
                timings[reference]["median_s"] / t["median_s"]
                if kind != "reference" and reference in timings else None
            ),
            "time_vs_spherejax_l2": t["median_s"] / l2_median,
            "distance_to_clean_fit": distance,
            "all_converged": fit["all_converged"],
            "problems": {str(b): s for b, s in fit["problems"].items()},
            "max_steps": fit["max_steps"],
        }
        if loss != "l2":
            ratio = l2_distance / distance if distance > 0 else float("inf")
            row["l2_distance_over_distance"] = ratio
            row["at_least_5x_closer"] = bool(ratio >= MIN_ROBUSTNESS_RATIO)
        out[name] = row
    return out


# --------------------------------------------------------------------------------------------
# Report


def fmt(x, spec: str, missing: str = "-") -> str:
    return missing if x is None else format(x, spec)


def print_report(summary: dict, agreement: dict, exact: dict, clean: dict, info: dict, data: dict, args) -> None:
    print(f"\nStage II fit, {data['samples']} samples x {data['bands']} bands "
          f"(simulated session, seed {args.seed}), {data['outlier_rows']} samples "
          f"({100 * OUTLIER_FRACTION:.0f} %) with gross errors; {args.dtype}, median of {args.repeats}")
    print(f"machine: {info['cpu_model']}, {info['nproc']} CPUs, jax {info['jax']}, optimistix "
          f"{info['optimistix']}, numpy {info['numpy']}, scipy {info['scipy']}")
    print(f"clean data: closed-form residual RMS {data['clean_residual_rms_min']:.1e}.."
          f"{data['clean_residual_rms_max']:.1e} per band (the measurement noise)")
    print(f"fixed scale s (1.4826 MAD of the closed-form residuals with outliers): "
          f"{data['fixed_scale_min']:.1e}..{data['fixed_scale_max']:.1e}")
    for loss, a in agreement.items():
        print(f"agreement {a['spherejax']} / {a['reference']}: prediction max |diff| "
              f"{a['prediction_max_abs_diff']:.1e}, coefficients {a['coeffs_max_abs_diff']:.1e}")

    header = (f"{'':<24}{'first ms':>9}{'median ms':>10}{'min ms':>8}{'vs ref':>8}{'vs l2':>7}"
              f"{'|c - c_clean|':>14}{'l2 / this':>10}{'':>5}{'steps':>6}  converged")
    print("\n" + header)
    print("-" * len(header))
    for name, r in summary.items():
        ratio = r.get("l2_distance_over_distance")
        verdict = "" if ratio is None else ("PASS" if r["at_least_5x_closer"] else "FAIL")
        first = None if r["first_call_s"] is None else 1e3 * r["first_call_s"]
        print(f"{name:<24}{fmt(first, '9.0f', '        -')}{1e3 * r['median_s']:>10.2f}"
              f"{1e3 * r['min_s']:>8.2f}{fmt(r['speed_ratio_vs_reference'], '7.1f', '      -'):>7}"
              f"{'x' if r['speed_ratio_vs_reference'] else ' '}"
              f"{r['time_vs_spherejax_l2']:>6.1f}x{r['distance_to_clean_fit']:>14.2e}"
              f"{fmt(ratio, '10.1f', '         -')}{verdict:>5}{r['max_steps']:>6}  "
              f"{'all' if r['all_converged'] else r['problems']}")
    print("-" * len(header))
    print("vs ref: reference median / this median (numpy lstsq for l2, scipy for huber and cauchy;")
    print("        scipy has no Tukey). vs l2: this median / spherejax closed-form median.")
    print("steps: spherejax IRLS iterations (Tukey: after its Huber start), scipy function "
          "evaluations; max over bands.")
    print("first ms: first call of that loss (trace + compile + run); the fixed-s rows reuse "
          "its executable.")

    print(f"\nclean data, max |c_loss - c_l2| (criterion: <= {CLEAN_TOLERANCE:g} on exact model data):")
    print(f"{'':<10}{'exact model data':>18}{'':>6}{'real clean data':>17}{'prediction':>12}")
    for loss in ROBUST:
        e, c = exact[loss], clean[loss]
        verdict = "PASS" if e["coeffs_max_abs_diff"] <= CLEAN_TOLERANCE else "FAIL"
        print(f"{loss:<10}{e['coeffs_max_abs_diff']:>18.1e}{verdict:>6}"
              f"{c['coeffs_max_abs_diff']:>17.1e}{c['prediction_max_abs_diff']:>12.1e}")
    print("exact model data: target = stage2(v, p, c_clean). Real clean data: the simulated "
          "targets, whose noise the robust")
    print("losses weight differently from least squares; the difference is of the order of the "
          "noise, not a criterion.")
    other = data["other_processes_cpu_fraction"]
    if other is not None:
        print(f"\nCPU used by other processes: {100 * other:.1f}% of the machine during timing")
        if other > 0.05:
            print("warning: other processes competed for the CPUs; the timings are pessimistic")


# --------------------------------------------------------------------------------------------


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=7, help="timed runs per implementation")
    parser.add_argument("--json", metavar="PATH", help="also write the results here")
    parser.add_argument("--seed", type=int, default=0, help="simulator seed")
    parser.add_argument("--dtype", choices=("float64", "float32"), default="float64",
                        help="dtype of the data given to spherejax (the reference is float64)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    info = machine_info()
    for dist in ("scipy", "optimistix"):
        info[dist] = metadata.version(dist)

    start = time.perf_counter()
    v, p, clean = training_data(args.seed)
    simulate_s = time.perf_counter() - start
    dirty = with_gross_outliers(clean)
    outlier_rows = int(np.sum(np.any(dirty != clean, axis=1)))
    c_clean = reference_l2(v, p, clean)
    scale = residual_scale(v, p, dirty)
    clean_residual_rms = np.sqrt(np.mean((clean - np.asarray(stage2(v, p, c_clean))) ** 2, axis=0))

    dtype = np.dtype(args.dtype)
    vd, pd, dirty_d = (x.astype(dtype) for x in (v, p, dirty))
    table = implementations(vd, pd, dirty_d, scale.astype(dtype))
    kinds = {name: (loss, kind) for name, (loss, kind, _) in table.items()}
    fns = {name: fn for name, (_, _, fn) in table.items()}

    # First calls before anything else touches these shapes, so each loss's compile is counted
    # once, in its own row; the fixed-s rows reuse the executable (the scale is a traced array).
    compile_s, fits = {}, {}
    for name, (loss, kind) in kinds.items():
        seconds, result = time_first_call(fns[name])
        if kind == "spherejax":
            compile_s[name] = seconds
        fits[name] = describe(result, "reference" if kind == "reference" else "spherejax")
    agreement = check_agreement(v, p, fits)

    with OtherProcessesLoad() as other_load:
        timings = time_interleaved(fns, args.repeats)
    summary = summarise(timings, compile_s, fits, kinds, c_clean)

    # c_clean is the float64 numpy fit; on exact data from it every loss must return it.
    exact = clean_agreement(vd, pd, np.asarray(stage2(v, p, c_clean)).astype(dtype))
    real_clean = clean_agreement(vd, pd, clean.astype(dtype))
    data = {
        "samples": int(v.shape[0]),
        "bands": int(v.shape[1]),
        "outlier_rows": outlier_rows,
        "simulate_and_measure_s": simulate_s,
        "clean_residual_rms_min": float(clean_residual_rms.min()),
        "clean_residual_rms_max": float(clean_residual_rms.max()),
        "fixed_scale_min": float(scale.min()),
        "fixed_scale_max": float(scale.max()),
        "other_processes_cpu_fraction": other_load.fraction,
    }
    print_report(summary, agreement, exact, real_clean, info, data, args)

    robust_ok = all(summary[f"{loss} spherejax"]["at_least_5x_closer"] for loss in ROBUST)
    exact_ok = all(exact[loss]["coeffs_max_abs_diff"] <= CLEAN_TOLERANCE for loss in ROBUST)
    converged_ok = all(r["all_converged"] for r in summary.values())
    print(f"\nrobust spherejax fits >= {MIN_ROBUSTNESS_RATIO:g}x closer to c_clean than the closed form: "
          f"{'PASS' if robust_ok else 'FAIL'}")
    print(f"every loss = closed form to {CLEAN_TOLERANCE:g} on exact model data: {'PASS' if exact_ok else 'FAIL'}")
    print(f"every band of every fit converged: {'yes' if converged_ok else 'NO'}")

    if args.json:
        record = {
            "benchmark": "bench_stage2_fit",
            "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "dtype": args.dtype,
            "seed": args.seed,
            "repeats": args.repeats,
            "outlier_fraction": OUTLIER_FRACTION,
            "outlier_seed": OUTLIER_SEED,
            "data": data,
            "fixed_scale": scale.tolist(),
            "clean_fit": c_clean.tolist(),
            "agreement_with_reference": agreement,
            "implementations": summary,
            "clean_vs_closed_form": {"exact_model_data": exact, "real_clean_data": real_clean},
            "criteria": {
                "robust_at_least_5x_closer": robust_ok,
                "exact_data_agrees_to_1e-4": exact_ok,
                "all_converged": converged_ok,
            },
            "machine": info,
            "argv": sys.argv,
        }
        write_record(args.json, record)
    return 0 if robust_ok and exact_ok else 1


if __name__ == "__main__":
    sys.exit(main())
