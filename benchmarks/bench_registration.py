"""Bands in register: what registration costs `correct`, and the edge error it removes.

1. Cost. 1024 x 1024 x 16 uint16 frames (`reference.make_inputs`) with the Stage II and estimator
   of the calibration `spherejax calibrate` makes by default on a session simulated as the demo's,
   and band maps of 2 px (`band_geometry.band_transforms` at this frame size): `correct` of NumPy
   frames with the maps against the same calibration without them [target: at most 1.5x], on
   every variant of the fused CPU kernel this CPU runs (forced through SPHEREJAX_FUSED), and the
   numpy reference of the same work (Eq. 10 in each band's geometry, bilinear resampling with
   NumPy indexing, then `reference.reference_correct`). spherejax's registered frames are checked
   against the reference's before any timing (the same quality bits, values to 1e-4).
2. Edge error. The paper's experiment simulated twice with one seed (the same scenes and noise):
   bands 2 px out of register, and in register. Each calibrated by `calibrate_session` (the
   in-register one as the truth's stand-in), the misregistered one with and without registration.
   Every test capture corrected; ΔE00 (D65) to the in-register session's Lab at the materials'
   edges (`evaluate.material_edges`: within a pixel of a step of 3 in L*) and inside them, pixel
   by pixel and as the colour of each pixel's 3 x 3 neighbourhood (`evaluate.neighbourhood_delta_e`:
   what a colour fringe changes and a sub-pixel blur does not; pixel by pixel, the bilinear
   resampling's blur of up to half a pixel and its averaging of neighbours' noise count too);
   and the maps' RMS error over the frame.

Run:
    python benchmarks/bench_registration.py [--size 1024] [--repeats 7] [--seed 0] [--json FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile

import jax
import numpy as np

import spherejax
from spherejax import band_geometry, calibrate, evaluate, io, simulate
from spherejax._engine import fused

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_kernel_contract import default_calibration, fused_switch  # noqa: E402
from harness import machine_info, time_interleaved, write_record  # noqa: E402
from reference import SATURATION, make_inputs, numpy_registration, reference_constants, reference_correct  # noqa: E402


def cost(args, made: spherejax.Calibration) -> dict:
    inputs = make_inputs(args.size, args.seed)
    instrument = dataclasses.replace(simulate.InstrumentModel(), band_misregistration_px=2.0)
    maps = band_geometry.band_transforms(instrument, (args.size, args.size), 24.0, args.seed)
    plain = spherejax.Calibration(
        dark=inputs["dark"], white=inputs["white"], patch=inputs["patch"], coeffs=np.asarray(made.coeffs),
        wiener=np.asarray(made.wiener), wiener_offset=np.asarray(made.wiener_offset),
        wiener_residual=made.wiener_residual, saturation=float(SATURATION),
    )
    registered = dataclasses.replace(plain, band_transforms=maps)
    raw = inputs["raw"]
    weights, whitepoint = reference_constants()

    def reference():
        frames, signal, bits = numpy_registration(raw, inputs["dark"], inputs["white"], maps, SATURATION)
        return reference_correct(frames, np.zeros_like(signal), signal, inputs["patch"] & (bits == 0), np.asarray(made.coeffs),
                                 np.asarray(made.wiener), weights, whitepoint, np.asarray(made.wiener_offset))

    # Checked before timing: spherejax's registered frames are the reference's.
    want_frames, _, want_bits = numpy_registration(raw, inputs["dark"], inputs["white"], maps, SATURATION)
    got_frames, got_bits = spherejax.plan(registered, raw.shape).register(raw)
    if not np.array_equal(np.asarray(got_bits), want_bits):
        raise SystemExit("bench_registration: the registered quality bits differ from the reference's")
    difference = np.abs(np.asarray(got_frames) - want_frames) / np.maximum(np.abs(want_frames), 1.0)
    if not difference.max() < 1e-4:
        raise SystemExit(f"bench_registration: registered frames differ from the reference's by {difference.max():.2g}")

    rows = {}
    for variant in (v for v in fused.VARIANTS if v in fused.supported_variants()):
        with fused_switch(variant):
            times = time_interleaved({
                "unregistered": lambda: jax.block_until_ready(spherejax.correct(raw, plain).lab),
                "registered": lambda: jax.block_until_ready(spherejax.correct(raw, registered).lab),
                "registration alone": lambda: jax.block_until_ready(
                    spherejax.plan(registered, raw.shape).register(raw)[0]),
            }, args.repeats)
        rows[variant] = {name: {"median_ms": 1e3 * t["median_s"], "min_ms": 1e3 * t["min_s"]} for name, t in times.items()}
        rows[variant]["registered / unregistered"] = times["registered"]["median_s"] / times["unregistered"]["median_s"]
    reference_time = time_interleaved({"reference": reference}, max(2, args.repeats // 3))["reference"]
    return {"size": args.size, "largest_displacement_px": band_geometry.largest_displacement(maps, (args.size,) * 2),
            "variants": rows, "reference_median_ms": 1e3 * reference_time["median_s"],
            "largest_frame_difference": float(difference.max())}


def edge_error(args, folder: str) -> dict:
    def session(misregistration):
        instrument = dataclasses.replace(simulate.InstrumentModel(), band_misregistration_px=misregistration)
        return io.write_simulated_session(os.path.join(folder, f"at{misregistration}"), seed=args.seed,
                                          instrument=instrument)

    moved, still = session(2.0), session(0.0)
    truth, _ = calibrate.calibrate_session(still)
    registered, _ = calibrate.calibrate_session(moved)
    plain, _ = calibrate.calibrate_session(moved, registration=False)
    errors = {name: {"edge": [], "inside": [], "edge, 3 x 3 neighbourhoods": []}
              for name in ("registered", "not registered")}
    for frame in moved.frames_with(role="sample", set="test"):
        reference = spherejax.correct(still.read(frame.id), truth)
        reference_lab = np.asarray(reference.lab, np.float64)
        near = evaluate.material_edges(reference_lab)
        for name, calibration in (("registered", registered), ("not registered", plain)):
            result = spherejax.correct(moved.read(frame.id), calibration)
            error = np.asarray(spherejax.delta_e_2000(np.asarray(result.lab, np.float64), reference_lab))
            fringe = evaluate.neighbourhood_delta_e(np.asarray(result.reflectance), np.asarray(reference.reflectance))
            usable = np.isfinite(error) & np.isfinite(fringe)
            errors[name]["edge"].append(error[near & usable])
            errors[name]["inside"].append(error[~near & usable])
            errors[name]["edge, 3 x 3 neighbourhoods"].append(fringe[near & usable])
    summary = {}
    for name, parts in errors.items():
        summary[name] = {}
        for where, values in parts.items():
            values = np.concatenate(values)
            summary[name][where] = {"median": float(np.median(values)), "p95": float(np.percentile(values, 95)),
                                    "pixels": int(values.size)}
    maps_error = band_geometry.rms_displacement(np.asarray(registered.band_transforms, np.float64),
                                                moved.band_transforms, moved.image_shape)
    summary["maps_rms_error_px"] = {"max": float(maps_error.max()), "mean": float(maps_error.mean())}
    return summary


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip-edges", action="store_true", help="time only (the edge error simulates two sessions)")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    record = {"machine": machine_info(), "seed": args.seed}
    with tempfile.TemporaryDirectory() as folder:
        made = default_calibration(folder, args.seed)
        record["cost"] = cost(args, made)
        if not args.skip_edges:
            record["edge_error"] = edge_error(args, os.path.join(folder, "edges"))
    c = record["cost"]
    print(f"cost at {c['size']}² x 16, maps of {c['largest_displacement_px']:.2f} px "
          f"(frames checked against the numpy reference: {c['largest_frame_difference']:.1e}):")
    for variant, row in c["variants"].items():
        print(f"  {variant:8s} unregistered {row['unregistered']['median_ms']:7.1f} ms, registered "
              f"{row['registered']['median_ms']:7.1f} ms ({row['registered / unregistered']:.2f}x; the registration "
              f"alone {row['registration alone']['median_ms']:.1f} ms); reference {c['reference_median_ms']:.0f} ms")
    if "edge_error" in record:
        e = record["edge_error"]
        for name in ("registered", "not registered"):
            fringe = e[name]["edge, 3 x 3 neighbourhoods"]
            print(f"  ΔE00 to the in-register session, {name:15s}: edges, 3 x 3 neighbourhoods median "
                  f"{fringe['median']:.2f} (p95 {fringe['p95']:.2f}, {fringe['pixels']} px); edges pixel by pixel "
                  f"median {e[name]['edge']['median']:.2f} (p95 {e[name]['edge']['p95']:.2f}); inside median "
                  f"{e[name]['inside']['median']:.2f} (p95 {e[name]['inside']['p95']:.2f})")
        print(f"  maps' RMS error over the frame: at most {e['maps_rms_error_px']['max']:.3f} px")
    if args.json:
        write_record(args.json, record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
