"""Time the Pallas prototype of the per-pixel step (spherejax/_engine/gpu_kernel.py) against the
jax.numpy path (equations.pixel_outputs) on a GPU, back to back, after checking that they agree.

Inputs as benchmarks/reference.py's make_inputs: (size, size, 16) uint16 raw, float32 dark and
white, the paper's Table 2 Stage II and the affine Wiener estimator; sizes above 1024 are the
1024 x 1024 frames tiled (making 4096 x 4096 with NumPy takes most of a minute), the patch ratio
from the tiled frame. Each function: 2 warm-up calls, then 20 timed calls, each waited for
(block_until_ready); median ms, ms per megapixel, and the fraction of the HBM floor (297 bytes a
pixel at --hbm-gbs GB/s, 3350 for an H100 SXM). Lowering or compilation errors are printed, not
raised.

    XLA_PYTHON_CLIENT_PREALLOCATE=false python benchmarks/bench_gpu_kernel.py [--sizes 1024 4096]
        [--variants 128x4 64x4 256x4 256x8] [--interpret] [--budget-s 150]

Needs the benchmarks' requirements (colour-science: reference.py imports it, and the Wiener
estimator's training spectra come from its datasets through spherejax.spectra). About 30 s on an
H100 for both sizes.

The kernel estimator (a calibration with a kernel residual, E8-E10; `gpu_residual`): at every
size, for each of --residual-points (default 64, the fit's; 200 takes the chunks' loop), the kernel
with a residual of that many inducing points against its affine twin (the same calibration without
the residual) and against the jax.numpy path with the residual, back to back, each kernel with
its constants prepared once (`gpu_kernel.prepare`, as a plan does), after checking the residual
kernel against the jax.numpy path; reported as the ratio kernel estimator / affine twin (the
issue's target on a GPU: at most 2x at 4096 x 4096 with the frame on the device).
--residual-variants: inducing points per chunk, and "-tf32x3" for the residual's products as three
TF32 tensor-core products instead of IEEE float32 FMAs; the first at every size, the others at the
largest.

--interpret runs the kernel in Pallas's interpreter (a CPU smoke test of this script, with small
--sizes); its times say nothing about a GPU:
    python benchmarks/bench_gpu_kernel.py --interpret --sizes 128 --variants 128x4 --residual-variants 64 32
"""

from __future__ import annotations

import argparse
import os
import pathlib
import statistics
import sys
import time
import traceback
import warnings

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import jax
import jax.numpy as jnp
import numpy as np
import reference

import spherejax
from spherejax import equations
from spherejax._engine import gpu_kernel
from spherejax._engine.gpu_kernel import pixel_outputs_pallas
from spherejax.estimation import kernel_residual
from spherejax.pixel_constants import PixelConstants

warnings.filterwarnings("ignore", "The Pallas Triton backend is deprecated", DeprecationWarning)

BYTES_PER_PIXEL = reference.BYTES_PER_PIXEL  # 297
_START = time.perf_counter()


def log(message):
    print(f"[{time.perf_counter() - _START:6.1f} s] {message}", flush=True)


