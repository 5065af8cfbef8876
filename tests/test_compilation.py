"""Compilation: `correct` compiles once per image shape and dtype, never per image, and strips of
one height share one executable (docs/design.md, "never compile per file")."""

from __future__ import annotations

import contextlib

import jax
import numpy as np
import pytest

import spherejax
from spherejax import io, stripwise

BACKEND_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"


@contextlib.contextmanager
def count_compilations():
    """Count XLA backend compilations inside the block (jax.monitoring's compile event)."""
    counter = {"n": 0}

    def listener(event, duration_s, **kwargs):
        if event == BACKEND_COMPILE_EVENT:
            counter["n"] += 1

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield counter
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def make_calibration(rng, shape):
    height, width, bands = shape
    dark = rng.uniform(90, 110, shape).astype(np.float32)
    white = rng.uniform(9000, 11000, shape).astype(np.float32)
    patch = np.zeros((height, width), bool)
    patch[2:6, 3:9] = True
    coeffs = np.tile(np.asarray([0.01, 0.97, 0.02, -0.01], np.float32), (bands, 1))
    wiener = (rng.uniform(0, 1, (31, bands)) / bands).astype(np.float32)
    return spherejax.Calibration(dark=dark, white=white, patch=patch, coeffs=coeffs, wiener=wiener, saturation=16383.0)


def test_counter_sees_a_compilation():
    with count_compilations() as compiled:
        jax.jit(lambda x: x * 3.25 + 1.5)(np.arange(7.0)).block_until_ready()
    assert compiled["n"] >= 1


def test_second_image_of_the_same_shape_does_not_compile(rng):
    shape = (24, 28, 16)
    calibration = make_calibration(rng, shape)
    first = rng.integers(0, 16000, shape).astype(np.uint16)
    spherejax.correct(first, calibration).reflectance.block_until_ready()
    with count_compilations() as compiled:
        for _ in range(3):
            raw = rng.integers(0, 16000, shape).astype(np.uint16)
            spherejax.correct(raw, calibration).lab.block_until_ready()
        # Another calibration of the same shapes (a new session) reuses the executable too.
        spherejax.correct(first, make_calibration(rng, shape)).lab.block_until_ready()
    assert compiled["n"] == 0


def test_another_shape_compiles_once(rng):
    shape = (20, 26, 16)
    calibration = make_calibration(rng, shape)
    with count_compilations() as compiled:
        for _ in range(3):
            spherejax.correct(rng.integers(0, 16000, shape).astype(np.uint16), calibration).lab.block_until_ready()
    # Once: whole frames are one program (the patch's box, its ratio and every pixel); it is not
    # compiled again for images 2 and 3. Off the CPU the calibration's plan is prepared by one
    # program more, on its device (`spherejax._engine.plan._prepare`); on the CPU in NumPy.
    assert compiled["n"] == (1 if jax.default_backend() == "cpu" else 2)


def test_strips_of_an_image_compile_once(tmp_path, rng):
    """Every strip has one height (the last is padded): a tall image compiles as one strip does."""
    shape = (70, 20, 16)
    calibration = make_calibration(rng, shape)
    io.save_calibration(tmp_path / "cal.h5", calibration, instrument_id="x", band_centres_nm=list(range(400, 701, 20)))
    for k in range(2):
        io.write_frame(tmp_path / f"{k}.tif", rng.integers(0, 16000, shape).astype(np.uint16))
    with io.open_calibration(tmp_path / "cal.h5") as opened:
        with io.open_cube(tmp_path / "0.tif", expected_shape=shape) as cube:
            list(stripwise.correct_strips(cube, opened, rows_per_strip=8))  # 9 strips, the last padded
        with count_compilations() as compiled:
            with io.open_cube(tmp_path / "1.tif", expected_shape=shape) as cube:
                strips = list(stripwise.correct_strips(cube, opened, rows_per_strip=8))
    assert len(strips) == 9 and compiled["n"] == 0


@pytest.fixture
def rng():
    return np.random.default_rng(11)
