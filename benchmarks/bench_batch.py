"""A batch of images: `correct` on a stack and under `jax.vmap`, per pixel against single images.

What it measures
    Milliseconds per megapixel of four ways to correct N frames of one calibration, each as a
    user writes it, with no set-up call (`spherejax.keep_freed_memory` is not called):

    - "single images": `for raw in frames: result = sj.correct(raw, calibration)`, the plain loop;
    - "stack": `sj.correct(stack, calibration)` on the (N, H, W, 16) array, one p per image;
    - "vmap": `jax.vmap(lambda r: sj.correct(r, calibration).lab)(stack)`;
    - "jit(vmap)": the same function under `jax.jit`.

    The frames are NumPy arrays, as read from files. Before timing, every way is checked to give
    the single images' Lab bit for bit (and the stack their reflectance and quality too; under
    `jax.jit`, to float32 rounding).

Against what
    The numpy + colour-science reference (reference.py) on one frame, timed in the same
    run (its ms/MP is the same per pixel whatever the batch), and the single-image loop: the
    target is that a batch costs per pixel what single images cost.

Run:
    python benchmarks/bench_batch.py [--size 512] [--images 8] [--repeats 7] [--json PATH]
"""

from __future__ import annotations

import argparse
import datetime
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import harness  # noqa: E402
import reference  # noqa: E402  (sets the colour-science warning filter first)
import jax  # noqa: E402

import spherejax  # noqa: E402


def frames_of(inputs: dict, images: int, seed: int = 1) -> np.ndarray:
    """(images, H, W, 16) uint16: the benchmark's frame with a different exposure of the sample
    in each image (the white patch untouched), so that p and the outputs differ per image."""
    raw = inputs["raw"].astype(np.float32)
    rng = np.random.default_rng(seed)
    scale = rng.uniform(0.8, 1.1, images).astype(np.float32)
    stack = np.rint(np.clip(raw[None] * scale[:, None, None, None], 0, 16383)).astype(np.uint16)
    stack[:, inputs["patch"]] = inputs["raw"][inputs["patch"]]
    return stack


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=512, help="image height = width in pixels")
    parser.add_argument("--images", type=int, default=8, help="frames in the batch")
    parser.add_argument("--repeats", type=int, default=7, help="timed runs per way")
    parser.add_argument("--json", metavar="PATH", help="also write the results here")
    args = parser.parse_args(argv)
    if args.size < reference.PATCH_SIZE + 8:
        parser.error(f"--size must be at least {reference.PATCH_SIZE + 8} to hold the white patch")
    if args.images < 1 or args.repeats < 1:
        parser.error("--images and --repeats must be at least 1")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    info = harness.machine_info()
    info["fused_kernel"] = spherejax._engine.fused.enabled()
    wiener, wiener_offset = reference.wiener_estimator()
    coeffs = reference.stage2_coeffs()
    inputs = reference.make_inputs(args.size)
    calibration = reference.make_calibration(inputs, coeffs, wiener, wiener_offset)
    xyz_weights, whitepoint_xy = reference.reference_constants()
    stack = frames_of(inputs, args.images)
    frames = list(stack)

    def single_images():
        result = None
        for raw in frames:
            result = spherejax.correct(raw, calibration)
        return jax.block_until_ready(result)

    def whole_stack():
        return jax.block_until_ready(spherejax.correct(stack, calibration))

    def lab_of(r):
        return spherejax.correct(r, calibration).lab

    vmapped = jax.vmap(lab_of)
    jitted = jax.jit(vmapped)

    def under_vmap():
        return jax.block_until_ready(vmapped(stack))

    def under_jit_vmap():
        return jax.block_until_ready(jitted(stack))

    def numpy_reference():
        return reference.reference_correct(
            frames[0], inputs["dark"], inputs["white"], inputs["patch"], coeffs, wiener, xyz_weights,
            whitepoint_xy, wiener_offset,
        )

    singles = [spherejax.correct(raw, calibration) for raw in frames]
    want_lab = np.stack([np.asarray(r.lab) for r in singles])
    batch = whole_stack()
    for name in ("reflectance", "lab", "quality"):
        want = np.stack([np.asarray(getattr(r, name)) for r in singles])
        if not np.array_equal(np.asarray(getattr(batch, name)), want, equal_nan=True):
            raise SystemExit(f"stack: {name} differs from the single images'")
    if not np.array_equal(np.asarray(under_vmap()), want_lab, equal_nan=True):
        raise SystemExit("vmap: Lab differs from the single images'")
    # Under an outer jit the calibration the function closes over is a constant, and XLA folds
    # the (16, 31) @ (31, 3) product of the Wiener matrix and the XYZ weights at compile time
    # with its own evaluator: the same numbers up to float32 rounding, not the same bits.
    jitted_lab = np.asarray(under_jit_vmap())
    if not (np.array_equal(np.isnan(jitted_lab), np.isnan(want_lab))
            and np.nanmax(np.abs(jitted_lab - want_lab)) < 1e-3):
        raise SystemExit("jit(vmap): Lab differs from the single images' by more than rounding")
    del singles, batch

    ways = {"single images": single_images, "stack": whole_stack, "vmap": under_vmap,
            "jit(vmap)": under_jit_vmap, "reference (one image)": numpy_reference}
    with harness.OtherProcessesLoad() as other_load:
        timings = harness.time_interleaved(ways, args.repeats)
    megapixels = args.size * args.size / 1e6
    per_mp = {}
    for name, t in timings.items():
        count = 1 if name.startswith("reference") else args.images
        per_mp[name] = 1e3 * t["median_s"] / (count * megapixels)
    print(f"\n{args.images} frames of {args.size} x {args.size} x 16 uint16, median of {args.repeats}, no set-up")
    print(f"machine: {info['cpu_model']}, {info['nproc']} CPUs, jax {info['jax']}, fused kernel "
          f"{'on' if info['fused_kernel'] else 'off'}, other load {100 * (other_load.fraction or 0):.1f} %\n")
    print(f"{'':24s} {'ms/MP':>8s} {'vs single':>10s} {'vs reference':>13s}")
    for name, value in per_mp.items():
        print(f"{name:24s} {value:8.1f} {value / per_mp['single images']:9.2f}x "
              f"{per_mp['reference (one image)'] / value:12.1f}x")
    if args.json:
        harness.write_record(args.json, {
            "benchmark": "bench_batch",
            "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "size": args.size, "images": args.images, "repeats": args.repeats,
            "ms_per_megapixel": per_mp, "timings": timings, "other_load": other_load.fraction,
            "machine": info, "argv": sys.argv,
        })
    return 0


if __name__ == "__main__":
    sys.exit(main())
