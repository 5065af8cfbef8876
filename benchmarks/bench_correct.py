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
    (SPHEREJAX_FUSED=0, `spherejax.fused`): the jax.numpy path the kernel replaced, which is
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
longer they wait: benchmarks/README.md, seventh speed session). Both are reported, with their
ratios to the reference timed the same way.

Run:
    python benchmarks/bench_correct.py [--size 1024] [--repeats 7] [--allocator reuse|default]
        [--json PATH]

Allocator: by default the script first calls `spherejax.allocator.keep_freed_memory()`, as the
command line does, so neither implementation pays the kernel for fresh zeroed pages on every
call; `--allocator default` leaves glibc as it comes (that module's docstring says why it matters).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import datetime
import json
import os
import platform
import statistics
import sys
import time
import warnings
from importlib import metadata

import numpy as np

# colour-science warns at import that matplotlib is missing; plotting is not used here.
warnings.filterwarnings("ignore", message=".*Matplotlib.* related API features are not available")

import colour  # noqa: E402
import jax  # noqa: E402

import spherejax  # noqa: E402
from spherejax import spectra  # noqa: E402
from spherejax import fused  # noqa: E402
from spherejax.allocator import keep_freed_memory  # noqa: E402
from spherejax.polynomial import PAPER_TABLE_2  # noqa: E402

BANDS = 16
SATURATION = 16383.0  # 14-bit ADC full scale
PATCH_SIZE = 35  # the paper's 35 x 35 pixel averaging region
SEED = 20190816  # fixed so every run times the same cube

# Bytes the path must move per pixel (docs/design.md, "Performance model"): read raw uint16, dark and
# white float32; write reflectance (31) and Lab (3) float32 and the uint8 quality mask.
BYTES_PER_PIXEL = BANDS * 2 + BANDS * 4 * 2 + (31 + 3) * 4 + 1  # = 297

REFLECTANCE_TOLERANCE = 1e-4
LAB_TOLERANCE = 1e-2


# --------------------------------------------------------------------------------------------
# Inputs


def stage2_coeffs() -> np.ndarray:
    """The paper's Table 2 as a (16, 4) float32 array, columns c1, c2, c3, c4."""
    return np.asarray(PAPER_TABLE_2, dtype=np.float32)


def camera_sensitivity() -> np.ndarray:
    """(16, 31): Gaussian filters, centres 400..700 step 20, FWHM 10 nm, on 400..700 step 10.

    Each row sums to 1, so a perfect diffuser (reflectance 1) gives response 1 in every band:
    the units of flat-fielded responses, which is what the Wiener matrix is applied to.
    """
    sigma = 10.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    centres = spherejax.BAND_CENTRES_NM[:, None].astype(np.float64)
    wavelengths = spherejax.WAVELENGTHS_NM[None, :].astype(np.float64)
    filters = np.exp(-0.5 * ((wavelengths - centres) / sigma) ** 2)
    return filters / filters.sum(axis=1, keepdims=True)


def wiener_estimator() -> tuple[np.ndarray, np.ndarray]:
    """(W (31, 16), r0 (31,)) float32: the affine Wiener estimator r = W v + r0 trained on every
    reflectance spherejax ships. A plain matrix (what `fit_wiener` returned before the
    estimator became affine) is taken with a zero offset."""
    reflectances = spectra.all_reflectances()
    responses = reflectances @ camera_sensitivity().T
    estimator = spherejax.fit_wiener(responses, reflectances)
    matrix = getattr(estimator, "matrix", estimator)
    offset = getattr(estimator, "offset", np.zeros(matrix.shape[0]))
    return np.asarray(matrix, dtype=np.float32), np.asarray(offset, dtype=np.float32)


def wiener_matrix() -> np.ndarray:
    """(31, 16) float32: the matrix W of `wiener_estimator` (its offset left out)."""
    return wiener_estimator()[0]


def vignetting(size: int) -> np.ndarray:
    """(size, size, 1) smooth cos^4-like falloff, 1 at the centre and about 0.7 in the corners."""
    axis = np.linspace(-1.0, 1.0, size, dtype=np.float32)
    radius2 = axis[:, None] ** 2 + axis[None, :] ** 2
    return (1.0 / (1.0 + 0.2 * radius2) ** 2)[..., None]


def sample_reflectance(size: int, rng: np.random.Generator) -> np.ndarray:
    """(size, size, 16) in 0.05..0.95: 32 x 32 px tiles of measured spectra at the band centres.

    Real spectra rather than noise so the Wiener step sees the band correlations it was trained
    for; tiles so the image has edges like a patterned background.
    """
    at_bands = spectra.all_reflectances()[:, ::2]  # 31 samples -> the 16 band centres
    tiles = -(-size // 32)
    choice = rng.integers(0, at_bands.shape[0], size=(tiles, tiles))
    tiled = np.repeat(np.repeat(at_bands[choice], 32, axis=0), 32, axis=1)[:size, :size]
    return np.clip(tiled, 0.05, 0.95).astype(np.float32)


def patch_mask(size: int) -> np.ndarray:
    """(size, size) bool: the 35 x 35 reference white patch, 8 px in from the top-left corner."""
    mask = np.zeros((size, size), dtype=bool)
    mask[8 : 8 + PATCH_SIZE, 8 : 8 + PATCH_SIZE] = True
    return mask


def make_inputs(size: int, seed: int = SEED) -> dict:
    """Synthetic but plausible frames: dark, white standard, one raw sample cube, the patch mask.

    The sample darkens the sphere by q = 0.97 (Eq. 9-15), so the white patch reads 0.97 of the
    white standard and p should come out near 1 / 0.97. A few pixels are driven to saturation so
    the quality-mask path is exercised and compared too.
    """
    rng = np.random.default_rng(seed)
    shape = (size, size, BANDS)
    dark = (100.0 + rng.normal(0.0, 3.0, shape)).astype(np.float32)
    white_signal = 12000.0 * vignetting(size) * rng.uniform(0.9, 1.1, BANDS).astype(np.float32)
    white = (dark + white_signal + rng.normal(0.0, 30.0, shape)).astype(np.float32)

    patch = patch_mask(size)
    reflectance = sample_reflectance(size, rng)
    reflectance[patch] = 1.0  # the patch is the same material as the white standard
    q_s = 0.97
    raw = dark + q_s * white_signal * reflectance + rng.normal(0.0, 20.0, shape)
    hot = rng.random((size, size)) < 1e-4
    raw[hot, rng.integers(0, BANDS)] = SATURATION
    raw = np.clip(np.rint(raw), 0, SATURATION).astype(np.uint16)
    return {"raw": raw, "dark": dark, "white": white, "patch": patch}


def make_calibration(inputs: dict, coeffs: np.ndarray, wiener: np.ndarray, wiener_offset=None) -> spherejax.Calibration:
    """The calibration of `make_inputs`; wiener_offset r0 (31,), None = zeros."""
    return spherejax.Calibration(
        dark=inputs["dark"],
        white=inputs["white"],
        patch=inputs["patch"],
        coeffs=coeffs,
        wiener=wiener,
        illuminant="D65",
        saturation=SATURATION,
        wiener_offset=np.zeros(31, np.float32) if wiener_offset is None else wiener_offset,
    )


# --------------------------------------------------------------------------------------------
# The reference: numpy + colour-science


def reference_correct(raw, dark, white, patch, coeffs, wiener, xyz_weights, whitepoint_xy, wiener_offset=None) -> dict:
    """The `correct` path in numpy, float32 throughout except inside colour-science.

    wiener_offset: the estimator's offset r0 (31,), None = zeros.

    Returns a dict with reflectance (H, W, 31), lab (H, W, 3) and valid (H, W) bool. Bad pixels
    (saturated, non-finite, white <= dark) and every pixel of an image whose patch ratio is not
    finite are NaN, as in spherejax.
    """
    raw_f = raw.astype(np.float32)
    saturated = np.any(raw_f >= SATURATION, axis=-1)
    nonfinite = np.any(~np.isfinite(raw_f), axis=-1)
    white_signal = white - dark
    no_flat_field = np.any(~(white_signal > 0), axis=-1)
    valid = ~(saturated | nonfinite | no_flat_field)

    # Eq. 10. Where white <= dark the division is meaningless; those pixels are NaN below anyway.
    sample_signal = raw_f - dark
    with np.errstate(divide="ignore", invalid="ignore"):
        v = sample_signal / white_signal

    # Eq. 14-15 over the usable pixels of the patch only, as spherejax does.
    in_patch = patch & valid
    p = white_signal[in_patch].sum(axis=0) / sample_signal[in_patch].sum(axis=0)  # (16,)
    if not np.all(np.isfinite(p)):
        valid = np.zeros_like(valid)

    # Eq. 23, coefficients (B, 4) ordered c1..c4.
    c_1, c_2, c_3, c_4 = coeffs.T
    v_tilde = (c_1 * p + c_2) * v + c_3 * p + c_4
    v_tilde[~valid] = np.nan

    reflectance = v_tilde @ wiener.T  # (H, W, 31)
    if wiener_offset is not None:
        reflectance += wiener_offset  # the affine estimate W v + r0; NaN rows stay NaN
    xyz = reflectance @ xyz_weights  # ASTM E308, Y = 100 for the perfect diffuser
    # colour-science works in float64 internally (its default float dtype); that is how a user
    # would call it, so it is left that way and only the result is cast back.
    lab = colour.XYZ_to_Lab(xyz / 100.0, whitepoint_xy).astype(np.float32)
    return {"reflectance": reflectance, "lab": lab, "valid": valid}


def reference_constants() -> tuple[np.ndarray, np.ndarray]:
    """D65 ASTM E308 weights (31, 3) float32 and the white point as CIE xy for colour-science."""
    xyz_weights = np.asarray(spherejax.tristimulus_weights("D65"), dtype=np.float32)
    white_xyz = spherejax.white_point_xyz("D65")
    return xyz_weights, colour.XYZ_to_xy(white_xyz / 100.0)


# --------------------------------------------------------------------------------------------
# Agreement


def compare(result: spherejax.CorrectionResult, reference: dict) -> dict:
    """Max abs differences over valid pixels; raises AssertionError when out of tolerance."""
    valid = np.asarray(result.valid)
    if not np.array_equal(valid, reference["valid"]):
        raise AssertionError(
            f"quality masks differ: spherejax marks {int((~valid).sum())} bad pixels, the "
            f"reference {int((~reference['valid']).sum())}"
        )
    if not valid.any():
        raise AssertionError("no valid pixel to compare: the patch ratio came out non-finite")
    reflectance_diff = float(np.max(np.abs(np.asarray(result.reflectance)[valid] - reference["reflectance"][valid])))
    lab_diff = float(np.max(np.abs(np.asarray(result.lab)[valid] - reference["lab"][valid])))
    bad = []
    if not reflectance_diff <= REFLECTANCE_TOLERANCE:  # `not <=` so NaN fails too
        bad.append(f"reflectance max |diff| {reflectance_diff:.3g} > {REFLECTANCE_TOLERANCE:g}")
    if not lab_diff <= LAB_TOLERANCE:
        bad.append(f"Lab max |diff| {lab_diff:.3g} > {LAB_TOLERANCE:g}")
    if bad:
        raise AssertionError("spherejax and the reference disagree: " + "; ".join(bad))
    return {
        "reflectance_max_abs_diff": reflectance_diff,
        "lab_max_abs_diff": lab_diff,
        "valid_pixels": int(valid.sum()),
        "bad_pixels": int((~valid).sum()),
    }


# --------------------------------------------------------------------------------------------
# Timing


def time_first_call(fn) -> tuple[float, object]:
    """Seconds for one call including trace and compile, and its (ready) result."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    return time.perf_counter() - start, out


def time_interleaved(fns: dict, repeats: int) -> dict:
    """Median and minimum seconds of `repeats` calls of each function in `fns`.

    Each function gets one untimed warm-up call (caches, allocator, and for JAX the compiled
    executable), then the functions take turns, A B A B ..., rather than all A runs and then all
    B runs: on a 2-core machine a transient background load then hits both implementations
    alike instead of skewing the ratio. Every function must return only once its work is done
    (the JAX one wraps its call in block_until_ready). The minimum is the least-disturbed run;
    the median is what a batch job sees.
    """
    for fn in fns.values():
        fn()
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    return {
        name: {"median_s": statistics.median(t), "min_s": min(t), "all_s": t}
        for name, t in times.items()
    }


def time_back_to_back(fns: dict, repeats: int) -> dict:
    """Median and minimum seconds of `repeats` consecutive calls of each function in turn (one
    untimed call first): what a plain loop over frames sees."""
    out = {}
    for name, fn in fns.items():
        fn()
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
        out[name] = {"median_s": statistics.median(times), "min_s": min(times), "all_s": times}
    return out


def copy_bandwidth(nbytes: int, threads: int, runs: int = 5) -> float:
    """Best-of-`runs` copy bandwidth in bytes/s, counting bytes read + bytes written (as STREAM).

    numpy's copy is single-threaded; with threads > 1 the buffer is split into contiguous
    chunks copied concurrently (np.copyto releases the GIL for plain dtypes), which is what a
    multi-threaded XLA kernel can draw on. Read + written is the convention that matches
    BYTES_PER_PIXEL, which also counts both directions.
    """
    src = np.ones(nbytes // 8, dtype=np.float64)  # ones, not empty: touch every page first
    dst = np.zeros_like(src)
    src_chunks = np.array_split(src, threads)
    dst_chunks = np.array_split(dst, threads)
    best = float("inf")
    with concurrent.futures.ThreadPoolExecutor(threads) as pool:
        for _ in range(runs):
            start = time.perf_counter()
            list(pool.map(np.copyto, dst_chunks, src_chunks))
            best = min(best, time.perf_counter() - start)
    return 2 * src.nbytes / best


# --------------------------------------------------------------------------------------------
# Report


class OtherProcessesLoad:
    """Context manager: the fraction of the machine's CPU time other processes used inside it.

    On a 2-core machine any other busy process (a test run, a build) shows up directly in the
    timings, so every result records whether its run was quiet: all CPUs' busy time from
    /proc/stat minus this process's own CPU time, over wall time x CPUs. None where /proc/stat
    is unavailable.
    """

    fraction: float | None = None

    @staticmethod
    def _machine_busy_s() -> float:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:8]]  # user .. softirq
        idle = fields[3] + fields[4]  # idle + iowait
        return (sum(fields) - idle) / os.sysconf("SC_CLK_TCK")

    @staticmethod
    def _own_s() -> float:
        t = os.times()
        return t.user + t.system

    def __enter__(self):
        try:
            self._start = (self._machine_busy_s(), self._own_s(), time.perf_counter())
        except (OSError, ValueError):
            self._start = None
        return self

    def __exit__(self, *exc):
        if self._start is not None:
            busy_0, own_0, wall_0 = self._start
            busy, own, wall = self._machine_busy_s() - busy_0, self._own_s() - own_0, time.perf_counter() - wall_0
            cpus = len(os.sched_getaffinity(0))
            self.fraction = max(0.0, busy - own) / (wall * cpus)
        return False


def machine_info() -> dict:
    cpu_model = "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu_model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass

    def version(dist):
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return None

    return {
        "platform": platform.platform(),
        "cpu_model": cpu_model,
        "nproc": len(os.sched_getaffinity(0)),
        "jax_devices": [str(d) for d in jax.devices()],
        "python": platform.python_version(),
        "numpy": np.__version__,
        "jax": jax.__version__,
        "jaxlib": version("jaxlib"),
        "equinox": version("equinox"),
        "colour-science": version("colour-science"),
        "spherejax": spherejax.__version__,
    }


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


def add_allocator_argument(parser: argparse.ArgumentParser) -> None:
    """--allocator reuse|default, shared by the benchmarks that time repeated calls."""
    parser.add_argument(
        "--allocator", choices=("reuse", "default"), default="default",
        help="default: glibc as it comes, what a user's script gets (spherejax reuses its own "
             "outputs' memory, spherejax.buffers); reuse: glibc keeps freed blocks "
             "(spherejax.allocator.keep_freed_memory, what the command line does), for both implementations",
    )


def apply_allocator_argument(args: argparse.Namespace) -> str:
    """Apply --allocator; call before any JAX work (glibc threads keep the arenas they have).
    Returns what is in effect, for the record."""
    if args.allocator == "reuse" and keep_freed_memory():
        return "reuse (keep_freed_memory)"
    return "glibc default"


def write_record(path: str, record: dict) -> None:
    """Write a benchmark's record as indented JSON (its folder created if missing)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(record, f, indent=2)
    print(f"\nwrote {path}")


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
