"""The kernel contract's speed bounds, for the calibration `calibrate` makes by default, on every
instruction-set variant this CPU runs.

What it measures (the issue's targets in brackets), all in one run, as same-run ratios:
  1. A session simulated as the demo's and calibrated with `spherejax calibrate` (its default
     estimator: `auto`, which takes the residual kernel estimator where cross-validation shows a
     gain); its Stage II and estimator applied to 1024 x 1024 x 16 uint16 frames
     (`reference.make_inputs`), with and without the kernel residual (the "affine twin").
  2. For each variant of the fused CPU kernel this CPU runs, forced through SPHEREJAX_FUSED (so
     that an AVX-512 machine measures the AVX2 code that CPUs without AVX-512 run), `correct` of
     NumPy frames (as an archive reads them) with the kernel calibration and with its twin:
     kernel / affine [<= 3x], reference / kernel [>= 5x], reference / affine [>= 10x], and the
     affine call's fraction of the all-threads copy floor [>= 35 %].
  3. The reference: numpy + colour-science of the affine twin (`reference.reference_correct`),
     checked against spherejax's affine result before any timing.
  4. The costliest residual a fit may make (the largest of `kernel_residual.INDUCING_POINT_COUNTS`
     at the largest of `RANKS`) [<= 3x], and any other counts and ranks asked for with
     `--residuals` (e.g. 80r8,96r4,128r8: what a larger bound would cost), each built on the
     default's whitening with inducing points drawn again near its own and weights of that rank
     (the kernel's time does not depend on the values: it has no data-dependent step), against
     the same affine twin, timed in a round of their own (after the reference in one round they
     read 4-5x, from the reference's memory traffic).

Every row names the CPU model and its widest instruction set. Run:
    python benchmarks/bench_kernel_contract.py [--size 1024] [--repeats 9] [--residuals 80r8,96r4] [--json FILE]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import os
import sys
import tempfile

import jax
import numpy as np

import spherejax
from spherejax._engine import fused
from spherejax.estimation import KernelResidual, kernel_residual

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from harness import copy_bandwidth, cpu_info, machine_info, time_interleaved, write_record  # noqa: E402
from reference import BANDS, SATURATION, compare, make_inputs, reference_constants, reference_correct  # noqa: E402

#: Bytes a pixel of `correct` must move: raw 16 x 2, dark and white 16 x 4 each read; reflectance
#: 31 x 4, Lab 3 x 4 and quality 1 written (as bench_correct.py).
BYTES_PER_PIXEL = 32 + 64 + 64 + 124 + 12 + 1


def default_calibration(folder: str, seed: int) -> spherejax.Calibration:
    """The calibration `spherejax calibrate` makes by default from a session simulated as the
    demo's (`spherejax simulate`), opened from its file."""
    from spherejax.cli.run import main as cli

    session, calibration = os.path.join(folder, "session"), os.path.join(folder, "cal.h5")
    with contextlib.redirect_stdout(open(os.devnull, "w")):
        if cli(["simulate", "-o", session, "--seed", str(seed)]) != 0:
            raise SystemExit("bench_kernel_contract: spherejax simulate failed")
        if cli(["calibrate", session, "-o", calibration]) != 0:
            raise SystemExit("bench_kernel_contract: spherejax calibrate failed")
    with spherejax.io.open_calibration(calibration) as opened:
        return opened.calibration()


def residual_at(residual: KernelResidual, m: int, r: int, seed: int) -> KernelResidual:
    """A residual of m inducing points and weights of rank r on `residual`'s whitening: inducing
    points its own, drawn again with a perturbation of 0.3 whitened units, weights of its scale."""
    rng = np.random.default_rng(seed)
    Z0, A0 = np.asarray(residual.inducing, np.float64), np.asarray(residual.weights, np.float64)
    Z = Z0[rng.integers(0, len(Z0), size=m)] + rng.normal(scale=0.3, size=(m, residual.bands))
    A = rng.normal(size=(31, r)) @ rng.normal(size=(r, m)) * (np.std(A0) / np.sqrt(r))
    return KernelResidual(*(np.asarray(x, np.float32) for x in (residual.centre, residual.whitening, Z, A)))


def residual_sizes(text: str) -> list[tuple[int, int]]:
    """[(m, r)]: the costliest a fit makes, then those of `--residuals` ("80r8,96r4")."""
    sizes = [(max(kernel_residual.INDUCING_POINT_COUNTS), max(kernel_residual.RANKS))]
    for item in filter(None, text.split(",")):
        m, _, r = item.partition("r")
        if not (m.isdigit() and r.isdigit() and int(m) > 0 and 0 < int(r) <= 8):
            raise SystemExit(f"bench_kernel_contract: --residuals: expected items like 80r8 (m >= 1, rank 1-8), got {item!r}")
        sizes.append((int(m), int(r)))
    return sizes


@contextlib.contextmanager
def fused_switch(value: str):
    previous = os.environ.get(fused.SWITCH)
    os.environ[fused.SWITCH] = value
    try:
        yield
    finally:
        if previous is None:
            del os.environ[fused.SWITCH]
        else:
            os.environ[fused.SWITCH] = previous


