"""Named reference problems shared by the tests."""

from __future__ import annotations

import contextlib
import json
import pathlib
import re
import signal
import subprocess
import time
import warnings

import colour
import h5py
import jax
import numpy as np
import OpenImageIO as oiio
import pytest

import spherejax
from spherejax.grid import WAVELENGTHS_NM
from spherejax.polynomial import PAPER_TABLE_2
from spherejax.simulate import ExperimentDesign

#: Reference data kept in the repository, each file cited in tests/data/README.md.
DATA = pathlib.Path(__file__).resolve().parent / "data"
#: Sharma, Wu, Dalal (2005), Table 1, doi:10.1002/col.20070.
SHARMA_CSV = DATA / "sharma2005_ciede2000.csv"

#: Zou et al. (2019), Table 2, (16, 4) ordered c1..c4.
TABLE_2 = np.asarray(PAPER_TABLE_2)


def sharma_pairs():
    """Sharma, Wu, Dalal (2005) Table 1: (pair numbers (34,), lab1 (34, 3), lab2 (34, 3), dE00 (34,))."""
    data = np.loadtxt(SHARMA_CSV, delimiter=",", skiprows=1)
    return data[:, 0].astype(int), data[:, 1:4], data[:, 4:7], data[:, 7]


def gaussian_sensitivity(fwhm_nm: float = 10.0) -> np.ndarray:
    """Sensitivity M (16, 31) of 16 Gaussian filters (400..700 nm step 20) under a smooth
    xenon-like lamp and a silicon-like quantum efficiency, on 400..700 nm step 10, with each
    band normalised so that reflectance 1 gives response 1 (the flat-fielded scale)."""
    wavelengths = np.arange(400, 701, 10, dtype=np.float64)
    centres = np.arange(400, 701, 20, dtype=np.float64)
    sigma = fwhm_nm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    filters = np.exp(-0.5 * ((wavelengths[None] - centres[:, None]) / sigma) ** 2)
    lamp = 0.8 + 0.4 * (wavelengths - 400.0) / 300.0  # gently rising, xenon-like in the visible
    quantum_efficiency = 0.35 + 0.5 * np.exp(-0.5 * ((wavelengths - 560.0) / 120.0) ** 2)
    M = filters * lamp * quantum_efficiency
    return M / M.sum(axis=1, keepdims=True)


def lambertian_sphere_frames(
    rho_sample: np.ndarray,
    rho_standard: float | np.ndarray,
    rho_patch: np.ndarray,
    patch: np.ndarray,
    beta: np.ndarray,
    lamp_change: np.ndarray,
    *,
    rho_wall: np.ndarray,
    alpha_ww: float,
    alpha_wsp: float,
    alpha_spw: float,
    gamma_phi0: np.ndarray,
    dark: np.ndarray,
):
    """Camera frames of a Lambertian multi-bounce sphere, Zou et al. (2019) Eqs. 7-9, 12, 13.

    Shapes: rho_sample (H, W, B) is the sample on the holder (outside the white patch);
    rho_patch (B,) the reference white patch placed at `patch` (H, W) in both frames; beta (H, W)
    the spatial non-uniformity; lamp_change (B,) = (Phi_0 + dPhi_0) / Phi_0 during the sample
    frame; rho_wall (B,); gamma_phi0 (B,) = gamma * Phi_0; dark (H, W, B).

    Returns (white_frame, sample_frame), each (H, W, B), dark current included.
    """
    rho_standard = np.broadcast_to(np.asarray(rho_standard, dtype=np.float64), rho_sample.shape)
    holder_standard = np.where(patch[..., None], rho_patch, rho_standard)
    holder_sample = np.where(patch[..., None], rho_patch, rho_sample)
    # Eq. 9: k depends on the area-weighted mean reflectance of everything on the holder.
    k_r = alpha_ww + alpha_wsp * alpha_spw * holder_standard.mean(axis=(0, 1))
    k_s = alpha_ww + alpha_wsp * alpha_spw * holder_sample.mean(axis=(0, 1))
    b = beta[..., None]
    u_r = holder_standard * b * gamma_phi0 / (1.0 - k_r * rho_wall)  # Eq. 7 and 12
    u_s = holder_sample * b * gamma_phi0 * lamp_change / (1.0 - k_s * rho_wall)  # Eq. 8 and 13
    return u_r + dark, u_s + dark


