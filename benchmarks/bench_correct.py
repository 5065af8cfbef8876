"""Throughput of `spherejax.correct` against a numpy + colour-science reference of the same path.

What it measures
    `spherejax.correct(raw, calibration)` on one synthetic (size, size, 16) uint16 cube: quality
    mask -> flat field (Eq. 10) -> white-patch ratio (Eq. 14-15) -> Stage II (Eq. 23) -> Wiener
    (16 -> 31, affine: W v + r0) -> XYZ (ASTM E308) -> CIELAB, output reflectance (H, W, 31) and Lab (H, W, 3).

Against what
    `reference_correct` below: the same path written the way a lab would write it without JAX,
    in numpy (float32 where numpy allows) with colour-science's `XYZ_to_Lab` for the last step.
    Both run in the same process on the same inputs, and their outputs are checked to agree
    before anything is timed (reflectance within 1e-4, Lab within 1e-2, identical quality masks).

    A third row times the same `spherejax.correct` call with its fused CPU kernel switched off
    (SPHEREJAX_FUSED=0, `spherejax._engine.fused`): the jax.numpy path the kernel replaced, which is
    still what runs on GPUs, in float64 and for gradients. It must agree with the reference too.

    A further figure puts them in physical terms: the memory floor. The path must read the raw cube
    (uint16), the dark frame and the white standard (float32) and write reflectance, Lab (float32)
    and the quality mask (uint8), 297 bytes per pixel; at the machine's copy bandwidth, measured
    in the same run, that takes `floor` seconds. docs/design.md, "Performance model".

Timing follows the optimistix / equinox benchmarks: the first call (trace + compile + run) is
reported on its own, then each implementation is timed `--repeats` times, the two taking turns,
and the median and the minimum are reported, with `jax.block_until_ready` on the JAX result (JAX
dispatches asynchronously, so without it only the dispatch would be timed). The share of CPU time
other processes took during timing is recorded, since on 2 cores it shows up in every figure.

Then each implementation is timed again back to back: `--repeats` calls in a plain loop of its
own, as a script that corrects a folder runs it. The two orders differ for XLA's programs: taking
turns, each jax.numpy call comes after 0.2 s of the reference on one core, and XLA's threads,
idle that long, join its steps late (on virtual machines, whose idle CPUs sleep deeper the
longer they wait: benchmarks/README.md, "a Zen 5 machine, the jax.numpy path back to back").
Both are reported, with their ratios to the reference timed the same way.

Run:
    python benchmarks/bench_correct.py [--size 1024] [--repeats 7] [--allocator reuse|default]
        [--json PATH]

Allocator: by default the script first calls `spherejax._engine.allocator.keep_freed_memory()`, as the
command line does, so neither implementation pays the kernel for fresh zeroed pages on every
call; `--allocator default` leaves glibc as it comes (that module's docstring says why it matters).
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys

import jax

import spherejax
from harness import (
    OtherProcessesLoad, add_allocator_argument, apply_allocator_argument, copy_bandwidth, machine_info, time_back_to_back,
    time_first_call, time_interleaved, write_record,
)
from reference import (
    BANDS, BYTES_PER_PIXEL, PATCH_SIZE, compare, make_calibration, make_inputs, reference_constants, reference_correct,
    stage2_coeffs, wiener_estimator,
)
from spherejax._engine import fused


def summarise(size: int, timings: dict, compile_s: float, bandwidth: dict, other_load, back_to_back: dict) -> dict:
    """Derived figures: MP/s, ms/MP, the ratios, and the fraction of the memory floor reached."""
    megapixels = size * size / 1e6
    floor_s = {name: size * size * BYTES_PER_PIXEL / bw for name, bw in bandwidth.items()}
    out = {"megapixels": megapixels, "compile_and_first_run_s": compile_s, "implementations": {}}
    for name, t in timings.items():
        out["implementations"][name] = {
            **t,
            "mp_per_s": megapixels / t["median_s"],
            "mp_per_s_best": megapixels / t["min_s"],
            "ms_per_mp": 1e3 * t["median_s"] / megapixels,
            # floor / measured: 1.0 would mean the path runs at memory speed.
            "floor_fraction": {bw: floor_s[bw] / t["median_s"] for bw in floor_s},
        }
    out["speed_ratio_spherejax_over_reference"] = (
        timings["reference"]["median_s"] / timings["spherejax"]["median_s"]
    )
    out["speed_ratio_jax_numpy_path_over_reference"] = (
        timings["reference"]["median_s"] / timings["spherejax jax.numpy path"]["median_s"]
    )
    out["back_to_back"] = {
        name: {
            **t, "ms_per_mp": 1e3 * t["median_s"] / megapixels,
            "speed_ratio_over_reference": back_to_back["reference"]["median_s"] / t["median_s"],
            "floor_fraction": {bw: floor_s[bw] / t["median_s"] for bw in floor_s},
        }
        for name, t in back_to_back.items()
    }
    out["bytes_per_pixel"] = BYTES_PER_PIXEL
    out["copy_bandwidth_gb_per_s"] = {k: v / 1e9 for k, v in bandwidth.items()}
    out["floor_ms_per_mp"] = {k: 1e3 * v / megapixels for k, v in floor_s.items()}
    out["other_processes_cpu_fraction"] = other_load
    return out


def print_report(summary: dict, agreement: dict, info: dict, size: int, repeats: int) -> None:
    print(f"\nspherejax.correct vs numpy + colour-science, {size} x {size} x {BANDS} uint16 "
          f"({summary['megapixels']:.3f} MP), median of {repeats}")
    print(f"machine: {info['cpu_model']}, {info['nproc']} CPUs, jax {info['jax']}, "
          f"numpy {info['numpy']}, colour-science {info['colour-science']}, "
          f"allocator {info.get('allocator', 'glibc default')}, "
          f"fused kernel {'on' if info.get('fused_kernel') else 'off'}")
    print(f"agreement over {agreement['valid_pixels']} valid pixels "
          f"({agreement['bad_pixels']} flagged bad in both): "
          f"reflectance max |diff| {agreement['reflectance_max_abs_diff']:.2e}, "
          f"Lab max |diff| {agreement['lab_max_abs_diff']:.2e}")
    header = f"{'':<26}{'median ms':>11}{'min ms':>9}{'MP/s':>9}{'ms/MP':>9}{'floor %':>9}"
    print("\n" + header)
    print("-" * len(header))
    for name, r in summary["implementations"].items():
        print(f"{name:<26}{1e3 * r['median_s']:>11.1f}{1e3 * r['min_s']:>9.1f}{r['mp_per_s']:>9.2f}"
              f"{r['ms_per_mp']:>9.1f}{100 * r['floor_fraction']['all_threads']:>9.1f}")
    print("-" * len(header))
    print(f"speed ratio spherejax / reference:   {summary['speed_ratio_spherejax_over_reference']:.2f}x")
    print(f"jax.numpy path / reference:          {summary['speed_ratio_jax_numpy_path_over_reference']:.2f}x")
    print(f"\nback to back ({repeats} calls of each in a plain loop of its own)")
    header = f"{'':<26}{'median ms':>11}{'min ms':>9}{'ms/MP':>9}{'floor %':>9}{'vs ref':>9}"
    print(header)
    print("-" * len(header))
    for name, r in summary["back_to_back"].items():
        print(f"{name:<26}{1e3 * r['median_s']:>11.1f}{1e3 * r['min_s']:>9.1f}{r['ms_per_mp']:>9.1f}"
              f"{100 * r['floor_fraction']['all_threads']:>9.1f}{r['speed_ratio_over_reference']:>8.2f}x")
    print("-" * len(header))
    print(f"spherejax compile + first run:       {summary['compile_and_first_run_s']:.2f} s")
    bw = summary["copy_bandwidth_gb_per_s"]
    floor = summary["floor_ms_per_mp"]
    threads = f"{info['nproc']}-thread copy (numpy, chunked):"
    print(f"{'single-thread copy (numpy):':<37}{bw['single_thread']:.1f} GB/s "
          f"-> floor {floor['single_thread']:.1f} ms/MP")
    print(f"{threads:<37}{bw['all_threads']:.1f} GB/s "
          f"-> floor {floor['all_threads']:.1f} ms/MP  (floor % above is against this)")
    print(f"{'bytes moved per pixel:':<37}{BYTES_PER_PIXEL} (read + written)")
    other = summary["other_processes_cpu_fraction"]
    if other is not None:
        print(f"{'CPU used by other processes:':<37}{100 * other:.1f}% of the machine during timing")
        if other > 0.05:
            print("warning: other processes competed for the CPUs; the timings are pessimistic")


# --------------------------------------------------------------------------------------------


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=1024, help="image height = width in pixels")
    parser.add_argument("--repeats", type=int, default=7, help="timed runs per implementation")
    parser.add_argument("--json", metavar="PATH", help="also write the results here")
    parser.add_argument("--copy-mib", type=int, default=512, help="buffer size of the copy test")
    add_allocator_argument(parser)
    args = parser.parse_args(argv)
    if args.size < PATCH_SIZE + 8:
        parser.error(f"--size must be at least {PATCH_SIZE + 8} to hold the white patch")
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    allocator = apply_allocator_argument(args)
    info = machine_info()
    info["allocator"] = allocator
    # "spherejax" is the fused CPU kernel unless it was not built or SPHEREJAX_FUSED=0 is set.
    info["fused_kernel"] = fused.enabled()

    coeffs = stage2_coeffs()
    wiener, wiener_offset = wiener_estimator()
    inputs = make_inputs(args.size)
    calibration = make_calibration(inputs, coeffs, wiener, wiener_offset)
    xyz_weights, whitepoint_xy = reference_constants()

    def run_spherejax():
        return jax.block_until_ready(spherejax.correct(inputs["raw"], calibration))

    def run_spherejax_jnp():
        # The same call with the fused CPU kernel switched off: the jax.numpy path it replaced.
        previous = os.environ.get(fused.SWITCH)
        os.environ[fused.SWITCH] = "0"
        try:
            return jax.block_until_ready(spherejax.correct(inputs["raw"], calibration))
        finally:
            if previous is None:
                del os.environ[fused.SWITCH]
            else:
                os.environ[fused.SWITCH] = previous

    def run_reference():
        return reference_correct(
            inputs["raw"], inputs["dark"], inputs["white"], inputs["patch"],
            coeffs, wiener, xyz_weights, whitepoint_xy, wiener_offset,
        )

    compile_s, result = time_first_call(run_spherejax)
    reference = run_reference()
    agreement = compare(result, reference)
    compare(run_spherejax_jnp(), reference)  # the jax.numpy path must agree too
    del result, reference  # keep the timed runs' memory the same for all implementations

    copy_bytes = args.copy_mib * 2**20
    with OtherProcessesLoad() as other_load:
        timings = time_interleaved(
            {"spherejax": run_spherejax, "spherejax jax.numpy path": run_spherejax_jnp,
             "reference": run_reference}, args.repeats
        )
        back_to_back = time_back_to_back(
            {"spherejax": run_spherejax, "spherejax jax.numpy path": run_spherejax_jnp,
             "reference": run_reference}, args.repeats
        )
        bandwidth = {
            "single_thread": copy_bandwidth(copy_bytes, threads=1),
            "all_threads": copy_bandwidth(copy_bytes, threads=info["nproc"]),
        }
    summary = summarise(args.size, timings, compile_s, bandwidth, other_load.fraction, back_to_back)
    print_report(summary, agreement, info, args.size, args.repeats)

    if args.json:
        record = {
            "benchmark": "bench_correct",
            "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "size": args.size,
            "bands": BANDS,
            "repeats": args.repeats,
            "copy_mib": args.copy_mib,
            "agreement": agreement,
            **summary,
            "machine": info,
            "argv": sys.argv,
        }
        write_record(args.json, record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