def inputs_of(size):
    base = reference.make_inputs(min(size, 1024))
    if size <= 1024:
        return base
    reps = -(-size // 1024)
    tile = lambda a: np.ascontiguousarray(np.tile(a, (reps, reps, 1))[:size, :size])
    return {"raw": tile(base["raw"]), "dark": tile(base["dark"]), "white": tile(base["white"]),
            "patch": reference.patch_mask(size)}


def time_calls(fn, args, warmups=2, calls=20):
    for _ in range(warmups):
        jax.block_until_ready(fn(*args))
    times = []
    for _ in range(calls):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return statistics.median(times), min(times)


@jax.jit
def compare(got, want):
    """(quality equal everywhere, NaN positions equal, max |diff| reflectance, max |diff| Lab)."""
    (r, l, q), (r0, l0, q0) = got, want
    nan_same = jnp.all(jnp.isnan(r) == jnp.isnan(r0)) & jnp.all(jnp.isnan(l) == jnp.isnan(l0))
    diff = lambda a, b: jnp.max(jnp.where(jnp.isnan(b), 0.0, jnp.abs(a - b)))
    return jnp.all(q == q0), jnp.sum(q != q0), nan_same, diff(r, r0), diff(l, l0), jnp.sum(q0 != 0)


def residual_for(raw, p, constants, saturation, points, seed=1):
    """A kernel residual (`KernelResidual`, float32) of `points` inducing points that matters on
    this frame, made as the fit makes one (E9-E12): whitened on the Stage II responses of the good
    pixels of a 256 x 256 sample of rows and columns, inducing points at `points` of them,
    lengthscale 2 folded in, weights A (31, m) from N(0, 0.05^2) cut to rank
    `kernel_residual.RESIDUAL_RANK` (the GPU kernel applies A whole: its cost does not depend on
    the rank). raw (H, W, 16), p (16,), constants: the frame's affine `PixelConstants`."""
    rng = np.random.default_rng(seed)
    every = (slice(None, None, max(1, raw.shape[0] // 256)),) * 2
    sample = constants.pixels(constants.dark[every], constants.white[every])
    *_, quality, _, _, v_tilde = equations.pixel_outputs(raw[every], p, sample, saturation=saturation,
                                                         intermediates=True)
    v = np.asarray(v_tilde, np.float64)[np.asarray(quality) == 0]
    mu, S = kernel_residual.whitening_of(v)
    S = S / 2.0
    Z = (v[rng.choice(len(v), points, replace=False)] - mu) @ S.T
    A = kernel_residual._at_rank(jnp.asarray(rng.normal(scale=0.05, size=(31, points))), kernel_residual.RESIDUAL_RANK)
    return kernel_residual.KernelResidual(*(jnp.asarray(x, jnp.float32) for x in (mu, S, Z, A)))


def with_residual(raw, p, constants, saturation, points):
    """`constants` with the kernel residual of `residual_for`, on the device."""
    c = constants
    residual = residual_for(raw, p, constants, saturation, points)
    return jax.device_put(PixelConstants(c.dark, c.white, c.coeffs, c.wiener, c.wiener_offset, c.tristimulus_weights,
                                         residual))


def time_residual(raw, p, constants, saturation, points, variant, args, block, warps):
    """Rows (name, median s, best s) of the affine kernel, the kernel with a residual of `points`
    inducing points (`variant`: "<chunk>" or "<chunk>-tf32x3") and the jax.numpy path with that
    residual, timed back to back after checking the residual kernel against the jax.numpy path;
    and the ratio kernel estimator / affine twin. None if the residual kernel failed to compile."""
    chunk = int(variant.removesuffix("-tf32x3"))
    precision = (jax.lax.DotAlgorithmPreset.TF32_TF32_F32_X3 if variant.endswith("-tf32x3")
                 else jax.lax.Precision.HIGHEST)
    kernel_constants = with_residual(raw, p, constants, saturation, points)
    prepare = jax.jit(gpu_kernel.prepare, static_argnames="inducing_chunk")
    affine_prepared = jax.block_until_ready(prepare(constants))
    kernel_prepared = jax.block_until_ready(prepare(kernel_constants, inducing_chunk=chunk))

    def pallas(r, p, c, k):
        return pixel_outputs_pallas(r, p, c, saturation=saturation, prepared=k, block_pixels=block,
                                    interpret=args.interpret, num_warps=None if args.interpret else warps,
                                    residual_precision=precision)

    kernel = jax.jit(pallas)
    plain = jax.jit(lambda r, p, c: equations.pixel_outputs(r, p, c, saturation=saturation))
    name = f"kernel estimator, {points} points, chunk {chunk}" + (" tf32x3" if variant.endswith("-tf32x3") else "")
    want = jax.block_until_ready(plain(raw, p, kernel_constants))
    try:
        start = time.perf_counter()
        got = jax.block_until_ready(kernel(raw, p, kernel_constants, kernel_prepared))
        log(f"{name}: first call (lower, compile, run) {time.perf_counter() - start:.2f} s")
    except Exception as error:  # noqa: BLE001 - report and go on
        log(f"{name}: FAILED to lower/compile/run: {type(error).__name__}: {str(error)[:2000]}")
        traceback.print_exc(limit=3)
        return None
    same_q, n_diff, nan_same, d_refl, d_lab, n_bad = (np.asarray(x) for x in compare(got, want))
    affine_want = plain(raw, p, constants)
    moved = float(jnp.nanmax(jnp.abs(want[0] - affine_want[0])))
    log(f"{name}: quality equal {bool(same_q)} ({int(n_diff)} differ), NaN positions equal {bool(nan_same)}, "
        f"max |diff| reflectance {float(d_refl):.3g}, Lab {float(d_lab):.3g}; the residual moves reflectance by "
        f"up to {moved:.3g}")
    del got, want, affine_want
    fns = {
        f"affine twin, block {block} warps {warps}": lambda: kernel(raw, p, constants, affine_prepared),
        name: lambda: kernel(raw, p, kernel_constants, kernel_prepared),
        f"jax.numpy, {points} points": lambda: plain(raw, p, kernel_constants),
    }
    rows = []
    for what, fn in fns.items():
        median, best = time_calls(lambda fn=fn: fn(), ())
        rows.append((what, median, best))
    return rows, rows[1][1] / rows[0][1]


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 4096])
    parser.add_argument("--variants", nargs="+", default=["128x4", "64x4", "256x4", "256x8", "512x8"],
                        help="block_pixels x num_warps; the first is checked and timed at every size, "
                             "the others at the largest")
    parser.add_argument("--hbm-gbs", type=float, default=3350.0)
    parser.add_argument("--interpret", action="store_true")
    parser.add_argument("--budget-s", type=float, default=150.0, help="skip further variants after this")
    parser.add_argument("--residual-points", type=int, nargs="*", default=[64, 200],
                        help="inducing points of the kernel estimator's residuals (none: no residual cases)")
    parser.add_argument("--residual-variants", nargs="+", default=["64", "32", "64-tf32x3"],
                        help="inducing points per chunk, -tf32x3 for TF32x3 products; the first at every size, "
                             "the others at the largest")
    args = parser.parse_args()
    device = jax.devices()[0]
    log(f"jax {jax.__version__}, {device.platform} {device.device_kind}, HBM floor at {args.hbm_gbs} GB/s")

    coeffs = reference.stage2_coeffs()
    wiener, wiener_offset = reference.wiener_estimator()
    rows, ratios = [], []
    for size in args.sizes:
        inputs = inputs_of(size)
        calibration = reference.make_calibration(inputs, coeffs, wiener, wiener_offset)
        raw = jax.device_put(inputs["raw"])
        constants = jax.device_put(PixelConstants.of(calibration, np.float32))
        p = jax.block_until_ready(spherejax.patch_ratio(raw, calibration))
        saturation = reference.SATURATION
        pixels = size * size
        floor_s = BYTES_PER_PIXEL * pixels / (args.hbm_gbs * 1e9)
        log(f"--- {size} x {size}: raw {raw.dtype} {raw.shape}, p {np.asarray(p)[:3]}..., floor {floor_s * 1e3:.3f} ms")

        plain = jax.jit(lambda r, p, c, saturation=saturation: equations.pixel_outputs(r, p, c, saturation=saturation))
        want = jax.block_until_ready(plain(raw, p, constants))
        fns = {"jax.numpy _pixel_outputs": plain}
        variants = args.variants if size == max(args.sizes) else args.variants[:1]
        variants = [*variants, f"{variants[0]}-approxdiv"] if size == max(args.sizes) else variants
        for variant in variants:
            if time.perf_counter() - _START > args.budget_s:
                log(f"budget: {variant} skipped")
                continue
            approx = variant.endswith("-approxdiv")
            block, warps = (int(x) for x in variant.removesuffix("-approxdiv").split("x"))
            name = f"pallas block {block} warps {warps}" + (" approx div" if approx else "")
            fn = jax.jit(lambda r, p, c, block=block, warps=warps, approx=approx, saturation=saturation: pixel_outputs_pallas(
                r, p, c, saturation=saturation, block_pixels=block, interpret=args.interpret,
                num_warps=None if args.interpret else warps, exact_division=False if approx else None))
            try:
                start = time.perf_counter()
                got = jax.block_until_ready(fn(raw, p, constants))
                log(f"{name}: first call (lower, compile, run) {time.perf_counter() - start:.2f} s")
            except Exception as error:  # noqa: BLE001 - report and go on
                log(f"{name}: FAILED to lower/compile/run: {type(error).__name__}: {str(error)[:2000]}")
                traceback.print_exc(limit=3)
                continue
            same_q, n_diff, nan_same, d_refl, d_lab, n_bad = (np.asarray(x) for x in compare(got, want))
            log(f"{name}: quality equal {bool(same_q)} ({int(n_diff)} differ, {int(n_bad)} flagged), NaN positions "
                f"equal {bool(nan_same)}, max |diff| reflectance {float(d_refl):.3g}, Lab {float(d_lab):.3g}")
            fns[name] = fn
            del got
        for name, fn in fns.items():  # back to back, the jax.numpy path first
            median, best = time_calls(fn, (raw, p, constants))
            rows.append((size, name, median * 1e3, best * 1e3, median * 1e3 / (pixels / 1e6), floor_s / median))
            log(f"{size}: {name}: median {median * 1e3:.3f} ms")
        del want
        block, warps = (int(x) for x in args.variants[0].split("x"))
        residual_variants = args.residual_variants if size == max(args.sizes) else args.residual_variants[:1]
        for points in args.residual_points:
            for variant in residual_variants:
                if time.perf_counter() - _START > args.budget_s:
                    log(f"budget: the residual of {points} points, chunk {variant}, skipped")
                    continue
                timed = time_residual(raw, p, constants, saturation, points, variant, args, block, warps)
                if timed is None:
                    continue
                pair, ratio = timed
                for name, median, best in pair:
                    rows.append((size, name, median * 1e3, best * 1e3, median * 1e3 / (pixels / 1e6),
                                 floor_s / median))
                ratios.append((size, pair[1][0], ratio))
                log(f"{size}: {pair[1][0]}: {pair[1][1] * 1e3:.3f} ms, {ratio:.2f}x its affine twin")
        del raw, constants
    print(f"\n{'size':>5} {'what':48} {'median ms':>10} {'min ms':>9} {'ms/MP':>8} {'HBM floor':>9}")
    for size, name, median, best, per_mp, fraction in rows:
        print(f"{size:>5} {name:48} {median:10.3f} {best:9.3f} {per_mp:8.4f} {fraction:9.1%}")
    for size, name, ratio in ratios:
        print(f"{size:>5} {name}: {ratio:.2f}x its affine twin, same run (target on a GPU at 4096: <= 2x)")


if __name__ == "__main__":
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    main()
