"""`spherejax.correct` on a GPU: agreement with the numpy + colour-science reference, then timings
against the GPU's memory (HBM) floor and the host-device link.

What it measures
    On the synthetic cubes of reference.py (`make_inputs`, (size, size, 16) uint16, the paper's
    Table 2 Stage II, the affine Wiener estimator fitted on every reflectance spherejax ships):

    1. agreement, at the smallest of --sizes: `spherejax.correct` on the GPU against the numpy +
       colour-science reference on the CPU (reference.compare: reflectance within 1e-4, Lab
       within 1e-2, identical quality masks, as bench_correct.py). Nothing is timed unless they
       agree; the script exits 1 if they do not;
    2. per size in --sizes (default 1024 4096), `correct` two ways:
       "numpy in/out": a NumPy frame in and `np.asarray` of reflectance, Lab and quality out,
       what a user gets who reads frames with NumPy (the upload and downloads included);
       "on device": the frame already on the GPU (`jax.device_put` once) and the outputs left
       there (`jax.block_until_ready`), the GPU's own work; where the plan runs the GPU kernel
       (`spherejax._engine.gpu_kernel`), also "on device, jax.numpy": a plan of the same frames
       that runs the jax.numpy path instead, timed back to back with the others and checked
       against the default's outputs first (quality identical, values to float32 rounding);
       and "on device, streamed": STREAMED_CALLS device-resident calls queued and waited for
       once at the end (`streamed`), reported a call: "on device" waits for every call, so the
       host's work for a call adds to the GPU's, where a loop that leaves its outputs on the
       device overlaps them; and at the largest size, `correct` on the device with a kernel-
       estimator calibration (a residual of --kernel-points inducing points, default 64, on the
       frame's responses: bench_gpu_kernel.residual_for) against its affine twin, back to back,
       as a ratio (target on a GPU: at most 2x at 4096^2), naming each plan's per-pixel step;
    3. a stack of --stack (default 8) frames of --stack-size (default 1024) in one `correct`
       call, both ways, and `jax.jit(jax.vmap(lambda r: correct(r, calibration)))` over it on
       the device, each first checked against the frames corrected one by one;
    4. `jax.value_and_grad` of the mean ΔE00 (CIEDE2000, over the valid pixels) of one such frame
       with respect to the Stage II coefficients (16, 4), jitted, next to the same loss without
       the gradient; the gradient must be finite and not all zero (else exit 1). The target Lab is
       the same frame corrected with Stage I only (`spherejax.identity_coeffs`), so the loss is
       how far Stage II moves the colours;
    5. host -> device (`jax.device_put` of a NumPy buffer) and device -> host (`np.asarray` of a
       fresh device array) copy speeds, GB/s one way, for a --copy-mib (default 256) buffer in
       pageable NumPy memory, as a user's frames are; and a device -> device copy (a jitted
       x * 2), counted read + written as STREAM and harness.copy_bandwidth do.

    Every timing is the median (and minimum) of --repeats (default 5) calls after an untimed
    warm-up, each way's calls back to back (`time_each_back_to_back` says why); the first call (trace,
    compile, run) is reported on its own. The device-resident way's first call comes first, so it
    holds the compilation; the numpy in/out way's then reuses that program.

The floors
    HBM floor: the bytes one call must move through device memory, summed from the actual
    arrays' nbytes (raw in, dark and white in, reflectance, Lab and quality out: 32 + 128 + 124
    + 12 + 1 = 297 B a pixel for one 16-band uint16 frame, docs/design.md "Performance model";
    a stack reads dark and white once), over the HBM bandwidth: --hbm-gbs, else the spec sheet's
    figure for a known card (HBM_GBS), else the measured device copy. "HBM floor %" = floor /
    median time, reported for the device-resident timings; 100 % would be memory speed. The
    gradient gets none (its backward pass has no such simple byte count): it is reported as a
    ratio to its own forward loss. Link floor: the raw frame uploaded and the outputs downloaded
    at the copy speeds measured in the same run, reported for the numpy in/out timings.

Run (a Python with the project and a CUDA build of jax installed):
    python benchmarks/bench_gpu.py [--sizes 1024 4096] [--stack 8] [--stack-size 1024]
        [--repeats 5] [--copy-mib 256] [--hbm-gbs GB/s] [--json PATH] [--allocator reuse|default]

    On the device machine (the session's `run` tool, from the repository root; only what is
    written under $OUT comes back), with a timeout_s of 300 or more:
        python benchmarks/bench_gpu.py --json $OUT/bench_gpu-<card>.json
    Expected, not yet measured when this was written: 2-3 minutes on an H100, most of it
    making the 4096 x 4096 inputs with NumPy (about 45 s on the 2-core CPU machine, scaled from
    1024 x 1024) and compiling; some 10-20 GiB of GPU and host memory at 4096 x 4096. The
    progress lines give the seconds since start, so a run that is cut off shows where.
    Record the printed table and the card, driver and versions in benchmarks/README.md and the
    JSON in benchmarks/results/.

    On a machine without a GPU it stops with exit status 2 unless --allow-cpu is given, which
    runs every step on the CPU as a smoke test of the script (its figures say nothing about a
    GPU):
        python benchmarks/bench_gpu.py --allow-cpu --sizes 128 256 --stack 2 --repeats 2
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import functools
import pathlib
import statistics
import sys
import time
from importlib import metadata

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import harness  # noqa: E402
import reference  # noqa: E402  (sets the colour-science warning filter first)
from bench_batch import frames_of  # noqa: E402
from bench_gpu_kernel import residual_for  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import spherejax  # noqa: E402
from spherejax._engine.plan import Plan, plan_for  # noqa: E402
from spherejax.pixel_constants import PixelConstants  # noqa: E402

#: Spec-sheet HBM bandwidth in GB/s by a substring of `device_kind` (case-insensitive, first
#: match wins). jax names an H100 SXM "NVIDIA H100 80GB HBM3"; other H100 variants (NVL) are
#: left to the measured copy rather than guessed.
HBM_GBS = (
    ("H200", 4800.0),
    ("H100 PCIe", 2000.0),
    ("H100 80GB HBM3", 3350.0),
    ("H100 SXM", 3350.0),
)

#: Jitted device -> device copies timed back to back in one run of `device_copy_bandwidth`, so
#: that the dispatch and the host's wait (tens of microseconds) are spread over several copies
#: of a buffer the GPU copies in a fraction of a millisecond.
COPY_LAUNCHES = 10

_START = time.perf_counter()


def log(message: str) -> None:
    """A progress line with the seconds since start: the device machine's time is limited, so a
    run that is cut off should show how far it got."""
    print(f"[{time.perf_counter() - _START:6.1f} s] {message}", flush=True)


# --------------------------------------------------------------------------------------------
# The device


def device_info() -> dict:
    """What `harness.machine_info` leaves out about the accelerator: jax's first device, its
    kind, platform, compute capability and memory, and the CUDA plugin's versions."""
    device = jax.devices()[0]
    try:
        memory = device.memory_stats() or {}
    except Exception:  # noqa: BLE001 - some backends (CPU) do not implement memory_stats
        memory = {}
    plugins = {}
    for dist in ("jax-cuda12-plugin", "jax-cuda12-pjrt", "jax-cuda13-plugin", "jax-cuda13-pjrt"):
        try:
            plugins[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            pass
    return {
        "default_backend": jax.default_backend(),
        "device_kind": device.device_kind,
        "device_platform": device.platform,
        "device_count": jax.device_count(),
        "compute_capability": getattr(device, "compute_capability", None),
        "device_memory_bytes": memory.get("bytes_limit"),
        "jax_plugins": plugins,
    }


def nominal_hbm_gbs(device_kind: str) -> float | None:
    """The spec sheet's HBM bandwidth (GB/s) of a card named `device_kind`, or None."""
    for pattern, gbs in HBM_GBS:
        if pattern.lower() in device_kind.lower():
            return gbs
    return None


def host_device_copy(nbytes: int, repeats: int) -> dict:
    """Upload and download speeds of an `nbytes` buffer, GB/s one way (bytes / seconds).

    Upload: `jax.device_put` of a NumPy array in ordinary (pageable) memory, as a user's frame
    is. Download: `np.asarray` of a device array made just before, since a jax.Array keeps the
    host copy of its first `np.asarray` and a second one would time nothing. One untimed run of
    each first; median and best of `repeats`.
    """
    host = np.ones(nbytes // 4, np.float32)  # ones, not empty: every page touched before timing
    up, down = [], []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        on_device = jax.block_until_ready(jax.device_put(host))
        up.append(time.perf_counter() - start)
        fresh = jax.block_until_ready(on_device * 2.0)  # a new buffer with no host copy yet
        start = time.perf_counter()
        np.asarray(fresh)
        down.append(time.perf_counter() - start)
        del on_device, fresh
    up, down = up[1:], down[1:]
    return {
        "bytes": host.nbytes,
        "upload_gb_per_s": host.nbytes / statistics.median(up) / 1e9,
        "upload_gb_per_s_best": host.nbytes / min(up) / 1e9,
        "download_gb_per_s": host.nbytes / statistics.median(down) / 1e9,
        "download_gb_per_s_best": host.nbytes / min(down) / 1e9,
        "upload_s": up,
        "download_s": down,
    }


def device_copy_bandwidth(nbytes: int, runs: int = 5) -> float:
    """Best-of-`runs` device copy bandwidth in bytes/s, read + written (as STREAM and
    harness.copy_bandwidth count), of a jitted x * 2 over an `nbytes` float32 array: what the
    HBM floor falls back to for a card not in HBM_GBS. x * 2 rather than a copy so that XLA
    cannot hand back the input's buffer."""
    scale = jax.jit(lambda x: x * 2.0)
    x = jax.block_until_ready(jnp.ones(nbytes // 4, jnp.float32))
    jax.block_until_ready(scale(x))  # compile
    best = float("inf")
    for _ in range(runs):
        start = time.perf_counter()
        for _ in range(COPY_LAUNCHES):
            y = scale(x)
        jax.block_until_ready(y)
        best = min(best, (time.perf_counter() - start) / COPY_LAUNCHES)
        del y
    return 2 * x.nbytes / best


# --------------------------------------------------------------------------------------------
# Rows of the report


def moved_bytes(raw, calibration: spherejax.Calibration, result: spherejax.CorrectionResult) -> int:
    """Bytes one `correct` call must move through device memory at least: raw (..., H, W, B),
    dark and white (H, W, B) read once, reflectance (..., H, W, 31), Lab (..., H, W, 3) and
    quality (..., H, W) written. The patch box and p (a few kB) are left out."""
    return int(
        raw.nbytes + calibration.dark.nbytes + calibration.white.nbytes
        + result.reflectance.nbytes + result.lab.nbytes + result.quality.nbytes
    )


def row(name: str, timing: dict, first_call_s: float, pixels: int, *, hbm_bytes: int | None = None,
        hbm_bytes_per_s: float | None = None, link_s: float | None = None) -> dict:
    """One timed way as the report and the record hold it.

    timing: a `harness.time_back_to_back` entry (seconds); pixels: pixels per call, over all
    frames; hbm_bytes: `moved_bytes` of a device-resident call, None for the others; link_s:
    seconds the upload of raw and the download of the outputs take at the measured copy speeds,
    for a numpy in/out call.
    """
    megapixels = pixels / 1e6
    out = {
        "name": name, "megapixels": megapixels, "first_call_s": first_call_s, **timing,
        "ms_per_mp": 1e3 * timing["median_s"] / megapixels,
    }
    if hbm_bytes is not None:
        floor_s = hbm_bytes / hbm_bytes_per_s
        out.update(hbm_bytes=hbm_bytes, bytes_per_pixel=hbm_bytes / pixels, hbm_floor_s=floor_s,
                   hbm_floor_fraction=floor_s / timing["median_s"])
    if link_s is not None:
        out.update(link_floor_s=link_s, link_floor_fraction=link_s / timing["median_s"])
    return out


def print_rows(rows: list[dict]) -> None:
    header = (f"{'':44}{'MP':>7}{'first s':>9}{'median ms':>11}{'min ms':>9}{'ms/MP':>9}"
              f"{'HBM floor %':>13}{'link floor %':>14}")
    print(header)
    print("-" * len(header))
    for r in rows:
        hbm = f"{100 * r['hbm_floor_fraction']:.1f}" if "hbm_floor_fraction" in r else "-"
        link = f"{100 * r['link_floor_fraction']:.1f}" if "link_floor_fraction" in r else "-"
        print(f"{r['name']:44}{r['megapixels']:7.2f}{r['first_call_s']:9.2f}{1e3 * r['median_s']:11.2f}"
              f"{1e3 * r['min_s']:9.2f}{r['ms_per_mp']:9.2f}{hbm:>13}{link:>14}")
    print("-" * len(header))


# --------------------------------------------------------------------------------------------
# The steps


def time_each_back_to_back(fns: dict, repeats: int) -> dict:
    """`harness.time_back_to_back`: each way's calls one after another, not interleaved.

    Why not interleaved, as the CPU benchmarks time. A device-resident call that follows a NumPy
    in/out call finds the GPU idle for as long as the host copies took (1.6 s at 4096^2 over a
    1.4 GB/s link) and ran at a fraction of its speed: on an H100, 7.7 ms a megapixel at 4096^2
    interleaved against 0.3 back to back (2026-11-26, benchmarks/README.md). What a pipeline that
    keeps its frames on the device sees is the back-to-back figure; the NumPy in/out way is
    bound by the link either way."""
    return harness.time_back_to_back(fns, repeats)


def numpy_in_out(raw: np.ndarray, calibration) -> spherejax.CorrectionResult:
    """`correct` as a NumPy user calls it, with `np.asarray` of every output (which waits for
    the device and copies to the host): a CorrectionResult of NumPy arrays, reflectance
    (..., H, W, 31), Lab (..., H, W, 3), quality (..., H, W) and p (..., 16)."""
    result = spherejax.correct(raw, calibration)
    return spherejax.CorrectionResult(
        np.asarray(result.reflectance), np.asarray(result.lab), np.asarray(result.quality), np.asarray(result.p)
    )


def on_device(raw: jax.Array, calibration):
    """`correct` on a device-resident frame, its outputs left on the device once computed."""
    return jax.block_until_ready(spherejax.correct(raw, calibration))


#: Calls queued by `streamed` before its one wait.
STREAMED_CALLS = 20


def streamed(raw: jax.Array, calibration, calls: int = STREAMED_CALLS):
    """`calls` device-resident `correct` calls queued one after another and waited for once, at
    the end: what a loop that keeps its frames and outputs on the device sees. JAX dispatches
    asynchronously, so the host's work for a call (the checks, the plan lookup, the dispatch)
    overlaps the GPU's work for the calls before it, where "on device" waits for each call and
    so adds the host's work and the wait's wake-up to every call."""
    result = None
    for _ in range(calls):
        result = spherejax.correct(raw, calibration)
    return jax.block_until_ready(result)


def per_call(timing: dict, calls: int) -> dict:
    """A `harness.time_back_to_back` entry of `calls` calls at a time, as seconds a call."""
    return {"median_s": timing["median_s"] / calls, "min_s": timing["min_s"] / calls,
            "all_s": [t / calls for t in timing["all_s"]]}


def jax_numpy_way(raw: jax.Array, calibration, result: spherejax.CorrectionResult):
    """None where `correct`'s plan of raw runs the jax.numpy path already; else a call of a plan
    of the same frames that runs the jax.numpy path (kernel_mode None), what ran on GPUs before
    the GPU kernel, after checking its outputs against `result` (the default plan's): quality
    identical, reflectance within 1e-5 and Lab within 1e-3 (float32 rounding of sums taken in
    another order; raises AssertionError otherwise)."""
    if plan_for(calibration, raw.shape, raw.dtype).kernel_mode is None:
        return None
    plan = Plan(calibration, raw.shape, raw.dtype, kernel_mode=None)
    other = jax.block_until_ready(plan(raw))
    np.testing.assert_array_equal(np.asarray(other.quality), np.asarray(result.quality))
    np.testing.assert_allclose(np.asarray(other.reflectance), np.asarray(result.reflectance), atol=1e-5, rtol=0)
    np.testing.assert_allclose(np.asarray(other.lab), np.asarray(result.lab), atol=1e-3, rtol=0)
    return lambda: jax.block_until_ready(plan(raw))


def link_seconds(raw, outputs_bytes: int, copies: dict) -> float:
    """Seconds to upload `raw` and download `outputs_bytes` at the measured median speeds."""
    return raw.nbytes / (copies["upload_gb_per_s"] * 1e9) + outputs_bytes / (copies["download_gb_per_s"] * 1e9)


def outputs_nbytes(result: spherejax.CorrectionResult) -> int:
    return int(result.reflectance.nbytes + result.lab.nbytes + result.quality.nbytes)


def as_reference(results: list[spherejax.CorrectionResult]) -> dict:
    """Frames corrected one by one, stacked, in the form `reference.compare` takes."""
    return {
        "reflectance": np.stack([np.asarray(r.reflectance) for r in results]),
        "lab": np.stack([np.asarray(r.lab) for r in results]),
        "valid": np.stack([np.asarray(r.valid) for r in results]),
    }


def check_agreement(inputs: dict, calibration, coeffs, wiener, wiener_offset) -> tuple[dict, dict]:
    """`correct` (numpy in/out and device-resident) against the numpy + colour-science reference
    on `inputs`; raises AssertionError (reference.compare) when out of tolerance. Also returns
    the seconds of those two first calls (trace, compile, run), which are the size's first."""
    xyz_weights, whitepoint_xy = reference.reference_constants()
    expected = reference.reference_correct(
        inputs["raw"], inputs["dark"], inputs["white"], inputs["patch"], coeffs, wiener, xyz_weights,
        whitepoint_xy, wiener_offset,
    )
    raw_dev = jax.block_until_ready(jax.device_put(inputs["raw"]))
    first_dev, result = harness.time_first_call(lambda: on_device(raw_dev, calibration))
    first_np, result_np = harness.time_first_call(lambda: numpy_in_out(inputs["raw"], calibration))
    agreement = reference.compare(result_np, expected)
    # The device-resident frame runs the same program; checked too, since it is timed too.
    reference.compare(result, expected)
    return agreement, {"numpy in/out": first_np, "on device": first_dev}


def time_sizes(sizes, inputs_of, calibration_of, copies, hbm_bytes_per_s, repeats, first_calls: dict) -> list[dict]:
    """Rows for one frame of each size, numpy in/out and on device. first_calls: {size: {way:
    seconds}} of first calls made before (the agreement check's), which these then are."""
    rows = []
    for size in sizes:
        inputs, calibration = inputs_of(size), calibration_of(size)
        raw_np = inputs["raw"]
        raw_dev = jax.block_until_ready(jax.device_put(raw_np))
        first_dev, result = harness.time_first_call(lambda: on_device(raw_dev, calibration))  # noqa: B023
        first_np, _ = harness.time_first_call(lambda: numpy_in_out(raw_np, calibration))  # noqa: B023
        first_np = first_calls.get(size, {}).get("numpy in/out", first_np)
        first_dev = first_calls.get(size, {}).get("on device", first_dev)
        hbm_bytes, out_bytes = moved_bytes(raw_dev, calibration, result), outputs_nbytes(result)
        jax_numpy, first_jax_numpy = None, None
        if (way := jax_numpy_way(raw_dev, calibration, result)) is not None:
            first_jax_numpy, _ = harness.time_first_call(way)
            jax_numpy = way
        del result
        ways = {
            "numpy in/out": lambda: numpy_in_out(raw_np, calibration),  # noqa: B023
            "on device": lambda: on_device(raw_dev, calibration),  # noqa: B023
            "on device, streamed": lambda: streamed(raw_dev, calibration),  # noqa: B023
        }
        if jax_numpy is not None:
            ways["on device, jax.numpy"] = jax_numpy
        timings = time_each_back_to_back(ways, repeats)
        timings["on device, streamed"] = per_call(timings["on device, streamed"], STREAMED_CALLS)
        pixels = size * size
        rows.append(row(f"{size}^2 numpy in/out", timings["numpy in/out"], first_np, pixels,
                        link_s=link_seconds(raw_np, out_bytes, copies)))
        rows.append(row(f"{size}^2 on device", timings["on device"], first_dev, pixels,
                        hbm_bytes=hbm_bytes, hbm_bytes_per_s=hbm_bytes_per_s))
        rows.append(row(f"{size}^2 on device, streamed", timings["on device, streamed"], first_dev, pixels,
                        hbm_bytes=hbm_bytes, hbm_bytes_per_s=hbm_bytes_per_s))
        if jax_numpy is not None:
            rows.append(row(f"{size}^2 on device, jax.numpy", timings["on device, jax.numpy"], first_jax_numpy,
                            pixels, hbm_bytes=hbm_bytes, hbm_bytes_per_s=hbm_bytes_per_s))
        kernel = plan_for(calibration, raw_dev.shape, raw_dev.dtype).kernel_mode or "the jax.numpy path"
        del raw_dev
        log(f"timed {size} x {size}; the plan's per-pixel step: {kernel}")
    return rows


def time_kernel_estimator(inputs: dict, calibration, points: int, hbm_bytes_per_s, repeats) -> tuple[list, dict]:
    """Rows for `correct` of a device-resident frame with its affine `calibration` and with its
    kernel-estimator twin (a residual of `points` inducing points, `residual_for`), back to back,
    and their ratio; the twin's plan is first checked against the jax.numpy path (and that timed
    too) where it runs a kernel (`jax_numpy_way`)."""
    raw = jax.block_until_ready(jax.device_put(inputs["raw"]))
    p = spherejax.patch_ratio(raw, calibration)
    residual = residual_for(raw, p, PixelConstants.of(calibration, np.float32), reference.SATURATION, points)
    name, kernel = f"kernel estimator m={points}", dataclasses.replace(calibration, wiener_residual=residual)
    twins, first, ways = {"affine twin": calibration, name: kernel}, {}, {}
    for way, c in twins.items():  # the kernel estimator last: `result` is its outputs
        first[way], result = harness.time_first_call(lambda c=c: on_device(raw, c))
        ways[way] = lambda c=c: on_device(raw, c)
    if (way := jax_numpy_way(raw, kernel, result)) is not None:
        first[f"{name}, jax.numpy"], _ = harness.time_first_call(way)
        ways[f"{name}, jax.numpy"] = way
    hbm_bytes = moved_bytes(raw, calibration, result)
    del result
    timings = time_each_back_to_back(ways, repeats)
    size = raw.shape[0]
    rows = [row(f"{size}^2 on device, {way}", timings[way], first[way], size * size, hbm_bytes=hbm_bytes,
                hbm_bytes_per_s=hbm_bytes_per_s) for way in ways]
    steps = {way: plan_for(c, raw.shape, raw.dtype).kernel_mode or "the jax.numpy path" for way, c in twins.items()}
    check = {"size": size, "inducing_points": points, "per_pixel_step": steps,
             "ratio": timings[name]["median_s"] / timings["affine twin"]["median_s"]}
    log(f"timed the kernel estimator at {size} x {size}: {check['ratio']:.2f}x its affine twin; {steps}")
    return rows, check


def time_stack(inputs: dict, calibration, frames: int, copies, hbm_bytes_per_s, repeats) -> tuple[list[dict], dict]:
    """Rows for a stack of `frames` frames in one call (numpy in/out, on device) and under
    jit(vmap) on the device, after checking both against the frames corrected one by one (the
    reference tolerances; on a GPU the batched programs may round differently)."""
    stack_np = frames_of(inputs, frames)
    stack_dev = jax.block_until_ready(jax.device_put(stack_np))
    singles = as_reference([spherejax.correct(stack_dev[k], calibration) for k in range(frames)])

    def corrected(frames, dark, white):
        """`correct` of each frame (N, H, W, 16) under jax.vmap; dark, white (H, W, 16)."""
        # Dark and white are arguments, not closed over: jax embeds the closed-over arrays of a
        # calibration in the program as constants (16.9 MB of HLO text at 256 x 256, measured
        # with jax 0.12) and XLA constant-folds steps of them at compile time, which at 1024 x
        # 1024 takes minutes. The small leaves stay closed over: a concrete patch keeps p to
        # the patch's box, as `correct` on the stack has it.
        frames_calibration = dataclasses.replace(calibration, dark=dark, white=white)
        return jax.vmap(lambda r: spherejax.correct(r, frames_calibration))(frames)

    jit_vmap = functools.partial(jax.jit(corrected), dark=calibration.dark, white=calibration.white)

    first_stack, stacked = harness.time_first_call(lambda: on_device(stack_dev, calibration))
    first_jv, mapped = harness.time_first_call(lambda: jit_vmap(stack_dev))
    first_np, _ = harness.time_first_call(lambda: numpy_in_out(stack_np, calibration))
    checks = {}
    for name, result in (("stack", stacked), ("jit(vmap)", mapped)):
        try:
            checks[name] = reference.compare(result, singles)
        except AssertionError as error:
            raise AssertionError(f"{name} against the frames one by one: {error}") from None
    hbm_bytes, out_bytes = moved_bytes(stack_dev, calibration, stacked), outputs_nbytes(stacked)
    del stacked, mapped, singles

    timings = time_each_back_to_back({
        "numpy in/out": lambda: numpy_in_out(stack_np, calibration),
        "on device": lambda: on_device(stack_dev, calibration),
        "jit(vmap)": lambda: jax.block_until_ready(jit_vmap(stack_dev)),
    }, repeats)
    size = inputs["raw"].shape[0]
    pixels = frames * size * size
    label = f"stack {frames} x {size}^2"
    rows = [
        row(f"{label} numpy in/out", timings["numpy in/out"], first_np, pixels,
            link_s=link_seconds(stack_np, out_bytes, copies)),
        row(f"{label} on device", timings["on device"], first_stack, pixels,
            hbm_bytes=hbm_bytes, hbm_bytes_per_s=hbm_bytes_per_s),
        row(f"{label} jit(vmap)", timings["jit(vmap)"], first_jv, pixels,
            hbm_bytes=hbm_bytes, hbm_bytes_per_s=hbm_bytes_per_s),
    ]
    log(f"timed the stack of {frames}")
    return rows, checks


def time_gradient(inputs: dict, calibration, repeats) -> tuple[list[dict], dict]:
    """Rows for the mean ΔE00 of one frame and its value_and_grad with respect to the Stage II
    coefficients, both jitted and device-resident; raises AssertionError if the gradient is not
    finite or all zero."""
    raw_dev = jax.block_until_ready(jax.device_put(inputs["raw"]))
    # Stage I only: a target every pixel's Lab is a definite distance from (Stage II moves it),
    # so the loss is not at a kink of ΔE00 (a distance) and its gradient is informative.
    stage1 = dataclasses.replace(calibration, coeffs=spherejax.identity_coeffs(calibration.bands))
    target = jax.block_until_ready(spherejax.correct(raw_dev, stage1).lab)  # (H, W, 3)

    def mean_delta_e(coeffs, raw, target, dark, white):
        """Mean ΔE00 over the valid pixels, a float32 scalar; coeffs (16, 4), raw, dark and
        white (H, W, 16), target (H, W, 3). Dark and white are arguments for the reason
        `time_stack` gives."""
        result = spherejax.correct(raw, dataclasses.replace(calibration, coeffs=coeffs, dark=dark, white=white))
        delta_e = spherejax.delta_e_2000(result.lab, target)  # (H, W), NaN on bad pixels
        # where, not nanmean: bad pixels must get a zero cotangent (the pipeline's safe-where).
        return jnp.sum(jnp.where(result.valid, delta_e, 0.0)) / jnp.sum(result.valid)

    frames = {"dark": calibration.dark, "white": calibration.white}
    loss = functools.partial(jax.jit(mean_delta_e), **frames)
    value_and_grad = functools.partial(jax.jit(jax.value_and_grad(mean_delta_e)), **frames)
    coeffs = calibration.coeffs
    first_loss, _ = harness.time_first_call(lambda: loss(coeffs, raw_dev, target))
    first_grad, (value, gradient) = harness.time_first_call(lambda: value_and_grad(coeffs, raw_dev, target))
    gradient = np.asarray(gradient)
    check = {
        "mean_delta_e00": float(value),
        "gradient_shape": list(gradient.shape),
        "gradient_max_abs": float(np.max(np.abs(gradient))),
        "gradient_finite": bool(np.all(np.isfinite(gradient))),
    }
    if not check["gradient_finite"]:
        raise AssertionError(f"d(mean ΔE00)/d(coeffs) is not finite: {int((~np.isfinite(gradient)).sum())} entries")
    if not check["gradient_max_abs"] > 0:
        raise AssertionError("d(mean ΔE00)/d(coeffs) is zero everywhere")

    timings = harness.time_interleaved({
        "loss": lambda: jax.block_until_ready(loss(coeffs, raw_dev, target)),
        "value_and_grad": lambda: jax.block_until_ready(value_and_grad(coeffs, raw_dev, target)),
    }, repeats)
    size = inputs["raw"].shape[0]
    pixels = size * size
    rows = [
        row(f"{size}^2 mean dE00 (loss only)", timings["loss"], first_loss, pixels),
        row(f"{size}^2 mean dE00 value_and_grad", timings["value_and_grad"], first_grad, pixels),
    ]
    check["grad_over_loss"] = timings["value_and_grad"]["median_s"] / timings["loss"]["median_s"]
    log("timed the gradient")
    return rows, check


# --------------------------------------------------------------------------------------------


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 4096],
                        help="frame heights = widths to time one frame at; agreement is checked at the smallest")
    parser.add_argument("--stack", type=int, default=8, help="frames in the stack")
    parser.add_argument("--stack-size", type=int, default=None,
                        help="height = width of the stack's frames and of the gradient's frame "
                             "(default 1024, or the largest of --sizes if that is smaller)")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per way")
    parser.add_argument("--copy-mib", type=int, default=256, help="buffer of the copy-speed tests, MiB")
    parser.add_argument("--kernel-points", type=int, default=64, help="inducing points of the kernel estimator (0: skip)")
    parser.add_argument("--hbm-gbs", type=float, default=None,
                        help="HBM bandwidth for the floor, GB/s (default: the card's spec sheet, "
                             "else the measured device copy)")
    parser.add_argument("--allow-cpu", action="store_true",
                        help="run on the CPU when there is no GPU (a smoke test of the script)")
    parser.add_argument("--json", metavar="PATH", help="also write the results here")
    harness.add_allocator_argument(parser)
    args = parser.parse_args(argv)
    smallest = reference.PATCH_SIZE + 8
    if args.stack_size is None:
        args.stack_size = min(1024, max(args.sizes))
    if min(args.sizes) < smallest or args.stack_size < smallest:
        parser.error(f"--sizes and --stack-size must be at least {smallest} to hold the white patch")
    if args.stack < 1 or args.repeats < 1 or args.copy_mib < 1:
        parser.error("--stack, --repeats and --copy-mib must be at least 1")
    if args.hbm_gbs is not None and not args.hbm_gbs > 0:
        parser.error("--hbm-gbs must be > 0")
    args.sizes = sorted(set(args.sizes))
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    allocator = harness.apply_allocator_argument(args)  # before any JAX work, as harness asks
    if jax.default_backend() == "cpu" and not args.allow_cpu:
        print("bench_gpu.py: no GPU here (jax's default backend is cpu); run it on a GPU machine, "
              "or pass --allow-cpu with small --sizes to smoke-test it", file=sys.stderr)
        return 2
    info = {**harness.machine_info(), **device_info(), "allocator": allocator}
    print(f"device: {info['device_kind']} ({info['device_platform']}, {info['device_count']} device(s)), "
          f"jax {info['jax']}, jaxlib {info['jaxlib']}, {info['nproc']} CPUs ({info['cpu_model']}), "
          f"python {info['python']}", flush=True)

    copy_bytes = args.copy_mib * 2**20
    copies = host_device_copy(copy_bytes, args.repeats)
    device_copy = device_copy_bandwidth(copy_bytes)
    nominal = nominal_hbm_gbs(info["device_kind"])
    if args.hbm_gbs is not None:
        hbm_gbs, hbm_source = args.hbm_gbs, "--hbm-gbs"
    elif nominal is not None:
        hbm_gbs, hbm_source = nominal, f"spec sheet of {info['device_kind']}"
    else:
        hbm_gbs, hbm_source = device_copy / 1e9, "measured device copy (x * 2, read + written)"
    hbm_bytes_per_s = hbm_gbs * 1e9
    log(f"copy speeds measured; HBM floor at {hbm_gbs:.0f} GB/s ({hbm_source})")

    coeffs = reference.stage2_coeffs()
    wiener, wiener_offset = reference.wiener_estimator()
    log("Wiener estimator fitted")

    # Inputs of one size at a time (4096^2 takes 2.5 GB of NumPy and as much on the device),
    # except the stack's, which is kept for the stack and the gradient.
    kept: dict = {}

    def inputs_of(size: int) -> dict:
        if size not in kept:
            for old in [s for s in kept if s != args.stack_size]:
                del kept[old]
            kept[size] = reference.make_inputs(size)
            log(f"inputs {size} x {size} made")
        return kept[size]

    def calibration_of(size: int) -> spherejax.Calibration:
        return reference.make_calibration(inputs_of(size), coeffs, wiener, wiener_offset)

    record: dict = {}
    try:
        smallest = args.sizes[0]
        agreement, first_calls = check_agreement(
            inputs_of(smallest), calibration_of(smallest), coeffs, wiener, wiener_offset
        )
        print(f"agreement with numpy + colour-science at {smallest} x {smallest} over "
              f"{agreement['valid_pixels']} valid pixels ({agreement['bad_pixels']} bad in both): reflectance max "
              f"|diff| {agreement['reflectance_max_abs_diff']:.2e} (tolerance {reference.REFLECTANCE_TOLERANCE:g}), "
              f"Lab max |diff| {agreement['lab_max_abs_diff']:.2e} (tolerance {reference.LAB_TOLERANCE:g})", flush=True)
        record["agreement"] = {"size": smallest, **agreement}

        with harness.OtherProcessesLoad() as other_load:
            rows = time_sizes(
                args.sizes, inputs_of, calibration_of, copies, hbm_bytes_per_s, args.repeats, {smallest: first_calls}
            )
            kernel_check = None
            if args.kernel_points > 0:
                kernel_rows, kernel_check = time_kernel_estimator(
                    inputs_of(args.sizes[-1]), calibration_of(args.sizes[-1]), args.kernel_points, hbm_bytes_per_s,
                    args.repeats)
                rows += kernel_rows
            stack_calibration = calibration_of(args.stack_size)
            stack_rows, stack_checks = time_stack(
                inputs_of(args.stack_size), stack_calibration, args.stack, copies, hbm_bytes_per_s, args.repeats
            )
            grad_rows, grad_check = time_gradient(inputs_of(args.stack_size), stack_calibration, args.repeats)
    except AssertionError as error:
        print(f"check FAILED: {error}", file=sys.stderr)
        return 1

    rows += stack_rows + grad_rows
    print(f"\nspherejax.correct on {info['device_kind']}, median of {args.repeats} after a warm-up; "
          f"HBM floor at {hbm_gbs:.0f} GB/s ({hbm_source})\n")
    print_rows(rows)
    print(f"stack and jit(vmap) against the frames one by one: Lab max |diff| "
          f"{stack_checks['stack']['lab_max_abs_diff']:.2e} and {stack_checks['jit(vmap)']['lab_max_abs_diff']:.2e}")
    print(f"mean ΔE00 (Table 2 Stage II against Stage I only) {grad_check['mean_delta_e00']:.3f}; gradient "
          f"{tuple(grad_check['gradient_shape'])} finite, max |d/dc| {grad_check['gradient_max_abs']:.3g}; "
          f"value_and_grad / loss {grad_check['grad_over_loss']:.2f}x")
    if kernel_check is not None:
        print(f"kernel estimator (m = {kernel_check['inducing_points']}) against its affine twin at "
              f"{kernel_check['size']}^2 on the device: {kernel_check['ratio']:.2f}x (target <= 2x); per-pixel step "
              f"{kernel_check['per_pixel_step']}")
    bytes_per_pixel = next(r["bytes_per_pixel"] for r in rows if "bytes_per_pixel" in r)
    print(f"bytes moved per pixel of one frame: {bytes_per_pixel:.0f} (from the arrays' nbytes; "
          f"reference.BYTES_PER_PIXEL = {reference.BYTES_PER_PIXEL})")
    print(f"host -> device {copies['upload_gb_per_s']:.2f} GB/s (best {copies['upload_gb_per_s_best']:.2f}), "
          f"device -> host {copies['download_gb_per_s']:.2f} GB/s (best {copies['download_gb_per_s_best']:.2f}), "
          f"{args.copy_mib} MiB pageable NumPy buffer")
    print(f"device copy {device_copy / 1e9:.0f} GB/s (read + written), "
          f"{100 * device_copy / hbm_bytes_per_s:.0f} % of the floor's {hbm_gbs:.0f} GB/s")
    if other_load.fraction is not None:
        print(f"CPU used by other processes: {100 * other_load.fraction:.1f} % of the machine during timing")
    if info["default_backend"] == "cpu":
        print("note: run on the CPU (--allow-cpu): a smoke test of the script, not a GPU figure")

    if args.json:
        record.update({
            "benchmark": "bench_gpu",
            "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "sizes": args.sizes, "stack": args.stack, "stack_size": args.stack_size, "repeats": args.repeats,
            "copy_mib": args.copy_mib, "bands": reference.BANDS,
            "hbm_gb_per_s": hbm_gbs, "hbm_source": hbm_source,
            "device_copy_gb_per_s": device_copy / 1e9, "host_device_copy": copies,
            "rows": rows, "stack_checks": stack_checks, "gradient": grad_check, "kernel_estimator": kernel_check,
            "other_processes_cpu_fraction": other_load.fraction,
            "total_s": time.perf_counter() - _START,
            "machine": info, "argv": sys.argv,
        })
        harness.write_record(args.json, record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