def widest_instruction_set(flags: str) -> str:
    for name, flag in (("AVX-512", "avx512f"), ("AVX2", "avx2"), ("SSE4.2", "sse4_2")):
        if flag in flags.split():
            return name
    return "x86-64"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--copy-mib", type=int, default=256)
    parser.add_argument("--residuals", default="", help="more residual sizes to time, e.g. 80r8,96r4")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)

    info = machine_info()
    cpu = cpu_info()
    with open("/proc/cpuinfo") as f:
        flags = next((line.split(":", 1)[1] for line in f if line.startswith("flags")), "")
    machine = (f"{cpu.get('model_name', 'unknown CPU')} family {cpu.get('family')} model {cpu.get('model')} "
               f"({widest_instruction_set(flags)}), {info['nproc']} threads")

    with tempfile.TemporaryDirectory() as folder:
        made = default_calibration(folder, args.seed)
    if made.wiener_residual is None:
        # Not a failure of spherejax: cross-validation found no gain on this session.
        print(f"bench_kernel_contract: calibrate's default took an affine estimator on the session of seed {args.seed}; "
              "nothing to measure (try another --seed)")
        return 0
    inputs = make_inputs(args.size)
    kernel = spherejax.Calibration(
        dark=inputs["dark"], white=inputs["white"], patch=inputs["patch"], coeffs=np.asarray(made.coeffs),
        wiener=np.asarray(made.wiener), wiener_offset=np.asarray(made.wiener_offset), illuminant="D65",
        saturation=SATURATION, wiener_residual=made.wiener_residual,
    )
    affine = dataclasses.replace(kernel, wiener_residual=None)
    sized = {f"m{m} r{r}": dataclasses.replace(kernel, wiener_residual=residual_at(made.wiener_residual, m, r, args.seed))
             for m, r in residual_sizes(args.residuals)}
    raw = inputs["raw"]
    xyz_weights, whitepoint_xy = reference_constants()

    def run_reference():
        return reference_correct(raw, inputs["dark"], inputs["white"], inputs["patch"], np.asarray(made.coeffs),
                                 np.asarray(made.wiener), xyz_weights, whitepoint_xy, np.asarray(made.wiener_offset))

    reference = run_reference()
    compare(jax.block_until_ready(spherejax.correct(raw, affine)), reference)  # exits non-zero on disagreement
    del reference

    megapixels = args.size * args.size / 1e6
    floor_s = args.size * args.size * BYTES_PER_PIXEL / copy_bandwidth(args.copy_mib << 20, threads=info["nproc"])
    rows = []
    variants = fused.supported_variants() if fused.enabled() else ()
    for variant in variants:
        with fused_switch(variant):
            modes = {label: spherejax.plan(c, raw.shape, dtype=raw.dtype).kernel_mode
                     for label, c in (("affine", affine), ("kernel", kernel))}
            # Each result is checked against the other route before timing: the kernel against the
            # jax.numpy definition of the same calibration.
            with fused_switch("0"):
                definition = spherejax.correct(raw, kernel)
            got = spherejax.correct(raw, kernel)
            good = np.asarray(got.quality) == 0
            error = float(np.max(np.abs(np.asarray(got.reflectance)[good] - np.asarray(definition.reflectance)[good])))
            if not error < 1e-4:
                raise SystemExit(f"bench_kernel_contract: the {variant} kernel differs from the definition by {error}")
            del definition, got
            timed = time_interleaved({
                "affine": lambda: jax.block_until_ready(spherejax.correct(raw, affine).lab),
                "kernel": lambda: jax.block_until_ready(spherejax.correct(raw, kernel).lab),
                "reference": run_reference,
            }, args.repeats)
            by_size = time_interleaved({
                "affine": lambda: jax.block_until_ready(spherejax.correct(raw, affine).lab),
                **{label: (lambda c=c: jax.block_until_ready(spherejax.correct(raw, c).lab)) for label, c in sized.items()},
            }, args.repeats)
        t = {name: timed[name]["median_s"] for name in timed}
        rows.append({
            "variant": variant, "kernel_modes": modes, "median_s": t, "max_abs_vs_definition": error,
            "kernel_over_affine": t["kernel"] / t["affine"], "reference_over_kernel": t["reference"] / t["kernel"],
            "reference_over_affine": t["reference"] / t["affine"], "affine_copy_floor_fraction": floor_s / t["affine"],
            "sizes_over_affine": {label: by_size[label]["median_s"] / by_size["affine"]["median_s"] for label in sized},
            "sizes_round_median_s": {name: by_size[name]["median_s"] for name in by_size},
        })

    residual = made.wiener_residual
    print(f"bench_kernel_contract: {args.size} x {args.size} x {BANDS} uint16 NumPy frames, median of {args.repeats}; "
          f"calibration from `spherejax calibrate` (seed {args.seed}): kernel estimator, "
          f"{residual.inducing.shape[0]} inducing points; jax {jax.__version__}")
    print(f"{'machine':<48} {'variant':<8} {'affine ms':>9} {'kernel ms':>9} {'ref ms':>8} {'kern/aff':>8} "
          f"{'ref/kern':>8} {'ref/aff':>8} {'floor':>6}")
    for row in rows:
        t = row["median_s"]
        print(f"{machine[:48]:<48} {row['variant']:<8} {1e3 * t['affine']:9.1f} {1e3 * t['kernel']:9.1f} "
              f"{1e3 * t['reference']:8.0f} {row['kernel_over_affine']:8.2f} {row['reference_over_kernel']:8.1f} "
              f"{row['reference_over_affine']:8.1f} {100 * row['affine_copy_floor_fraction']:5.1f}%  "
              + ", ".join(f"{label} {ratio:.2f}x" for label, ratio in row["sizes_over_affine"].items()))
    print(f"copy floor {1e3 * floor_s / megapixels:.1f} ms/MP ({BYTES_PER_PIXEL} bytes a pixel at the all-threads copy bandwidth)")
    if args.json:
        write_record(args.json, {
            "benchmark": "bench_kernel_contract", "size": args.size, "repeats": args.repeats, "rows": rows,
            "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "machine": {**info, "instruction_set": widest_instruction_set(flags)}, "argv": sys.argv,
        })
    return 0


if __name__ == "__main__":
    sys.exit(main())
