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
from spherejax import band_geometry, band_resampling, calibrate, evaluate, io, simulate
from spherejax._engine import fused

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_kernel_contract import default_calibration, fused_switch  # noqa: E402
from harness import machine_info, time_interleaved, write_record  # noqa: E402
from reference import SATURATION, make_inputs, reference_constants, reference_correct  # noqa: E402


def numpy_registration(raw, dark, white, maps, saturation):
    """The registration in NumPy (`band_resampling` is the definition): (u' (H, W, B) float32, the
    registered white signal s', bits (H, W) uint8)."""
    height, width, bands = raw.shape
    raw_f = raw.astype(np.float32)
    signal = white - dark
    unusable = ~(signal > 0) | ~np.isfinite(signal)
    saturated = np.isfinite(raw_f) & (raw_f >= saturation)
    nonfinite = ~np.isfinite(raw_f)
    good = ~(unusable | saturated | nonfinite)
    v = np.where(good, (raw_f - dark) / np.where(unusable, 1, signal), 0).astype(np.float32)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    out, s_out = np.empty_like(v), np.empty_like(v)
    bits = np.zeros((height, width), np.uint8)
    for b in range(bands):
        m = maps[b].astype(np.float32)
        xs, ys = m[0, 0] * x + m[0, 1] * y + m[0, 2], m[1, 0] * x + m[1, 1] * y + m[1, 2]
        tol = band_resampling.COVERAGE_TOLERANCE_PX
        covered = (xs >= -tol) & (xs <= width - 1 + tol) & (ys >= -tol) & (ys <= height - 1 + tol)
        xs, ys = np.clip(xs, 0, width - 1), np.clip(ys, 0, height - 1)
        x0 = np.minimum(np.floor(xs), width - 2).astype(int)
        y0 = np.minimum(np.floor(ys), height - 2).astype(int)
        fx, fy = xs - x0, ys - y0
        taps = [(y0, x0, (1 - fy) * (1 - fx)), (y0, x0 + 1, (1 - fy) * fx), (y0 + 1, x0, fy * (1 - fx)),
                (y0 + 1, x0 + 1, fy * fx)]
        value = sum(w * v[r, c, b] for r, c, w in taps)
        white_value = sum(w * np.where(unusable, 0, signal)[r, c, b] for r, c, w in taps)
        touched = {name: np.zeros((height, width), bool) for name in ("sat", "nonfinite", "white")}
        for r, c, w in taps:
            touched["sat"] |= saturated[r, c, b] & (w > 0)
            touched["nonfinite"] |= nonfinite[r, c, b] & (w > 0)
            touched["white"] |= unusable[r, c, b] & (w > 0)
        bits |= np.where(touched["sat"], 1, 0).astype(np.uint8) | np.where(touched["nonfinite"], 2, 0).astype(np.uint8)
        bits |= np.where(touched["white"], 4, 0).astype(np.uint8) | np.where(~covered, 32, 0).astype(np.uint8)
        out[..., b] = value
        s_out[..., b] = np.where(covered & ~touched["white"], white_value, 1)
    frames = np.where((bits == 0)[..., None], out, -1) * s_out
    return frames.astype(np.float32), s_out.astype(np.float32), bits


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
        frames, signal, _ = numpy_registration(raw, inputs["dark"], inputs["white"], maps, SATURATION)
        return reference_correct(frames, np.zeros_like(signal), signal, inputs["patch"], np.asarray(made.coeffs),
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
