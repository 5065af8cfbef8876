"""What the uncertainties cost, and how right they are: `correct(..., noise=)` against `correct`,
and the propagated uncertainties against Monte Carlo (JCGM 101:2008).

Cost
    `spherejax.correct(raw, calibration)` and `spherejax.correct(raw, calibration,
    noise=NoiseModel(...))` on bench_correct's synthetic (size, size, 16) uint16 cube, as the user
    gets them (default path), timed in turns with the numpy + colour-science reference of the
    plain path (`reference.reference_correct`). The target: with noise, at most 3 times the
    plain call. The plain call's outputs are checked against the reference first.

Agreement with Monte Carlo
    `spherejax.monte_carlo`: the ColorChecker scene with dark, near-full-scale and neutral
    patches; every trial draws dark, white and sample frames from the camera's noise (Poisson
    electrons, read noise, averaging, 16-bit rounding) and runs the path. Reported per kind of
    pixel: the median over pixels of (median propagated u) / (empirical standard deviation) for
    L*, a*, b*, and the coverage of the true Lab (the path on noise-free frames) by the k = 2
    intervals. Then ΔE00 against a reference at a distance d from the true colour, d = 0 .. 4:
    first order is exact for a linear function of Gaussian inputs, and ΔE00 is a distance, so
    near d = 0 the propagated u (-> 0) and the mean of ΔE00 (a folded, not a Gaussian,
    distribution) part from the Monte Carlo: the table shows where.

Run:
    python benchmarks/bench_uncertainty.py [--size 1024] [--repeats 5] [--trials 400] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))

import harness  # noqa: E402
import reference  # noqa: E402

import spherejax  # noqa: E402
from spherejax import monte_carlo as mc  # noqa: E402
from spherejax import uncertainty  # noqa: E402


def cost(size: int, repeats: int) -> dict:
    inputs = reference.make_inputs(size)
    coeffs = reference.stage2_coeffs()
    wiener, offset = reference.wiener_estimator()
    calibration = reference.make_calibration(inputs, coeffs, wiener, offset)
    instrument = spherejax.simulate.InstrumentModel()
    noise = spherejax.NoiseModel(
        gain=instrument.gain_e_per_dn, read_noise=instrument.read_noise_e / instrument.gain_e_per_dn,
        dark_frames=16, white_frames=8, sample_frames=4,
    )
    xyz_weights, whitepoint = reference.reference_constants()
    expected = reference.reference_correct(
        inputs["raw"], inputs["dark"], inputs["white"], inputs["patch"], coeffs, wiener, xyz_weights, whitepoint, offset
    )
    reference.compare(spherejax.correct(inputs["raw"], calibration), expected)  # raises if not
    with_noise = spherejax.correct(inputs["raw"], calibration, noise=noise)
    if not np.all(np.isfinite(np.asarray(with_noise.lab_u)[np.asarray(with_noise.valid)])):
        raise SystemExit("lab_u is not finite on good pixels")
    timings = harness.time_interleaved(
        {
            "correct": lambda: jax.block_until_ready(spherejax.correct(inputs["raw"], calibration)),
            "correct(noise=)": lambda: jax.block_until_ready(spherejax.correct(inputs["raw"], calibration, noise=noise)),
            "numpy + colour-science": lambda: reference.reference_correct(
                inputs["raw"], inputs["dark"], inputs["white"], inputs["patch"], coeffs, wiener, xyz_weights, whitepoint, offset
            ),
        },
        repeats,
    )
    megapixels = size * size / 1e6
    out = {name: {"median_ms_per_mp": t["median_s"] * 1e3 / megapixels, "min_ms_per_mp": t["min_s"] * 1e3 / megapixels}
           for name, t in timings.items()}
    out["noise_over_plain"] = timings["correct(noise=)"]["median_s"] / timings["correct"]["median_s"]
    out["noise_over_reference"] = timings["correct(noise=)"]["median_s"] / timings["numpy + colour-science"]["median_s"]
    return out


def agreement(trials: int) -> dict:
    scene = mc.noise_scene(block=6)
    run = mc.run(scene, scene.noise_model(), trials=trials, seed=1)
    good = np.all(np.isfinite(run.lab), axis=(0, -1)) & (scene.kind != mc.KIND_PATCH)
    empirical = np.std(run.lab, axis=0, ddof=1)
    propagated = np.median(run.lab_u, axis=0)
    inside = np.abs(run.lab - run.true_lab) <= 2 * run.lab_u
    kinds = {}
    for kind, name in mc.KIND_NAMES.items():
        pixels = good & (scene.kind == kind)
        kinds[name] = {
            "pixels": int(pixels.sum()),
            "u_over_sd": np.median(propagated[pixels] / empirical[pixels], axis=0).tolist(),
            "coverage_k2": inside[:, pixels].mean(axis=(0, 1)).tolist(),
            "sd": np.median(empirical[pixels], axis=0).tolist(),
        }
    # ΔE00 against references at distance d along a fixed direction, at every chart pixel.
    pixels = good & (scene.kind == mc.KIND_CHART)
    lab, cov, true = run.lab[:, pixels], run.lab_covariance[:, pixels], run.true_lab[pixels]
    direction = np.array([1.0, -1.0, 1.0]) / np.sqrt(3.0)
    delta_e = {}
    for distance in (0.0, 0.1, 0.25, 0.5, 1.0, 2.0, 4.0):
        reference = true + distance * direction
        de = np.asarray(spherejax.delta_e_2000(jnp.asarray(lab), jnp.asarray(reference[None])))
        u = np.asarray(uncertainty.delta_e_uncertainty(jnp.asarray(lab), jnp.asarray(cov), jnp.asarray(reference[None].repeat(trials, 0))))
        true_de = np.asarray(spherejax.delta_e_2000(jnp.asarray(true), jnp.asarray(reference)))
        delta_e[distance] = {
            "true_delta_e": float(np.median(true_de)),
            "mean_delta_e": float(np.median(de.mean(axis=0))),
            "u_over_sd": float(np.median(np.median(u, axis=0) / de.std(axis=0, ddof=1))),
            "coverage_k2": float(np.mean(np.abs(de - true_de) <= 2 * u)),
        }
    return {"trials": trials, "kinds": kinds, "delta_e": delta_e}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=1024, help="image height = width for the cost")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per implementation")
    parser.add_argument("--trials", type=int, default=400, help="Monte Carlo trials")
    parser.add_argument("--json", metavar="PATH", help="also write the results here")
    args = parser.parse_args(argv)
    spherejax.keep_freed_memory()

    costs = cost(args.size, args.repeats)
    print(f"cost at {args.size} x {args.size} x 16 (ms per megapixel, median / min)")
    for name in ("correct", "correct(noise=)", "numpy + colour-science"):
        print(f"  {name:24s} {costs[name]['median_ms_per_mp']:8.1f} / {costs[name]['min_ms_per_mp']:8.1f}")
    print(f"  with noise / without: {costs['noise_over_plain']:.2f}x (target <= 3)   "
          f"with noise / reference (no uncertainty): {costs['noise_over_reference']:.2f}x")

    checks = agreement(args.trials)
    print(f"\nMonte Carlo, {checks['trials']} trials: propagated u / empirical sd, and coverage of k = 2 (L*, a*, b*)")
    for name, row in checks["kinds"].items():
        ratio = " ".join(f"{x:5.3f}" for x in row["u_over_sd"])
        cover = " ".join(f"{x:5.3f}" for x in row["coverage_k2"])
        print(f"  {name:16s} {row['pixels']:4d} px   u/sd {ratio}   coverage {cover}")
    print("\nΔE00 against a reference at distance d (chart pixels): where first order holds")
    print("  d      true ΔE00  mean ΔE00  u/sd   coverage k=2")
    for distance, row in checks["delta_e"].items():
        print(f"  {distance:4.2f}   {row['true_delta_e']:8.3f}   {row['mean_delta_e']:8.3f}  {row['u_over_sd']:5.2f}  {row['coverage_k2']:6.3f}")
    if args.json:
        record = {"cost": costs, "monte_carlo": checks, "machine": harness.machine_info()}
        pathlib.Path(args.json).write_text(json.dumps(record, indent=2, default=str))
    if costs["noise_over_plain"] > 3.0:
        print("\nnote: correct(noise=) took more than 3 times correct in this run", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