def no_compilation_cache_writes(env: dict[str, str]) -> dict[str, str]:
    """`env` for a child process that may be cut short in the middle of a write (SIGKILL, a
    file-size limit): it still loads programs from the test run's shared persistent compilation
    cache (tests/conftest.py) but writes none, so it can never leave a torn cache entry behind
    for the other processes. (JAX writes an entry only when compiling it took at least this many
    seconds.)"""
    return {**env, "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "inf"}


# --- a command stopped partway (the kill-and-resume tests of `correct` and `acquire`) ----------

#: The one line `spherejax correct` / `spherejax acquire` ends with when SIGINT or SIGTERM stops it
#: (spherejax.interrupt): done so far, of how many, and the unit.
INTERRUPTED = re.compile(r"spherejax: interrupted after (\d+) of (\d+) (inputs|band images); run again with --resume")


def wait_until(process: subprocess.Popen, condition) -> float:
    """Poll until `condition()` holds or the process ends; return the time."""
    while not condition() and process.poll() is None:
        time.sleep(0.002)
    return time.perf_counter()


def sigkill(process: subprocess.Popen) -> bool:
    """SIGKILL `process` and reap it; False (and no kill) if it had already ended, successfully."""
    if process.poll() is not None:
        _, err = process.communicate()
        assert process.returncode == 0, err.decode() if isinstance(err, bytes) else err
        return False
    process.send_signal(signal.SIGKILL)
    process.communicate(timeout=60)
    assert process.returncode == -signal.SIGKILL
    return True


def write_with_oiio(path, pages):
    """Write pages with OpenImageIO directly (formats spherejax itself never writes)."""
    specs = [oiio.ImageSpec(p.shape[1], p.shape[0], p.shape[2], p.dtype.name) for p in pages]
    output = oiio.ImageOutput.create(str(path))
    assert output.open(str(path), specs)
    for index, (spec, pixels) in enumerate(zip(specs, pages)):
        if index:
            assert output.open(str(path), spec, "AppendSubimage")
        assert output.write_image(pixels)
    output.close()


# --- the backend JAX computes on ------------------------------------------------------------
#
# Every exact figure and ulp bound in the tests was measured on XLA's CPU backend. On a GPU the
# same jax.numpy code rounds a little differently (XLA on NVIDIA GPUs lowers float32 division to
# a reciprocal and a multiply; its exp and log are other code than the CPU's), and the
# CPU-only machinery (the fused kernel, an XLA custom call for the CPU only; the reuse of output
# memory; the block loop of the jax.numpy path) does not run at all. Tests name both here: a CPU
# figure stays what it is, and each other backend's figure says where it came from.

#: JAX's default backend in the test process ("cpu", "gpu", "tpu"): where `correct` and the
#: tests' jax.numpy calls compute.
BACKEND = jax.default_backend()
#: True on XLA's CPU backend, the one every exact figure of the tests was measured on.
ON_CPU = BACKEND == "cpu"


def cpu_only(reason: str):
    """Mark a test of CPU-only mechanics: skipped where JAX's default backend is not the CPU,
    with `reason` (what it tests that only the CPU has) in the skip message. Never skips on CPU."""
    return pytest.mark.skipif(not ON_CPU, reason=f"CPU-only mechanics, not run on the {BACKEND} backend: {reason}")


def ulp_bound(cpu: float, gpu: float) -> float:
    """A bound in units in the last place: `cpu` on the CPU backend, `gpu` on any other. The
    caller's comment gives the GPU figure's reason and measured error (or says it was not
    measured)."""
    return cpu if ON_CPU else gpu


#: ulp of a quotient on a non-CPU backend. XLA on an NVIDIA GPU divides float32 as a reciprocal
#: and a multiply, within 2 ulp of the correctly rounded quotient: the white standard
#: flat-fielded, (white - dark) / (white - dark), came out 0.99999994 (1 - 2**-24, one ulp below
#: 1) instead of 1 on an H200, jax 0.11.2. float64: not measured; the same 2 ulp kept, tight.
GPU_DIVISION_ULPS = 2


def division_rtol(dtype) -> float:
    """Relative tolerance of a quotient the tests expect exactly: 0 on CPU, where XLA divides as
    IEEE 754 does (correctly rounded: x / x is exactly 1); GPU_DIVISION_ULPS ulp of 1 in `dtype`
    on any other backend."""
    return 0.0 if ON_CPU else GPU_DIVISION_ULPS * float(np.finfo(dtype).eps)


def assert_exact_or_close(actual, desired, rtol: float, err_msg: str = "") -> None:
    """np.testing.assert_array_equal where `rtol` is 0 (the CPU figure of `division_rtol`), else
    assert_allclose within `rtol` and no absolute tolerance (NaN where `desired` is NaN)."""
    if rtol == 0:
        np.testing.assert_array_equal(actual, desired, err_msg=err_msg)
    else:
        np.testing.assert_allclose(actual, desired, rtol=rtol, atol=0, err_msg=err_msg)


#: A small experiment design (tests/test_cli.py, the `workspace` fixture of tests/conftest.py).
SMALL = ExperimentDesign(training_backgrounds=3, training_patches=3, test_backgrounds=2, test_patches=3, targets=16)


# --- colour-science as the colorimetric oracle ---------------------------------------------

#: colour-science's names of spherejax's illuminants.
COLOUR_NAME = {"D65": "D65", "A": "A", "F2": "FL2"}


def colour_sd_to_xyz(refl_31, illuminant, observer="CIE 1931 2 Degree Standard Observer"):
    """colour-science's sd_to_XYZ (ASTM E308, its default) for one 400..700/10 nm spectrum."""
    sd = colour.SpectralDistribution(refl_31, WAVELENGTHS_NM.astype(float))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "Trimming ..." notice for a 400-700 nm input
        return colour.sd_to_XYZ(
            sd, colour.MSDS_CMFS[observer], colour.SDS_ILLUMINANTS[COLOUR_NAME[illuminant]],
            method="ASTM E308",
        )


def colour_lab(refl, illuminant, observer="CIE 1931 2 Degree Standard Observer"):
    """colour-science's Lab of each spectrum, white = perfect diffuser under the illuminant."""
    white = colour_sd_to_xyz(np.ones(31), illuminant, observer)
    xyz = np.stack([colour_sd_to_xyz(r, illuminant, observer) for r in refl])
    return colour.XYZ_to_Lab(xyz / 100.0, colour.XYZ_to_xy(white / 100.0))


def calibration_entries(path) -> dict:
    """Every entry of a calibration file, read without spherejax: with h5py from HDF5 (format
    version 4 on: the datasets and the root's "header" attribute), with numpy from an older .npz.
    The header, where there is one, is "header": a uint8 array of its JSON's UTF-8 bytes."""
    with open(path, "rb") as file:
        hdf5 = file.read(8) == b"\x89HDF\r\n\x1a\n"
    if not hdf5:
        with np.load(path, allow_pickle=False) as archive:
            return {name: archive[name] for name in archive.files}
    with h5py.File(path, "r") as stored:
        entries = {name: stored[name][()] for name in stored}
        if "header" in stored.attrs:
            text = stored.attrs["header"]
            raw = text.encode("utf-8", "surrogateescape") if isinstance(text, str) else bytes(text)
            entries["header"] = np.frombuffer(raw, dtype=np.uint8)
    return entries


def write_calibration_entries(path, entries: dict, container: str | None = None) -> None:
    """Write `entries` (as `calibration_entries` gives them) as a calibration file: "hdf5" laid out
    as save_calibration lays it out (the header a UTF-8 string attribute of the root, each array
    a dataset, the frames chunked by rows), or "npz" as the writer of format versions 1 to 3 did
    (np.savez). None: by the header's format version (an .npz before 4), HDF5 without one."""
    if container is None:
        try:
            version = json.loads(entries["header"].tobytes())["format_version"]
        except (KeyError, TypeError, ValueError, RecursionError):  # no header, not JSON, no version
            version = None
        container = "npz" if isinstance(version, int) and version < 4 else "hdf5"
    if container == "npz":
        with open(path, "wb") as file:
            np.savez(file, **entries)
        return
    from spherejax.io import calibration_files

    with h5py.File(path, "w") as stored:
        for name, array in entries.items():
            if name == "header":
                # Bytes as they are (UTF-8 or not), in a UTF-8 string attribute as save_calibration's.
                stored.attrs.create("header", array.tobytes(), dtype=h5py.string_dtype("utf-8"))
                continue
            array = np.asarray(array)
            frame = name in calibration_files._FRAME_ARRAYS
            chunks = calibration_files._row_chunks(array.shape, array.dtype.itemsize) if frame else None
            stored.create_dataset(name, data=array, chunks=chunks)


@contextlib.contextmanager
def refused(error_type, path, match, *, says_expected=True):
    """Expect `error_type` with a one-line message that starts with `path` and matches `match`,
    and (unless the failure is the system's, like a full disk) says what was expected."""
    with pytest.raises(error_type, match=match) as info:
        yield info
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: "), message
    assert ("(expected " in message) == says_expected, message


def listing(folder: pathlib.Path) -> list[str]:
    """Everything below `folder`, hidden temporary files and folders included."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def image_program(raw, calibration, kernel_mode, intermediates=False):
    """`correct`'s whole-frame program (`spherejax._engine.steps.image_step`) on constants
    prepared afresh, without a plan's routes: no reuse of memory, no direct kernel call, nothing
    kept. What the routes of a plan are compared against, bit for bit."""
    import jax.numpy as jnp

    from spherejax import calibration as calibration_module
    from spherejax._engine import kernels, steps
    from spherejax.pixel_constants import PatchConstants, PixelConstants

    dtype = calibration_module.compute_dtype(raw, calibration)
    height, width = calibration.image_shape
    box = calibration.patch_box or (0, height, 0, width)
    return steps.image_step(
        jnp.asarray(raw), PixelConstants.of(calibration, dtype), PatchConstants.of(calibration, dtype, box),
        np.array([box[0], box[2]], np.int32), box_shape=(box[1] - box[0], box[3] - box[2]),
        saturation=calibration_module.saturation_level(raw, calibration), intermediates=intermediates,
        kernel=kernels.of_mode(kernel_mode),
    )


def nonlinear_targets(rng, n):
    """Responses (n, 8) and reflectances (n, 31) of a family with three degrees of freedom t (as a
    family of three dyes): responses linear in t, reflectances an affine map of the responses
    plus a smooth nonlinear function of t."""
    t = rng.uniform(0.0, 1.0, size=(n, 3))
    fixed = np.random.default_rng(99)  # the same maps for every draw
    V = 0.2 + t @ fixed.uniform(0.0, 0.5, size=(3, 8))
    basis = np.sin(np.linspace(0, 3, 31))[None]
    R = 0.3 + V @ fixed.normal(scale=0.05, size=(8, 31)) + 0.05 * np.sin(3 * t[:, :1] + 2 * t[:, 1:2]) * basis
    return V, R


def numpy_kernel_estimate(v, calibration):
    """W v + r0 + A k(v) in float64 of Stage II responses v (..., B) with a calibration whose
    estimator has a kernel residual: E9-E10 of spherejax.estimation.kernel_residual written out,
    the oracle the kernels' residual is tested against."""
    k = calibration.wiener_residual
    u = (v - np.asarray(k.centre, np.float64)) @ np.asarray(k.whitening, np.float64).T
    features = np.exp(-0.5 * np.sum((u[..., None, :] - np.asarray(k.inducing, np.float64)) ** 2, axis=-1))
    return (v @ np.asarray(calibration.wiener, np.float64).T + np.asarray(calibration.wiener_offset, np.float64)
            + features @ np.asarray(k.weights, np.float64).T)


#: The saturation level of `make_fused_case`'s frames (a 14-bit camera's full scale).
FUSED_SATURATION = 16383.0


def make_fused_case(height, width, bands, *, raw_dtype=np.uint16, images=(), seed=0, saturation=FUSED_SATURATION, offset=False):
    """(raw, calibration): frames with every kind of bad pixel for the fused kernel's tests, of
    `bands` bands (`images` leading axes of raw); with
    `offset`, a non-zero Wiener offset r0 of both signs (else r0 = 0)."""
    rng = np.random.default_rng(seed)
    dark = rng.uniform(95, 105, (height, width, bands)).astype(np.float32)
    white = (dark + rng.uniform(8000, 12000, (height, width, bands))).astype(np.float32)
    # Reflectances from 0.001 to 1.2: XYZ / white spans both branches of the Lab companding.
    level = np.exp(rng.uniform(np.log(1e-3), np.log(1.2), (*images, height, width, 1)))
    raw = dark + (white - dark) * level * rng.uniform(0.9, 1.1, (*images, height, width, bands))
    raw = np.clip(np.rint(raw), 0, saturation - 1)
    index = (0,) * len(images)
    raw[(*index, 3, 4, 5 % bands)] = saturation  # saturated
    white[10, 11, 2 % bands] = dark[10, 11, 2 % bands]  # white == dark
    white[12, 13, 3 % bands] = dark[12, 13, 3 % bands] - 5  # white < dark
    raw[(*index, 12, 13, 0)] = saturation  # saturated and no flat field: two bits
    # Below the dark level: by 7 % of the white signal (a dark frame 700 counts too high) ...
    dark[2, 21, 1 % bands] += 700
    raw[(*index, 2, 21, 1 % bands)] = 0
    # ... and by 0.5 %, which noise allows: not flagged.
    raw[(*index, 0, 22, 2 % bands)] = np.floor(dark[0, 22, 2 % bands] - 0.005 * (white - dark)[0, 22, 2 % bands])
    if raw_dtype == np.float32:
        white[14, 15, 1 % bands] = np.nan
        white[16, 17, 0] = np.inf
        raw[(*index, 6, 7, 0)] = np.nan
        raw[(*index, 8, 9, bands - 1)] = -np.inf
        raw[(*index, 18, 19, 0)] = np.inf
        raw[(*index, 1, 20, 0)] = -1000.0  # a raw value of -1000 counts: v about -0.11
    raw = raw.astype(raw_dtype)
    patch = np.zeros((height, width), bool)
    patch[height // 2 - 4:height // 2 + 4, width // 2 - 5:width // 2 + 5] = True
    coeffs = np.asarray(PAPER_TABLE_2[np.arange(bands) % 16], np.float32)
    wiener = (np.abs(rng.normal(0.0, 1.0, (31, bands))) / bands).astype(np.float32)
    wiener_offset = (rng.uniform(-0.05, 0.05, 31) if offset else np.zeros(31)).astype(np.float32)
    calibration = spherejax.Calibration(
        dark=dark, white=white, patch=patch, coeffs=coeffs, wiener=wiener, saturation=saturation,
        wiener_offset=wiener_offset,
    )
    return raw, calibration


def tiny_frames():
    """A 6 x 7 x 16 float64 scene of the uncertainty tests, drawn with seed 3: (rng (for more
    draws after these), the Monte Carlo scene `monte_carlo.noise_scene(block=2)` (its Wiener
    estimator), raw, dark, white, patch (the 2 x 2 white patch, raw there 1.1 x the white))."""
    from spherejax import monte_carlo as mc

    rng = np.random.default_rng(3)
    height, width, bands = 6, 7, 16
    scene = mc.noise_scene(block=2)
    dark = 100.0 + rng.normal(0, 2, (height, width, bands))
    white = dark + rng.uniform(9000, 12000, (height, width, bands))
    raw = dark + (white - dark) * rng.uniform(0.03, 1.0, (height, width, bands)) * 1.1
    patch = np.zeros((height, width), bool)
    patch[:2, :2] = True
    raw[patch] = dark[patch] + (white[patch] - dark[patch]) * 1.1
    return rng, scene, raw, dark, white, patch


# --- the command line, in process ---------------------------------------------------------


def run_cli(argv, capsys):
    """(exit status, stdout, stderr) of `spherejax ARGV` run in this process."""
    from spherejax import cli

    status = cli.main(argv)
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def assert_refused(status, err, *fragments):
    """A bad input's refusal: exit status 2 and one line "spherejax: error: ..." holding every
    fragment, no traceback."""
    from spherejax import cli

    assert status == cli.EXIT_BAD_INPUT
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("spherejax: error: ")
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])



def corrected_oracle(files) -> dict:
    """For `corrected_workspace`'s files: correct(..., noise=) of the raw cube with the
    calibration's own noise model (the per-pixel oracle of the viewer's tests), and what it used:
    {"result", "raw", "calibration", "noise"}."""
    import spherejax as sj
    from spherejax import io

    calibration_file = io.open_calibration(files["calibration"])
    calibration, noise = calibration_file.calibration(), calibration_file.noise_model
    calibration_file.close()
    raw = io.read_cube(files["raw"], expected_shape=(*calibration.image_shape, calibration.bands))
    return {"result": sj.correct(raw, calibration, noise=noise), "raw": raw, "calibration": calibration, "noise": noise}
