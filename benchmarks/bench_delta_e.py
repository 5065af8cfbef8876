"""Throughput of `spherejax.delta_e_2000` against colour-science's CIEDE2000, float32 and float64.

What it measures
    `spherejax.delta_e_2000(lab1, lab2)` (jitted, Sharma et al. 2005) on N pairs of Lab colours
    (default 10^6), in float32 and in float64 (jax x64 on).

Against what
    `colour.delta_E(lab1, lab2, method="CIE 2000")` on the same pairs in the same run (numpy;
    colour-science computes in float64 whatever it is given). Before timing, the two must agree
    within 1e-4 ΔE00 (float64) and 2e-3 (float32, over pairs away from the hue discontinuity
    where float32 rounding can legitimately pick the other side: see tests/test_delta_e.py).

Inputs
    Lab pairs from a fixed seed: L* 0..100, a*, b* -100..100, the second colour a small random
    step (ΔE up to ~10) from the first, as colour-difference work sees them, plus the 34 pairs of
    Sharma et al.'s Table 1 at the front.

Timing as bench_correct.py: the first call (trace + compile) apart, then spherejax and the
reference take turns for --repeats calls; median and minimum, block_until_ready on JAX results.

Run:
    python benchmarks/bench_delta_e.py [--pairs 1000000] [--repeats 7] [--allocator reuse|default]
        [--json PATH]

    --allocator as in bench_correct.py: by default glibc keeps freed blocks, as the command line
    has it, for both implementations. It matters here too: without it every call page-faults on
    XLA's fresh output buffers, and spherejax takes twice as long.
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import warnings

import numpy as np

warnings.filterwarnings("ignore", message=".*Matplotlib.* related API features are not available")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import colour  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from harness import OtherProcessesLoad, add_allocator_argument, apply_allocator_argument, machine_info, time_first_call, time_interleaved, write_record  # noqa: E402

import spherejax  # noqa: E402

SEED = 20050101
# Sharma, Wu, Dalal (2005), Table 1, doi:10.1002/col.20070: kept with the tests' reference data
# (tests/data/README.md cites it), so a clone benchmarks the same pairs as the tests check.
SHARMA_CSV = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests", "data", "sharma2005_ciede2000.csv")
TOLERANCE = {"float64": 1e-4, "float32": 2e-3}


def make_pairs(n: int, seed: int = SEED) -> tuple[np.ndarray, np.ndarray]:
    """(lab1, lab2), each (n, 3) float64."""
    rng = np.random.default_rng(seed)
    lab1 = np.column_stack([rng.uniform(0, 100, n), rng.uniform(-100, 100, n), rng.uniform(-100, 100, n)])
    lab2 = lab1 + rng.normal(0, 3.0, (n, 3))
    # Read unconditionally: the table is in the repository, and a missing copy must fail the run
    # rather than silently benchmark (and check) without the published pairs.
    table = np.loadtxt(SHARMA_CSV, delimiter=",", skiprows=1)
    k = min(n, len(table))
    lab1[:k], lab2[:k] = table[:k, 1:4], table[:k, 4:7]
    return lab1, lab2


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--json", metavar="PATH")
    add_allocator_argument(parser)
    args = parser.parse_args(argv)
    allocator = apply_allocator_argument(args)
    info = machine_info()
    info["allocator"] = allocator
    lab1, lab2 = make_pairs(args.pairs)
    expected = np.asarray(colour.delta_E(lab1, lab2, method="CIE 2000"))

    delta_e = spherejax.delta_e_2000  # jitted by spherejax (a jax.jit around it would drop its compiler options)
    results, failures = {}, []
    for name, dtype in (("float32", np.float32), ("float64", np.float64)):
        a, b = jax.device_put(lab1.astype(dtype)), jax.device_put(lab2.astype(dtype))
        compile_s, out = time_first_call(lambda: delta_e(a, b))  # noqa: B023
        error = np.abs(np.asarray(out, np.float64) - expected)
        # float32 may take the other side of the hue switch for pairs within rounding of it.
        worst = float(np.quantile(error, 0.9999)) if name == "float32" else float(error.max())
        if worst > TOLERANCE[name]:
            failures.append(f"{name}: ΔE00 differs from colour-science by {worst:.3g} > {TOLERANCE[name]}")
        a_np, b_np = lab1.astype(dtype), lab2.astype(dtype)
        with OtherProcessesLoad() as load:
            timings = time_interleaved({
                "spherejax": lambda: jax.block_until_ready(delta_e(a, b)),  # noqa: B023
                "colour-science": lambda: colour.delta_E(a_np, b_np, method="CIE 2000"),  # noqa: B023
            }, args.repeats)
        ratio = timings["colour-science"]["median_s"] / timings["spherejax"]["median_s"]
        results[name] = {
            "compile_s": compile_s, "max_abs_diff": float(error.max()), "checked_quantile_diff": worst,
            "timings": timings, "ratio": ratio, "other_load": load.fraction,
        }
    if failures:
        print("agreement FAILED: " + "; ".join(failures))
        return 1

    print(f"ΔE00 on {args.pairs:,} Lab pairs, median of {args.repeats} ({info['cpu_model']}, {info['nproc']} CPUs, "
          f"allocator {allocator})")
    print(f"{'dtype':8} {'spherejax ms':>13} {'colour-science ms':>18} {'ratio':>7} {'Mpairs/s':>9} {'compile s':>10} {'max |diff|':>11} {'other load':>11}")
    for name, r in results.items():
        t = r["timings"]
        print(f"{name:8} {t['spherejax']['median_s'] * 1e3:13.1f} {t['colour-science']['median_s'] * 1e3:18.1f} "
              f"{r['ratio']:6.1f}x {args.pairs / t['spherejax']['median_s'] / 1e6:9.1f} {r['compile_s']:10.2f} "
              f"{r['max_abs_diff']:11.2e} {r['other_load'] * 100 if r['other_load'] is not None else float('nan'):10.0f}%")
    if args.json:
        record = {
            "benchmark": "bench_delta_e", "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "pairs": args.pairs, "repeats": args.repeats, "results": results, "machine": info, "argv": sys.argv,
        }
        write_record(args.json, record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
