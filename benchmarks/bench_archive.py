"""Archive throughput of `spherejax correct` (batch correction) against a plain numpy script.

What it measures
    `spherejax.archive.run_batch` (what `spherejax correct -c CAL INPUT... -o OUT` runs) on
    --files simulated captures of --size x --size x 16 uint16 (default 200 1-megapixel captures),
    in-process and with 2 local dask workers (`spherejax.cluster.DaskExecutor(workers=2)`, as
    `--workers 2`). Each input gives four outputs (`spherejax.archive`):
    reflectance (31-channel float32 OpenEXR), Lab (3-channel float32 OpenEXR), both with
    spherejax's default compression (io.DEFAULT_EXR_COMPRESSION, none), quality
    (uint8 PNG) and an sRGB preview (8-bit PNG), each written under a temporary name, fsynced,
    hashed and renamed into place, plus one fsynced manifest line per input. Figures: wall
    seconds, files/s, megapixels/s and the speed ratio against the reference (reference wall /
    this wall: above 1 is faster than the reference).

Against what
    1. The reference: a plain numpy + colour-science batch, the script a lab would write. For
       each input it reads the TIFF with OpenImageIO, corrects it with
       `reference.reference_correct` (the calibration's arrays loaded with `numpy.load`),
       computes the quality bits and the same sRGB preview (`spherejax.archive.srgb_preview`,
       itself numpy + colour-science) and writes the same four outputs with OpenImageIO (same
       formats, channel names, EXR compression): plain writes, no temporary
       names, no fsync, no manifest, no checksums. One process.
       Before anything is timed, the first capture is corrected both ways and the files are read
       back and compared: reflectance within 1e-4 and Lab within 1e-2 over the valid pixels,
       identical quality images (else the script stops with an error); the preview difference
       is reported.
    2. The I/O floor, as context: read every input (decode the TIFF) and write four outputs'
       worth of precomputed arrays (the reference's outputs of the first capture) with
       OpenImageIO, the same formats and compression; once without fsync and once with an fsync
       of each output file. No correction at all: what the file formats alone cost. Each step
       (read, each output, the fsyncs) is timed per file, and its median reported.
    3. The raw floor, the bound the archive's throughput targets are set against: each
       input's bytes read (no decoding) and one input's outputs' bytes, as spherejax wrote them,
       written as plain files under spherejax's fsync policy (temporary name, fsync, rename,
       folder fsync). Measured three times (first, after spherejax's run, last) and the median
       taken: on a virtual machine the same bytes took 0.04-0.34 s a file from run to run.
       Once more, after spherejax's run, written past the page cache as spherejax writes its
       EXR and ENVI outputs (`spherejax.io.direct_io`): what the disk alone costs.
    4. fsync: the in-process run measures the seconds spent inside `os.fsync` (a wrapper that
       only reads the clock around the real call; spherejax calls it through the `os` module).
       And a diagnostic, never a headline figure: spherejax in-process again with `os.fsync`
       replaced by a no-op; (normal - no-op) / normal also counts what fsync changes outside
       the call (writeback left to the kernel), but two runs differ by noise too.

How
    Every timed run is a fresh child process (`--child`, internal, started with `python -c` so
    that dask's spawned workers do not re-import this script, numpy, colour and JAX with it),
    so that none inherits another's heap or JAX state: spherejax's in-process run therefore
    includes its JAX compile, and the first file's time is reported on its own. Each run's
    wall time covers its whole batch (the reference's `numpy.load` of the calibration and
    spherejax's calibration check included), not the child's Python start-up and imports. Before each run
    the previous run's OUT is deleted and the file system synced (`os.sync`), so a run never pays
    for the writeback of the one before; right after each run the script times another
    `os.sync()`, reported as "sync after": the reference and the no-fsync floor leave their
    outputs in the page cache, and that column says what getting them to disk would cost. The
    inputs are in the page cache for every run (written just before; they fit in memory).
    For the workers the dask start-up (LocalCluster + client + worker plugin) is timed apart
    from the batch; the workers use a JAX compilation cache in the work folder, empty at the
    start, so their first files compile. Each result records the share of the machine's CPU
    that other processes took during its child's life (`harness.OtherProcessesLoad`,
    counting the child and its workers as this run's own); on 2 cores that matters.

Data
    Simulating 200 1-megapixel captures with `spherejax.simulate` takes about 5 s each on a
    2-core machine (17 minutes), so the simulator renders --distinct (default 8) distinct
    captures and the --files inputs are made from them cheaply. The physical simulator runs at
    --size x --size: `ExperimentDesign(pixels_per_cm = size / 8)` makes the 8 cm holder `size`
    rows high, and the holder is made `size - 32` columns wide (`InstrumentModel.holder_width_m`,
    7.75 cm instead of 10 at 1024) so that with the 32-column white-patch strip the frame is
    square. The session is the paper's experiment scaled down: 3 grey patches on 3 training
    backgrounds, the 144-target chart, and --distinct test captures (3 coloured patches on a
    patterned background each, rotating positions). The calibration is a real one:
    `calibrate.calibrate_session` on that session (Stage II closed form, Wiener from the
    target chart), saved with `io.save_calibration`. Input k is test capture k mod --distinct
    plus zero-mean Gaussian noise of 8 DN (a window of one noise field rolled by a random
    offset per file, then rounded and clipped to the 14-bit range), so every file has its own
    bytes, and 1e-4 of its pixels are saturated in one band (as in bench_correct.py), so that
    the bad-pixel path is exercised and checked. Each is written with `io.write_frame` (16-bit
    deflate TIFF, channels "400nm"..), by a pool of processes (2.6 s per 1-MP file).

Formats
    --format exr (the default, what `spherejax correct` writes) or envi (`--format envi`: the
    reflectance and Lab as ENVI images instead of EXR). With envi the reference writes its
    reflectance and Lab with Spectral Python's `envi.save_image` (BIP float32, NaN as the data
    ignore value, the wavelengths in the header), and the I/O floor writes the same; the PNGs
    are as above.

Run:
    python benchmarks/bench_archive.py [--files 200] [--size 1024] [--format exr|envi] [--json PATH]
    python benchmarks/bench_archive.py --files 6 --size 256 --skip-workers     # smoke test
Options: --distinct N, --workdir DIR (the file system to test: a temporary folder is made in
it and removed unless --keep), --keep, --skip-workers, --skip-diagnostic. A 200 x 1024 run needs
about 30 GB free in the work folder while a run's outputs exist (128 MiB per file; each run's
OUT is deleted after it). On a 2-core machine its setup takes about 8 minutes (simulate 1,
calibrate 0.2, write the inputs 6) and each of the six runs 7-12 minutes (2-3.5 s per file):
about an hour and a quarter in all. `--files 20` takes about 8 minutes.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import h5py
import numpy as np
import spectral
from spectral.io import envi as spectral_envi
import OpenImageIO as oiio

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from harness import OtherProcessesLoad, machine_info, write_record  # noqa: E402
from reference import (  # noqa: E402
    LAB_TOLERANCE, REFLECTANCE_TOLERANCE, SATURATION, numpy_registration, reference_constants, reference_correct,
)

from spherejax import archive, io  # noqa: E402
from spherejax.io.envi import IGNORE_VALUE  # noqa: E402
from spherejax.grid import BAND_CENTRES_NM, WAVELENGTHS_NM  # noqa: E402
from spherejax.pipeline import (  # noqa: E402
    QUALITY_PATCH_UNUSABLE,
    QUALITY_SATURATED,
    QUALITY_WHITE_NOT_ABOVE_DARK,
)

BAND_NAMES = [f"{nm}nm" for nm in BAND_CENTRES_NM.tolist()]
REFLECTANCE_NAMES = io.reflectance_channel_names(WAVELENGTHS_NM.tolist())  # as spherejax writes them
ENVI_IGNORE_VALUE = IGNORE_VALUE  # flagged pixels in ENVI outputs, as spherejax writes them
LAB_NAMES = ["L*", "a*", "b*"]  # spherejax's names ("a" alone would be taken for alpha)
STRIP_PX = 32  # the white-patch strip beside the holder (ExperimentDesign.strip_px)
INPUT_NOISE_DN = 8.0  # per-file variation of the inputs (module docstring, Data)
HOT_PIXEL_FRACTION = 1e-4  # pixels driven to saturation in each input, as bench_correct does
SEED = 20190816

#: The timed runs, in the order they run, and how the table names them.
RUN_LABELS = {
    "reference": "numpy + colour-science (ref)",
    "before": "spherejax before (--compare-with)",
    "spherejax": "spherejax, in-process",
    "workers": "spherejax, 2 dask workers",
    "before-workers": "spherejax before, 2 dask workers",
    "floor": "I/O floor, no fsync",
    "floor-fsync": "I/O floor, fsync per output",
    "raw-floor": "raw floor: bytes read, written, fsync",
    "raw-floor-direct": "raw floor, writes past the page cache",
    "spherejax-nofsync": "diagnostic: spherejax, fsync no-op",
}


# --------------------------------------------------------------------------------------------
# Inputs: a simulated session, its calibration, and the input files


def simulate_captures(folder: pathlib.Path, size: int, distinct: int, seed: int) -> tuple[list[np.ndarray], pathlib.Path, dict]:
    """Simulate a scaled-down experiment at size x size, calibrate on it, save the calibration.

    Returns the `distinct` test captures (size, size, 16) uint16, the calibration file and the
    setup timings.
    """
    from spherejax import calibrate, simulate

    pixels_per_cm = size / 8.0  # the default 8 cm holder height -> `size` rows
    instrument = simulate.InstrumentModel(holder_width_m=(size - STRIP_PX) / pixels_per_cm / 100.0)
    design = simulate.ExperimentDesign(
        pixels_per_cm=pixels_per_cm, strip_px=STRIP_PX,
        training_patches=3, training_backgrounds=3, fluorescent_training_backgrounds=1,
        test_patches=3, test_backgrounds=distinct, fluorescent_test_backgrounds=1,
    )
    if design.image_shape(instrument) != (size, size):
        raise RuntimeError(f"the simulator gives frames of {design.image_shape(instrument)}, not {(size, size)}")
    timings = {}
    start = time.perf_counter()
    session = io.write_simulated_session(folder / "session", seed=seed, instrument=instrument, design=design)
    timings["simulate_s"] = time.perf_counter() - start

    start = time.perf_counter()
    calibration, report = calibrate.calibrate_session(session)
    calibration_path = folder / "calibration.h5"
    io.save_calibration(
        calibration_path, calibration, instrument_id=session.instrument_id,
        band_centres_nm=[int(b) for b in session.band_centres_nm],
        metadata={"session": str(session.path), "calibration_report": report.as_dict()},
    )
    timings["calibrate_s"] = time.perf_counter() - start
    captures = [session.read(frame) for frame in session.frames_with(role="sample", set="test")]
    if len(captures) != distinct:
        raise RuntimeError(f"expected {distinct} test captures, the session has {len(captures)}")
    timings["simulated_frames"] = len(session.frames)
    return captures, calibration_path, timings


def _write_input(task: tuple) -> None:
    """One input file (in a pool process): a capture plus the noise field rolled by `shift`."""
    capture_path, noise_path, shift, path = task
    capture = np.load(capture_path, mmap_mode="r")
    shifted = np.roll(np.load(noise_path, mmap_mode="r"), shift).reshape(capture.shape)
    raw = np.clip(capture.astype(np.int32) + shifted, 0, SATURATION).astype(np.uint16)
    # A few saturated pixels, so that the bad-pixel path (NaN, quality bits, magenta) is in
    # every file and in the agreement check.
    hot = np.random.default_rng(shift).random(capture.shape[:2]) < HOT_PIXEL_FRACTION
    raw[hot, shift % capture.shape[-1]] = SATURATION
    io.write_frame(path, raw, channel_names=BAND_NAMES)


def write_inputs(folder: pathlib.Path, captures: list[np.ndarray], files: int, seed: int) -> list[pathlib.Path]:
    """`files` input TIFFs: capture k mod len(captures) plus rolled Gaussian noise (docstring).

    Writing a 1-MP deflate TIFF takes about 2.6 s of one core and OpenImageIO holds the GIL, so
    the files are written by a pool of processes, one per core ("spawn": JAX is already running
    here and must not be forked), which read the captures and the noise from .npy files.
    """
    import concurrent.futures
    import multiprocessing

    folder.mkdir()
    staging = folder.parent / "staging"
    staging.mkdir()
    rng = np.random.default_rng(seed)
    noise = np.rint(rng.normal(0.0, INPUT_NOISE_DN, captures[0].size)).astype(np.int32)
    np.save(staging / "noise.npy", noise)
    capture_paths = []
    for i, capture in enumerate(captures):
        capture_paths.append(staging / f"capture-{i}.npy")
        np.save(capture_paths[-1], capture)
    paths = [folder / f"capture-{k:04d}.tif" for k in range(files)]
    tasks = [
        (str(capture_paths[k % len(captures)]), str(staging / "noise.npy"), int(rng.integers(noise.size)), str(path))
        for k, path in enumerate(paths)
    ]
    processes = min(len(os.sched_getaffinity(0)), files)
    with concurrent.futures.ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn")) as pool:
        list(pool.map(_write_input, tasks))
    shutil.rmtree(staging)
    return paths


# --------------------------------------------------------------------------------------------
# Plain OpenImageIO reads and writes (the reference and the I/O floor)


def read_image(path, sample_type) -> np.ndarray:
    """The whole image (H, W, C) as `sample_type` (oiio.UINT16, FLOAT, UINT8)."""
    image = oiio.ImageInput.open(str(path))
    if image is None:
        raise OSError(f"{path}: {oiio.geterror()}")
    try:
        pixels = image.read_image(sample_type)
        if pixels is None:
            raise OSError(f"{path}: {image.geterror()}")
    finally:
        image.close()
    return pixels


def channel_names_of(path) -> list[str]:
    image = oiio.ImageInput.open(str(path))
    names = list(image.spec().channelnames)
    image.close()
    return names


def write_image(path, pixels: np.ndarray, channel_names, compression: str | None = None) -> None:
    """One plain OpenImageIO write: the format from the name, no temporary file, no fsync."""
    height, width, channels = pixels.shape
    sample_type = {np.dtype(np.float32): oiio.FLOAT, np.dtype(np.uint8): oiio.UINT8}[pixels.dtype]
    spec = oiio.ImageSpec(width, height, channels, sample_type)
    spec.channelnames = tuple(channel_names)
    spec.alpha_channel = -1  # as spherejax: no band and no Lab channel is alpha
    if compression is not None:
        spec.attribute("compression", compression)
    output = oiio.ImageOutput.create(str(path))
    if output is None:
        raise OSError(f"{path}: {oiio.geterror()}")
    written = output.open(str(path), spec) and output.write_image(np.ascontiguousarray(pixels))
    detail = output.geterror()
    if not output.close() or not written:
        raise OSError(f"{path}: could not be written: {detail or output.geterror()}")


def write_envi(header_path: pathlib.Path, pixels: np.ndarray, band_names, wavelengths=None) -> None:
    """One plain ENVI write with Spectral Python's `save_image` (header + BIP float32 data), NaN
    as the data ignore value as spherejax writes it; no temporary file, no fsync."""
    metadata = {"band names": list(band_names), "data ignore value": ENVI_IGNORE_VALUE}
    if wavelengths is not None:
        metadata.update({"wavelength": list(wavelengths), "wavelength units": "Nanometers"})
    data = np.where(np.isnan(pixels), np.float32(ENVI_IGNORE_VALUE), pixels).astype(np.float32)
    spectral_envi.save_image(str(header_path), data, metadata=metadata, interleave="bip", ext=".img",
                             dtype=np.float32, force=True)


def write_outputs(stem: pathlib.Path, arrays: dict, output_format: str = "exr", fsync: bool = False,
                  steps: dict | None = None, exr_compression: str = io.DEFAULT_EXR_COMPRESSION) -> None:
    """One input's outputs in `output_format`, named as spherejax names them ("<stem>.<kind>"),
    EXRs with `exr_compression`; with `fsync`, each file is fsynced once written. `steps`
    collects seconds per step."""
    paths = {kind: stem.parent / f"{stem.name}.{kind}" for kind in archive.OUTPUT_KINDS_BY_FORMAT[output_format]}
    if output_format == "exr":
        writes = {
            "reflectance.exr": lambda: write_image(paths["reflectance.exr"], arrays["reflectance"], REFLECTANCE_NAMES,
                                                   exr_compression),
            "lab.exr": lambda: write_image(paths["lab.exr"], arrays["lab"], LAB_NAMES, exr_compression),
        }
    else:
        writes = {
            "reflectance.envi": lambda: write_envi(paths["reflectance.hdr"], arrays["reflectance"], REFLECTANCE_NAMES,
                                                   WAVELENGTHS_NM.tolist()),
            "lab.envi": lambda: write_envi(paths["lab.hdr"], arrays["lab"], LAB_NAMES),
        }
    writes["quality.png"] = lambda: write_image(paths["quality.png"], arrays["quality"][..., None], ["quality"])
    writes["preview.png"] = lambda: write_image(paths["preview.png"], arrays["preview"], ["R", "G", "B"])
    for step, write in writes.items():
        start = time.perf_counter()
        write()
        if steps is not None:
            steps.setdefault(step, []).append(time.perf_counter() - start)
    if fsync:
        start = time.perf_counter()
        for path in paths.values():
            fd = os.open(path, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        if steps is not None:
            steps.setdefault("fsync", []).append(time.perf_counter() - start)


def read_outputs(stem: pathlib.Path, output_format: str) -> dict:
    """The four output arrays of one input as written (ENVI's ignore value back to NaN)."""
    name = lambda kind: stem.parent / f"{stem.name}.{kind}"  # noqa: E731
    # spherejax's quality mask is a palette PNG whose indices are the bits (OpenImageIO would
    # read its colours); io.read_quality_png reads it and the reference's grey one alike.
    arrays = {"quality": io.read_quality_png(name("quality.png")),
              "preview": read_image(name("preview.png"), oiio.UINT8)}
    for output in ("reflectance", "lab"):
        if output_format == "exr":
            arrays[output] = read_image(name(f"{output}.exr"), oiio.FLOAT)
        else:
            pixels = np.asarray(spectral.open_image(str(name(f"{output}.hdr"))).load(), dtype=np.float32)
            arrays[output] = np.where(pixels == ENVI_IGNORE_VALUE, np.float32(np.nan), pixels)
    return arrays


# --------------------------------------------------------------------------------------------
# The reference: numpy + colour-science


def load_reference_calibration(path) -> dict:
    """The calibration's arrays read with h5py (not spherejax), plus what the reference derives
    from them once per batch: the colorimetric constants and the pixels without a flat field."""
    with h5py.File(path, "r") as stored:
        arrays = {name: stored[name][()] for name in ("dark", "white", "patch", "coeffs", "wiener", "wiener_offset")}
        # The estimator's kernel residual, where "auto" chose one (format 5; m = 0 rows: affine).
        arrays["residual"] = tuple(
            stored[f"wiener_residual_{part}"][()].astype(np.float32) for part in ("centre", "whitening", "inducing", "weights")
        ) if "wiener_residual_weights" in stored else None
        # Bands in register (format 7): the maps `calibrate` estimates by default.
        arrays["band_transforms"] = stored["band_transforms"][()] if "band_transforms" in stored else None
        header = json.loads(stored.attrs["header"])
    # reference_correct is written for a D65, 14-bit calibration (reference.py's constants).
    if header["illuminant"] != "D65" or header["saturation"] != SATURATION:
        raise ValueError(
            f"{path}: the reference needs a D65 calibration with saturation {SATURATION:g}, got "
            f"{header['illuminant']} and {header['saturation']}"
        )
    arrays["xyz_weights"], arrays["whitepoint_xy"] = reference_constants()
    arrays["no_flat_field"] = np.any(~(arrays["white"] - arrays["dark"] > 0), axis=-1)
    return arrays


def reference_outputs(raw: np.ndarray, calibration: dict) -> dict:
    """The four output arrays of one raw cube: reflectance, Lab, quality bits, preview.

    With band maps the bands are first registered (`reference.numpy_registration`), and the
    registered frames corrected with dark 0 and white s', as spherejax does."""
    dark, white, patch = calibration["dark"], calibration["white"], calibration["patch"]
    if calibration["band_transforms"] is not None:
        raw, white, quality = numpy_registration(raw, dark, white, calibration["band_transforms"], SATURATION)
        # Flagged pixels NaN: the reference then leaves them out of the patch and the outputs.
        raw = np.where((quality == 0)[..., None], raw, np.float32(np.nan))
        dark = np.zeros_like(white)
    else:
        quality = np.where(np.any(raw >= SATURATION, axis=-1), QUALITY_SATURATED, 0).astype(np.uint8)
        quality[calibration["no_flat_field"]] |= QUALITY_WHITE_NOT_ABOVE_DARK
    result = reference_correct(
        raw, dark, white, patch, calibration["coeffs"],
        calibration["wiener"], calibration["xyz_weights"], calibration["whitepoint_xy"],
        calibration["wiener_offset"], calibration["residual"],
    )
    # Invalid with no pixel-level reason: the white-patch ratio was not finite.
    quality[~result["valid"] & (quality == 0)] = QUALITY_PATCH_UNUSABLE
    return {
        "reflectance": result["reflectance"],
        "lab": result["lab"],
        "quality": quality,
        "preview": archive.srgb_preview(result["reflectance"]),
    }


def reference_batch(inputs: list, out: pathlib.Path, calibration_path, output_format: str = "exr",
                    exr_compression: str = io.DEFAULT_EXR_COMPRESSION) -> list[float]:
    """Correct every input into `out` the plain way; returns each file's seconds."""
    calibration = load_reference_calibration(calibration_path)
    out.mkdir(parents=True, exist_ok=True)
    seconds = []
    for path in inputs:
        start = time.perf_counter()
        raw = read_image(path, oiio.UINT16)
        write_outputs(out / pathlib.Path(path).stem, reference_outputs(raw, calibration), output_format,
                      exr_compression=exr_compression)
        seconds.append(time.perf_counter() - start)
    return seconds


# --------------------------------------------------------------------------------------------
# The I/O floor


def io_floor(inputs: list, out: pathlib.Path, arrays: dict, fsync: bool, output_format: str = "exr",
             exr_compression: str = io.DEFAULT_EXR_COMPRESSION) -> tuple[list[float], dict]:
    """Read (decode) every input and write the precomputed `arrays` as its four outputs.

    Returns each file's seconds and the seconds of each step per file (read, each output,
    fsync): where the time of the formats goes.
    """
    out.mkdir(parents=True, exist_ok=True)
    seconds, steps = [], {"read": []}
    for path in inputs:
        start = time.perf_counter()
        read_image(path, oiio.UINT16)
        steps["read"].append(time.perf_counter() - start)
        write_outputs(out / pathlib.Path(path).stem, arrays, output_format, fsync=fsync, steps=steps,
                      exr_compression=exr_compression)
        seconds.append(time.perf_counter() - start)
    return seconds, steps


def raw_floor(inputs: list, out: pathlib.Path, outputs: dict[str, bytes], direct: bool = False) -> tuple[list[float], dict]:
    """The raw floor: for each input, read its bytes (a plain read, no decoding) and write
    `outputs` (kind -> the bytes of one input's outputs as spherejax wrote them in the agreement
    check, precomputed) as plain files under the same fsync policy as spherejax's
    (`spherejax.atomic_files`): each file written under a temporary name, fsynced, renamed into
    place, and its folder fsynced. No decoding, correction or encoding: what the disk and the
    kernel alone cost. With `direct`, each file is written past the page cache where the disk
    takes it, as spherejax writes its EXR and ENVI outputs (`spherejax.io.direct_io`): what the
    disk alone costs. Returns each file's seconds and the seconds of each step per file."""
    from spherejax.io.direct_io import DirectFile

    out.mkdir(parents=True, exist_ok=True)
    seconds, steps = [], {"read": [], "write": [], "fsync": []}
    for path in inputs:
        start = time.perf_counter()
        with open(path, "rb") as handle:
            handle.read()
        steps["read"].append(time.perf_counter() - start)
        written = fsynced = 0.0
        for kind, data in outputs.items():
            final = out / f"{pathlib.Path(path).stem}.{kind}"
            temporary = final.with_name(f".{final.name}.tmp")
            begin = time.perf_counter()
            with open(temporary, "wb") as handle:
                if direct:
                    unbuffered = DirectFile(handle.fileno())
                    unbuffered.write(data)
                    middle = time.perf_counter()
                    unbuffered.finish()  # the last partial block, and the fsync
                else:
                    handle.write(data)
                    handle.flush()
                    middle = time.perf_counter()
                    os.fsync(handle.fileno())
            os.replace(temporary, final)
            folder = os.open(out, os.O_RDONLY)
            try:
                os.fsync(folder)
            finally:
                os.close(folder)
            written += middle - begin
            fsynced += time.perf_counter() - middle
        steps["write"].append(written)
        steps["fsync"].append(fsynced)
        seconds.append(time.perf_counter() - start)
    return seconds, steps


# --------------------------------------------------------------------------------------------
# The timed runs, each in its own child process


def _cpu_s() -> float:
    """CPU seconds of this process and of its children that have been waited for."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _spherejax_batch(job: dict, executor=None, options: dict | None = None) -> tuple[list[float], float]:
    """run_batch over the inputs folder with the job's output options (`options` instead where
    given); (each file's seconds in completion order, wall)."""
    seconds = []
    options = job["spherejax_options"] if options is None else options

    def on_result(spec, result):
        if result is None or result.status != "done":
            raise RuntimeError(f"{spec.source}: {'skipped' if result is None else result.reason}")
        seconds.append(result.seconds)

    start = time.perf_counter()
    archive.run_batch([job["inputs_dir"]], job["out"], job["calibration"], output_format=job["output_format"],
                      on_result=on_result, executor=executor, **options)
    return seconds, time.perf_counter() - start


def child_run(kind: str, job: dict) -> dict:
    """One timed run, in a fresh process (`run_in_child`); returns its record, which `main`
    writes where BENCH_ARCHIVE_RESULT says."""
    out = pathlib.Path(job["out"])
    inputs = sorted(pathlib.Path(job["inputs_dir"]).glob("*.tif"))
    record: dict = {}
    cpu_0 = _cpu_s()
    if kind == "reference":
        start = time.perf_counter()
        seconds = reference_batch(inputs, out, job["calibration"], job["output_format"], job["exr_compression"])
        wall = time.perf_counter() - start
    elif kind in ("floor", "floor-fsync"):
        arrays = read_outputs(pathlib.Path(job["floor_stem"]), job["output_format"])  # not timed: precomputed
        cpu_0 = _cpu_s()
        start = time.perf_counter()
        seconds, steps = io_floor(inputs, out, arrays, fsync=kind == "floor-fsync", output_format=job["output_format"],
                                  exr_compression=job["exr_compression"])
        wall = time.perf_counter() - start
        record["median_step_s"] = {step: statistics.median(t) for step, t in steps.items()}
    elif kind in ("raw-floor", "raw-floor-direct"):
        stem = pathlib.Path(job["spherejax_stem"])
        outputs = {kind: (stem.parent / f"{stem.name}.{kind}").read_bytes()
                   for kind in archive.OUTPUT_KINDS_BY_FORMAT[job["output_format"]]}  # not timed
        cpu_0 = _cpu_s()
        start = time.perf_counter()
        seconds, steps = raw_floor(inputs, out, outputs, direct=kind == "raw-floor-direct")
        wall = time.perf_counter() - start
        record["median_step_s"] = {step: statistics.median(t) for step, t in steps.items()}
    elif kind == "before":
        seconds, wall = _spherejax_batch(job, options=job["before_options"])
    elif kind == "spherejax":
        from spherejax.archive import stage_times

        # Time spent inside os.fsync, measured directly (the wrapper only reads the clock).
        # spherejax calls os.fsync through the os module at call time, so this reaches it.
        real_fsync, fsync_time = os.fsync, {"s": 0.0, "calls": 0}

        def timed_fsync(fd):
            start = time.perf_counter()
            try:
                real_fsync(fd)
            finally:
                fsync_time["s"] += time.perf_counter() - start
                fsync_time["calls"] += 1

        os.fsync = timed_fsync
        with stage_times.collecting() as stages:
            seconds, wall = _spherejax_batch(job)
        record["fsync_s"], record["fsync_calls"] = fsync_time["s"], fsync_time["calls"]
        record["stages"] = stages
    elif kind == "spherejax-nofsync":
        os.fsync = lambda fd: None  # diagnostic only: what the run costs without durability
        seconds, wall = _spherejax_batch(job)
    elif kind in ("workers", "before-workers"):
        from spherejax.cluster import DaskExecutor

        # An empty compilation cache of our own: the workers' first files compile, every run.
        os.environ["SPHEREJAX_COMPILATION_CACHE"] = job["jax_cache"]
        start = time.perf_counter()
        with DaskExecutor(workers=2) as executor:
            record["startup_s"] = time.perf_counter() - start
            options = job["before_options"] if kind == "before-workers" else None
            seconds, wall = _spherejax_batch(job, executor, options=options)
            shutdown = time.perf_counter()
        record["shutdown_s"] = time.perf_counter() - shutdown
        # Worker CPU is counted once the workers have been reaped, i.e. only after shutdown:
        # this covers start-up, batch and shutdown.
        record["cpu_s_note"] = "client and workers, start-up to shutdown"
    else:
        raise ValueError(f"unknown run {kind!r}")
    record["cpu_s"] = _cpu_s() - cpu_0
    import spherejax

    record["spherejax_file"] = spherejax.__file__  # which spherejax ran (the "before" runs check it)
    start = time.perf_counter()
    os.sync()
    record["sync_after_s"] = time.perf_counter() - start
    record.update(wall_s=wall, per_file_s=seconds)
    return record


class LoadWithChildren(OtherProcessesLoad):
    """`OtherProcessesLoad` counting waited-for children (the timed run and its workers) as own."""

    @staticmethod
    def _own_s() -> float:
        return _cpu_s()


def run_in_child(kind: str, job: dict, workdir: pathlib.Path) -> dict:
    """Run `child_run(kind, job)` in a fresh Python process and return its record."""
    result_path = workdir / f"result-{kind}.json"
    job = dict(job, out=str(workdir / f"out-{kind}"))
    # `python -c`, not this file as the main script: dask starts its workers with "spawn", which
    # re-imports a main script (and with it numpy, colour, JAX) in every worker; `spherejax
    # correct`'s workers import only the small spherejax.cli.
    # The "before" runs import spherejax from the --compare-with tree, first on the path of the
    # child and of the dask workers it starts (spawned with the parent's sys.path). The child
    # runs in the work folder: with `python -c` the current folder is on the path, and in a
    # checkout it would hold a spherejax of its own.
    before = f"sys.path.insert(0, {job['compare_with']!r}); " if kind.startswith("before") else ""
    launcher = (f"import sys; {before}sys.path.insert(0, {os.path.dirname(os.path.abspath(__file__))!r}); "
                "import bench_archive; sys.exit(bench_archive.main(sys.argv[1:]))")
    env = dict(os.environ, BENCH_ARCHIVE_RESULT=str(result_path))
    command = [sys.executable, "-c", launcher, "--child", kind, "--job", json.dumps(job)]
    os.sync()  # the previous run's writeback is not this run's cost
    with LoadWithChildren() as load:
        subprocess.run(command, check=True, env=env, cwd=workdir)
    record = json.loads(result_path.read_text())
    record["other_processes_cpu_fraction"] = load.fraction
    if kind.startswith("before") and not record.get("spherejax_file", "").startswith(job["compare_with"]):
        raise RuntimeError(f"the {kind} run imported {record.get('spherejax_file')}, not --compare-with's spherejax")
    shutil.rmtree(job["out"])  # N x ~100 MB at 1 MP: only one run's outputs on disk at a time
    return record


# --------------------------------------------------------------------------------------------
# Agreement of the reference with spherejax, on the first capture, through the files


def check_agreement(first_input: pathlib.Path, calibration_path, folder: pathlib.Path,
                    output_format: str = "exr", exr_compression: str = io.DEFAULT_EXR_COMPRESSION) -> tuple[dict, pathlib.Path]:
    """Correct the first input both ways and compare the files; raise if they disagree.

    Returns the agreement figures and the reference outputs' stem (the I/O floor writes them).
    """
    calibration = load_reference_calibration(calibration_path)
    reference_stem = folder / "reference" / first_input.stem
    reference_stem.parent.mkdir(parents=True)
    write_outputs(reference_stem, reference_outputs(read_image(first_input, oiio.UINT16), calibration), output_format,
                  exr_compression=exr_compression)
    options = {"exr_compression": exr_compression} if output_format == "exr" else {}
    summary = archive.run_batch([first_input], folder / "spherejax", calibration_path, output_format=output_format,
                                **options)
    if summary.corrected != 1:
        raise RuntimeError(f"spherejax did not correct {first_input}: {summary.failed}")
    spherejax_stem = folder / "spherejax" / first_input.stem

    def channels(stem):
        if output_format == "exr":
            return [channel_names_of(stem.parent / f"{stem.name}.{output}.exr") for output in ("reflectance", "lab")]
        headers = [spectral.open_image(str(stem.parent / f"{stem.name}.{output}.hdr")).metadata
                   for output in ("reflectance", "lab")]
        return [[float(nm) for nm in header.get("wavelength", [])] + header.get("band names", []) for header in headers]

    if channels(spherejax_stem) != channels(reference_stem):
        raise AssertionError(f"channels differ: spherejax's {channels(spherejax_stem)}, the reference's {channels(reference_stem)}")
    ours, theirs = read_outputs(spherejax_stem, output_format), read_outputs(reference_stem, output_format)
    quality = ours["quality"]
    differing = int(np.count_nonzero(quality != theirs["quality"]))
    if differing:
        raise AssertionError(f"quality images differ in {differing} pixels")
    valid = quality == 0
    if not valid.any():
        raise AssertionError("no valid pixel to compare")
    diff = lambda kind: float(np.max(np.abs(ours[kind][valid] - theirs[kind][valid])))  # noqa: E731
    agreement = {
        "reflectance_max_abs_diff": diff("reflectance"),
        "lab_max_abs_diff": diff("lab"),
        "preview_max_level_diff": int(np.max(np.abs(ours["preview"].astype(int) - theirs["preview"]))),
        "preview_pixels_differing": int(np.count_nonzero(np.any(ours["preview"] != theirs["preview"], axis=-1))),
        "valid_pixels": int(valid.sum()),
        "bad_pixels": int((~valid).sum()),
    }
    bad = []
    if not agreement["reflectance_max_abs_diff"] <= REFLECTANCE_TOLERANCE:  # `not <=`: NaN fails
        bad.append(f"reflectance max |diff| {agreement['reflectance_max_abs_diff']:.3g} > {REFLECTANCE_TOLERANCE:g}")
    if not agreement["lab_max_abs_diff"] <= LAB_TOLERANCE:
        bad.append(f"Lab max |diff| {agreement['lab_max_abs_diff']:.3g} > {LAB_TOLERANCE:g}")
    if bad:
        raise AssertionError("spherejax and the reference disagree: " + "; ".join(bad))
    agreement["output_bytes_per_file"] = sum(
        (reference_stem.parent / f"{reference_stem.name}.{kind}").stat().st_size
        for kind in archive.OUTPUT_KINDS_BY_FORMAT[output_format]
    )
    return agreement, reference_stem


def half_float_accuracy(spherejax_stem: pathlib.Path) -> dict:
    """What `--reflectance-type half` costs on the first capture (a simulated one): the float32
    reflectance spherejax wrote, rounded to half floats as OpenImageIO writes them (to nearest),
    against itself: the largest spectral error, and ΔE00 (CIEDE2000, colour-science) between the
    D65 Lab of the two (ASTM E308 weights, reference.py), over the valid pixels."""
    import colour

    reflectance = read_image(spherejax_stem.parent / f"{spherejax_stem.name}.reflectance.exr", oiio.FLOAT)
    valid = np.all(np.isfinite(reflectance), axis=-1)
    full = reflectance[valid].astype(np.float64)
    half = reflectance[valid].astype(np.float16).astype(np.float64)
    xyz_weights, whitepoint_xy = reference_constants()

    def lab(r):
        return colour.XYZ_to_Lab(r @ xyz_weights.astype(np.float64) / 100.0, whitepoint_xy)

    delta_e = colour.delta_E(lab(full), lab(half), method="CIE 2000")
    return {
        "valid_pixels": int(valid.sum()),
        "max_abs_spectral_error": float(np.max(np.abs(half - full))),
        "p99_abs_spectral_error": float(np.percentile(np.abs(half - full), 99)),
        "max_delta_e00": float(np.max(delta_e)), "p99_delta_e00": float(np.percentile(delta_e, 99)),
        "mean_delta_e00": float(np.mean(delta_e)),
    }


# --------------------------------------------------------------------------------------------
# Report


def summarise(runs: dict, files: int, megapixels: float) -> dict:
    """Derived figures of every run: files/s, MP/s, ratio to the reference, first file."""
    reference_wall = runs["reference"]["wall_s"]
    for kind, r in runs.items():
        wall = r["wall_s"]
        r["files_per_s"] = files / wall
        r["mp_per_s"] = files * megapixels / wall
        r["speed_vs_reference"] = reference_wall / wall
        r["first_file_s"] = r["per_file_s"][0]
        r["median_file_s"] = statistics.median(r["per_file_s"])
        r["cpu_cores_busy"] = r["cpu_s"] / wall if not kind.endswith("workers") else None
        if kind.endswith("workers"):
            # Completion order: the first result of each worker is among the first two; the
            # slower of those carries the compile.
            r["first_file_s"] = max(r["per_file_s"][:2])
            total = wall + r["startup_s"]
            r["with_startup"] = {
                "wall_s": total, "files_per_s": files / total, "mp_per_s": files * megapixels / total,
                "speed_vs_reference": reference_wall / total,
            }
    derived = {
        # Measured inside the headline run: seconds in os.fsync over its wall time.
        "fsync_time_share_in_process": runs["spherejax"]["fsync_s"] / runs["spherejax"]["wall_s"],
    }
    sj = runs["spherejax"]
    if "raw-floor-direct" in runs:
        derived["spherejax_vs_raw_floor_direct"] = sj["wall_s"] / runs["raw-floor-direct"]["wall_s"]
    if "raw-floor" in runs:
        derived["spherejax_vs_raw_floor"] = sj["wall_s"] / runs["raw-floor"]["wall_s"]
        if "workers" in runs:
            derived["workers_vs_raw_floor"] = runs["workers"]["wall_s"] / runs["raw-floor"]["wall_s"]
    if "before" in runs:
        derived["files_per_s_vs_before"] = sj["files_per_s"] / runs["before"]["files_per_s"]
    for kind in ("workers", "before-workers"):
        # How the 2 workers scale: their files per second over the same code's in-process run's.
        in_process = "spherejax" if kind == "workers" else "before"
        if kind in runs and in_process in runs:
            derived[f"{kind}_vs_in_process"] = runs[kind]["files_per_s"] / runs[in_process]["files_per_s"]
    derived["stages"] = stage_table(sj.get("stages", []), files)
    if "spherejax-nofsync" in runs:
        # Diagnostic: also counts what fsync changes outside the call (writeback left to the
        # kernel instead); two separate runs, so subject to run-to-run noise.
        normal, no_fsync = runs["spherejax"]["wall_s"], runs["spherejax-nofsync"]["wall_s"]
        derived["fsync_share_in_process_vs_noop_run"] = (normal - no_fsync) / normal
    return derived


def stage_table(records: list[dict], files: int) -> dict:
    """Per stage (`spherejax.archive.stage_times`): the median seconds per input and the total
    over the run; plus "other" (an input's seconds in no stage: opening, checks, and where
    inputs overlap, the wait for the interpreter) and "input" (an input's wall seconds)."""
    if not records:
        return {}
    names = sorted({name for record in records for name in record["stages"]},
                   key=lambda name: (name.split(" ")[0] in ("encode", "commit"), name))
    table = {}
    for name in names:
        values = [record["stages"].get(name, 0.0) for record in records]
        table[name] = {"median_s": statistics.median(values), "total_s": sum(values)}
    other = [record["seconds"] - sum(record["stages"].values()) for record in records]
    table["other"] = {"median_s": statistics.median(other), "total_s": sum(other)}
    table["input"] = {"median_s": statistics.median(r["seconds"] for r in records),
                      "total_s": sum(r["seconds"] for r in records)}
    return table


def print_report(record: dict) -> None:
    info, runs = record["machine"], record["runs"]
    mp = record["megapixels_per_file"]
    print(f"\nspherejax correct vs numpy + colour-science: {record['files']} files of "
          f"{record['size']} x {record['size']} x 16 uint16 ({mp:.3f} MP each, "
          f"{record['files'] * mp:.1f} MP), {record['distinct']} distinct simulated captures, "
          f"{record.get('output_format', 'exr').upper()} outputs")
    print(f"machine: {info['cpu_model']}, {info['nproc']} CPUs, jax {info['jax']}, numpy {info['numpy']}, "
          f"colour-science {info['colour-science']}, OpenImageIO {oiio.__version__}")
    a = record["agreement"]
    print(f"agreement on the first capture over {a['valid_pixels']} valid pixels ({a['bad_pixels']} bad in "
          f"both): reflectance max |diff| {a['reflectance_max_abs_diff']:.2e}, Lab {a['lab_max_abs_diff']:.2e}, "
          f"quality identical, preview max {a['preview_max_level_diff']} level(s) in "
          f"{a['preview_pixels_differing']} pixels")
    if "half_float" in a:
        h = a["half_float"]
        print(f"--reflectance-type half on this capture: spectral error max {h['max_abs_spectral_error']:.2e} "
              f"(99th percentile {h['p99_abs_spectral_error']:.2e}), ΔE00 max {h['max_delta_e00']:.3f}, "
              f"99th percentile {h['p99_delta_e00']:.3f}, mean {h['mean_delta_e00']:.4f} over {h['valid_pixels']} pixels")
    print(f"inputs {record['input_bytes_per_file'] / 2**20:.1f} MiB/file, outputs "
          f"{a['output_bytes_per_file'] / 2**20:.1f} MiB/file")

    header = (f"{'run':<36}{'wall s':>9}{'files/s':>9}{'MP/s':>8}{'vs ref':>8}{'1st file s':>11}"
              f"{'median file s':>14}{'cores':>7}{'sync after s':>13}{'other load':>11}")
    print("\n" + header)
    print("-" * len(header))

    def row(label, r, wall, files_per_s, mp_per_s, ratio):
        cores = "" if r.get("cpu_cores_busy") is None else f"{r['cpu_cores_busy']:.2f}"
        load = "" if r.get("other_processes_cpu_fraction") is None else f"{100 * r['other_processes_cpu_fraction']:.0f}%"
        print(f"{label:<36}{wall:>9.2f}{files_per_s:>9.2f}{mp_per_s:>8.2f}{ratio:>7.2f}x"
              f"{r['first_file_s']:>11.2f}{r['median_file_s']:>14.3f}{cores:>7}{r['sync_after_s']:>13.2f}{load:>11}")

    for kind, label in RUN_LABELS.items():
        if kind not in runs:
            continue
        r = runs[kind]
        if kind == "spherejax-nofsync":
            print("-" * len(header))
        row(label, r, r["wall_s"], r["files_per_s"], r["mp_per_s"], r["speed_vs_reference"])
        if kind.endswith("workers"):
            s = r["with_startup"]
            print(f"{'  + dask start-up ' + format(r['startup_s'], '.2f') + ' s':<36}{s['wall_s']:>9.2f}"
                  f"{s['files_per_s']:>9.2f}{s['mp_per_s']:>8.2f}{s['speed_vs_reference']:>7.2f}x")
    print("-" * len(header))
    print("vs ref = reference wall / this wall (above 1: faster). 1st file includes spherejax's JAX compile "
          "(workers: the slower of the two workers' first files). cores = CPU seconds / wall. sync after = an "
          "os.sync() right after the run (outputs left in the page cache). other load = CPU share other "
          "processes took.")
    sj, derived = runs["spherejax"], record["derived"]
    print(f"fsync: spherejax in-process spent {sj['fsync_s']:.2f} s in {sj['fsync_calls']} os.fsync calls, "
          f"{100 * derived['fsync_time_share_in_process']:.1f}% of its wall time", end="")
    if "fsync_share_in_process_vs_noop_run" in derived:
        loads = [runs[k].get("other_processes_cpu_fraction") for k in ("spherejax", "spherejax-nofsync")]
        noise = "" if None in loads else f" (other load {100 * loads[0]:.0f}% vs {100 * loads[1]:.0f}%)"
        print(f"; diagnostic run with os.fsync a no-op: {100 * derived['fsync_share_in_process_vs_noop_run']:.0f}% "
              f"less wall time{noise}", end="")
    print()
    stages = derived.get("stages") or {}
    if stages:
        wall = sj["wall_s"]
        print(f"\nspherejax in-process, where an input's time goes ({record['files']} inputs, "
              f"{sj['cpu_cores_busy']:.2f} cores busy; inputs overlap, so the totals add up to more than the wall "
              f"{wall:.2f} s):")
        print(f"{'stage':<30}{'median s/input':>15}{'total s':>10}{'share of wall':>15}")
        for name, t in stages.items():
            print(f"{name:<30}{t['median_s']:>15.3f}{t['total_s']:>10.2f}{100 * t['total_s'] / wall:>14.0f}%")
        print(f"(fsync, inside the commits: {sj['fsync_s'] / record['files']:.3f} s per input)")
    if "spherejax_vs_raw_floor" in derived:
        print(f"spherejax in-process / raw floor: {derived['spherejax_vs_raw_floor']:.2f}x the raw floor's wall time", end="")
        if "workers_vs_raw_floor" in derived:
            print(f"; 2 dask workers {derived['workers_vs_raw_floor']:.2f}x", end="")
        print()
    if "files_per_s_vs_before" in derived:
        print(f"spherejax in-process / before: {derived['files_per_s_vs_before']:.2f}x the files per second of "
              f"{record['compare_with']}")
    for kind in ("workers", "before-workers"):
        if f"{kind}_vs_in_process" in derived:
            print(f"{RUN_LABELS[kind]}: {derived[f'{kind}_vs_in_process']:.2f}x the files per second of the same code "
                  f"in-process (without the dask start-up)")
    if "spherejax_vs_raw_floor_direct" in derived:
        print(f"spherejax in-process / raw floor written past the page cache: {derived['spherejax_vs_raw_floor_direct']:.2f}x")
    if "all_wall_s" in runs.get("raw-floor", {}):
        print(f"raw floor: the median of three runs, {', '.join(f'{s:.2f}' for s in runs['raw-floor']['all_wall_s'])} s")
    for kind in ("floor", "floor-fsync", "raw-floor", "raw-floor-direct"):
        if kind in runs:
            steps = ", ".join(f"{step} {t:.3f}" for step, t in runs[kind]["median_step_s"].items())
            print(f"{RUN_LABELS[kind]}, median s per file: {steps}")
    loads = [r["other_processes_cpu_fraction"] for r in runs.values() if r.get("other_processes_cpu_fraction") is not None]
    if loads and max(loads) > 0.05:
        print("warning: other processes competed for the CPUs during some runs; those timings are pessimistic")
    s = record["setup"]
    print(f"setup (not timed above): simulate {s['simulate_s']:.1f} s ({s['simulated_frames']} frames), "
          f"calibrate {s['calibrate_s']:.1f} s, write inputs {s['write_inputs_s']:.1f} s, "
          f"agreement check {s['check_s']:.1f} s")


# --------------------------------------------------------------------------------------------


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--files", type=int, default=200, help="number of input captures (default 200)")
    parser.add_argument("--size", type=int, default=1024, help="capture height = width in pixels (default 1024)")
    parser.add_argument("--distinct", type=int, default=8,
                        help="distinct captures rendered by the simulator; the inputs are variations of them (default 8)")
    parser.add_argument("--workdir", metavar="DIR",
                        help="folder (file system) to work in; a temporary folder is made in it (default: the system's)")
    parser.add_argument("--keep", action="store_true", help="keep the work folder (inputs, calibration, check outputs)")
    parser.add_argument("--json", metavar="PATH", help="also write the results here")
    parser.add_argument("--format", choices=archive.OUTPUT_FORMATS, default="exr",
                        help="the outputs' format for every run, spherejax's --format (default exr)")
    parser.add_argument("--skip-workers", action="store_true", help="leave out the 2-worker dask run")
    parser.add_argument("--skip-diagnostic", action="store_true", help="leave out the fsync no-op diagnostic run")
    parser.add_argument("--exr-compression", choices=io.EXR_COMPRESSIONS, default=None,
                        help="spherejax's --exr-compression, also the reference's and the I/O floor's (default: "
                             "spherejax's default; the --compare-with run keeps its own default unless this is given)")
    parser.add_argument("--reflectance-type", choices=("float", "half"), default="float",  # io.EXR_PIXEL_TYPES
                        help="spherejax's --reflectance-type (EXR only; the reference, the floors and the "
                             "--compare-with run write float32)")
    parser.add_argument("--compare-with", metavar="TREE",
                        help="a checkout of spherejax (its fused kernel built in place) whose `correct` is timed in "
                             "the same run as \"before\", with its own defaults: today's code against the code it replaces")
    parser.add_argument("--child", help=argparse.SUPPRESS)  # internal: one timed run
    parser.add_argument("--job", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child is None:
        if args.size < 224:
            parser.error("--size must be at least 224: the simulator's 12 x 12 target chart takes 192 columns")
        if args.files < 2:
            parser.error("--files must be at least 2")
        if args.distinct < 1:
            parser.error("--distinct must be at least 1")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.child is not None:
        record = child_run(args.child, json.loads(args.job))
        pathlib.Path(os.environ["BENCH_ARCHIVE_RESULT"]).write_text(json.dumps(record))
        return 0

    info = machine_info()
    workdir = pathlib.Path(tempfile.mkdtemp(prefix="bench_archive-", dir=args.workdir)).resolve()
    print(f"work folder: {workdir}", flush=True)
    try:
        setup = {}
        print(f"simulating {args.distinct} distinct {args.size} x {args.size} captures and calibrating ...", flush=True)
        captures, calibration_path, timings = simulate_captures(workdir, args.size, args.distinct, SEED)
        setup.update(timings)
        start = time.perf_counter()
        inputs_dir = workdir / "inputs"
        inputs = write_inputs(inputs_dir, captures, args.files, SEED)
        setup["write_inputs_s"] = time.perf_counter() - start
        del captures
        shutil.rmtree(workdir / "session")  # only the calibration and the inputs are needed now

        print("checking that the reference agrees with spherejax on the first capture ...", flush=True)
        start = time.perf_counter()
        exr_compression = args.exr_compression or io.DEFAULT_EXR_COMPRESSION
        agreement, reference_stem = check_agreement(inputs[0], calibration_path, workdir / "check", args.format,
                                                    exr_compression)
        # What the raw floor writes: one input's outputs as the timed spherejax run writes them.
        spherejax_options = {"exr_compression": exr_compression} if args.format == "exr" else {}
        if args.reflectance_type != "float":
            spherejax_options["reflectance_type"] = args.reflectance_type
        archive.run_batch([inputs[0]], workdir / "floor-bytes", calibration_path, output_format=args.format,
                          **spherejax_options)
        setup["check_s"] = time.perf_counter() - start
        if args.format == "exr":
            agreement["half_float"] = half_float_accuracy(workdir / "check" / "spherejax" / inputs[0].stem)
        need = int(1.2 * args.files * agreement["output_bytes_per_file"])
        free = shutil.disk_usage(workdir).free
        if need > free:
            raise SystemExit(f"{workdir}: a run's outputs need about {need / 1e9:.1f} GB, {free / 1e9:.1f} GB free")

        job = {
            "inputs_dir": str(inputs_dir), "calibration": str(calibration_path),
            "floor_stem": str(reference_stem), "jax_cache": str(workdir / "jax-cache"),
            "spherejax_stem": str(workdir / "floor-bytes" / inputs[0].stem),
            "output_format": args.format, "exr_compression": exr_compression,
            "spherejax_options": spherejax_options,
            "before_options": {"exr_compression": args.exr_compression} if args.exr_compression else {},
            "compare_with": os.path.abspath(args.compare_with) if args.compare_with else None,
        }
        kinds = [k for k in RUN_LABELS
                 if not (args.skip_workers and k == "workers") and not (args.skip_diagnostic and k == "spherejax-nofsync")
                 and not (k.startswith("before") and not args.compare_with)
                 and not (args.skip_workers and k == "before-workers")]
        runs = {}
        # The raw floor three times, first, after spherejax's in-process run and last: on a
        # virtual machine's disk the same bytes took from 0.04 to 0.34 s a file to write from one
        # run to the next (writeback of the runs before, the host's cache), so one measurement
        # made the ratios to it swing by half. The median of the three is the floor.
        kinds.remove("raw-floor")
        kinds.insert(0, "raw-floor")
        kinds.insert(kinds.index("spherejax") + 1, "raw-floor")
        kinds.append("raw-floor")
        # Once, after spherejax's run: the same bytes written as spherejax writes its large
        # outputs, past the page cache (where the kernel's copy cost the plain floor most of its time).
        kinds.remove("raw-floor-direct")
        kinds.insert(kinds.index("spherejax") + 2, "raw-floor-direct")
        floors = []
        for kind in kinds:
            print(f"timing: {RUN_LABELS[kind]} ...", flush=True)
            record = run_in_child(kind, job, workdir)
            print(f"  {record['wall_s']:.2f} s", flush=True)
            if kind == "raw-floor":
                floors.append(record)
            else:
                runs[kind] = record
        floors.sort(key=lambda record: record["wall_s"])
        runs["raw-floor"] = dict(floors[1], all_wall_s=[record["wall_s"] for record in floors])
        megapixels = args.size * args.size / 1e6
        derived = summarise(runs, args.files, megapixels)
        record = {
            "benchmark": "bench_archive",
            "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "files": args.files, "size": args.size, "bands": len(BAND_NAMES), "distinct": args.distinct,
            "output_format": args.format, "exr_compression": exr_compression,
            "reflectance_type": args.reflectance_type, "compare_with": job["compare_with"],
            "megapixels_per_file": megapixels,
            "input_bytes_per_file": sum(p.stat().st_size for p in inputs) / len(inputs),
            "input_noise_dn": INPUT_NOISE_DN, "seed": SEED,
            "setup": setup, "agreement": agreement, "runs": runs, "derived": derived,
            "openimageio": oiio.__version__, "machine": info, "argv": sys.argv,
        }
        print_report(record)
        if args.json:
            write_record(args.json, record)
    finally:
        if args.keep:
            print(f"kept {workdir}")
        else:
            shutil.rmtree(workdir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
