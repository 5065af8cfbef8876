"""What the batch-correction tests share (tests/test_archive.py, tests/robustness/): small
16-band frames and calibrations, running the command line in this process or in a child, and
reading what a batch wrote."""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import numpy as np
import OpenImageIO as oiio

import spherejax
from spherejax import archive, cli
from spherejax.grid import BAND_CENTRES_NM

from .helpers import no_compilation_cache_writes, wait_until  # noqa: F401 (wait_until: re-exported)

H, W, B = 40, 48, 16
BANDS = [int(b) for b in BAND_CENTRES_NM]
NAMES = [f"{b}nm" for b in BANDS]
KINDS = archive.OUTPUT_KINDS


def make_calibration(rng, *, instrument_id="sphere-1", bands=BANDS):
    nb = len(bands)
    dark = rng.uniform(90, 110, (H, W, nb)).astype(np.float32)
    white = rng.uniform(9000, 11000, (H, W, nb)).astype(np.float32)
    patch = np.zeros((H, W), dtype=bool)
    patch[2:8, 2:8] = True
    wiener = (rng.uniform(0, 1, (31, nb)) / nb).astype(np.float32)
    calibration = spherejax.Calibration(
        dark=dark, white=white, patch=patch, coeffs=np.asarray(spherejax.identity_coeffs(nb)),
        wiener=wiener, saturation=16383.0,
    )
    return calibration, bands, instrument_id


def frame(rng, shape=(H, W, B)):
    raw = rng.integers(2000, 9000, shape).astype(np.uint16)
    raw[0, 0, 0] = 16383  # one saturated pixel: NaN in the outputs, magenta in the preview
    return raw






def run(argv, capsys):
    status = cli.main(argv)
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def outputs_of(out: pathlib.Path) -> dict[str, bytes]:
    """Every output file under OUT (manifest and lock left out) -> bytes."""
    skip = {archive.MANIFEST_NAME, archive.LOCK_NAME}
    return {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file() and p.name not in skip}


def read_exr(path):
    """(pixels (H, W, C) float32, channel names, attributes) through OpenImageIO."""
    image = oiio.ImageInput.open(str(path))
    spec = image.spec()
    pixels = image.read_image(oiio.FLOAT)
    attributes = {a.name: a.value for a in spec.extra_attribs}
    names = list(spec.channelnames)
    image.close()
    return pixels, names, attributes


def spec_alpha(path):
    image = oiio.ImageInput.open(str(path))
    alpha = image.spec().alpha_channel
    image.close()
    return alpha


def manifest_records(out):
    return [json.loads(line) for line in (out / archive.MANIFEST_NAME).read_text().splitlines() if line.strip()]


def start_correct(argv, *, may_be_killed: bool = True, quiet: bool = False, env: dict | None = None) -> subprocess.Popen:
    """`spherejax correct` in a child process (`spherejax -q correct` if `quiet`: errors and
    the stop line only), stderr piped. One that may be killed (SIGKILL) reads the shared
    compilation cache but writes none (`helpers.no_compilation_cache_writes`); an uninterrupted
    reference run, or one only ever stopped by SIGINT / SIGTERM, fills it for the others. `env`:
    variables added to the child's environment."""
    command = [sys.executable, "-m", "spherejax.cli", *(["-q"] if quiet else []), "correct", *map(str, argv)]
    env = {**os.environ, "JAX_PLATFORMS": "cpu", **(env or {})}
    if may_be_killed:
        env = no_compilation_cache_writes(env)
    return subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def holds_lock(process: subprocess.Popen, out: pathlib.Path):
    """True once `process` holds OUT's lock (a killed run's lock file stays behind: check the pid)."""

    def condition():
        try:
            return json.loads((out / archive.LOCK_NAME).read_text().partition("\n")[0])["pid"] == process.pid  # its first line
        except (OSError, ValueError, KeyError):
            return False

    return condition
