"""What `spherejax.correct` costs a call beyond its compiled program: the host-side work of the
checks and the plan lookup, measured on frames so small that the program itself costs little.

What it measures
    On one (16, 16, 16) uint16 frame already on the device (a jax.Array), with the jax.numpy path
    (SPHEREJAX_FUSED=0, the route GPUs take when the GPU kernel does not apply) and NumPy frames
    never involved: the median time a call of

    - `spherejax.correct(raw, calibration)`: what a user calls;
    - `plan(raw)`: the calibration's plan, looked up once (`spherejax.plan`), called directly;
    - `steps.image_step(...)`: the jitted program alone, the floor of both.

    each over --calls calls after a warm-up, `jax.block_until_ready` on the last result only (the
    calls queue as a pipeline of frames would). "correct - plan" is the price of the checks and
    the lookup; on a GPU, at a megapixel, a call of the program takes about 0.3-1 ms, so tens of
    microseconds matter there (benchmarks/README.md, the GPU section).

Run:
    python benchmarks/bench_call_overhead.py [--calls 3000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ["SPHEREJAX_FUSED"] = "0"  # the jax.numpy path: no NumPy route, no custom call

import jax  # noqa: E402
import numpy as np  # noqa: E402

import spherejax  # noqa: E402
from harness import machine_info  # noqa: E402
from spherejax._engine import steps  # noqa: E402


def calibration_and_frame(size: int = 16):
    rng = np.random.default_rng(0)
    shape = (size, size, 16)
    patch = np.zeros(shape[:2], bool)
    patch[2:6, 3:9] = True
    calibration = spherejax.Calibration(
        dark=rng.uniform(90, 110, shape).astype(np.float32), white=rng.uniform(9000, 11000, shape).astype(np.float32),
        patch=patch, coeffs=np.tile(np.asarray([0.01, 0.97, 0.02, -0.01], np.float32), (16, 1)),
        wiener=(rng.uniform(0, 1, (31, 16)) / 16).astype(np.float32), saturation=16383.0,
    )
    raw = jax.device_put(rng.integers(0, 16000, shape).astype(np.uint16))
    return calibration, raw


def per_call_us(call, calls: int, repeats: int) -> float:
    """Median over `repeats` runs of `calls` calls, µs a call."""
    for _ in range(50):
        jax.block_until_ready(call())
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            result = call()
        jax.block_until_ready(result)
        runs.append((time.perf_counter() - start) / calls * 1e6)
    return statistics.median(runs)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    calibration, raw = calibration_and_frame()
    plan = spherejax.plan(calibration, raw.shape, dtype=raw.dtype)
    statics = {"box_shape": plan.box_shape, "saturation": plan.saturation, "kernel_mode": plan.kernel_mode}
    ways = {
        "correct(raw, calibration)": lambda: spherejax.correct(raw, calibration),
        "plan(raw)": lambda: plan(raw),
        "steps.image_step (the program)": lambda: steps.image_step(
            raw, plan.constants, plan.patch, plan.box_origin, intermediates=False, no_flat_field=plan.no_flat_field,
            **statics),
    }
    info = machine_info()
    print(f"{info['cpu_model']}, {info['nproc']} CPUs, jax {jax.__version__}, backend {jax.default_backend()}; "
          f"(16, 16, 16) uint16 on the device, {args.calls} calls x {args.repeats}")
    times = {name: per_call_us(call, args.calls, args.repeats) for name, call in ways.items()}
    for name, us in times.items():
        print(f"  {name:32} {us:8.1f} us a call")
    print(f"  correct - plan                   {times['correct(raw, calibration)'] - times['plan(raw)']:8.1f} us")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
