"""Correct one image in row strips, so that memory stays bounded whatever the image's size.

    p   = white-patch ratio (Eq. 14-15) from the patch's bounding box only (rows r0:r1 of the
          input, the calibration cropped to the box: `io.CalibrationFile.patch_calibration`)
    for each strip of rows:
          raw rows (`io.CubeReader.read_rows`), dark and white rows (`io.CalibrationFile.rows`)
          -> `pipeline.correct(rows, calibration_rows, p=p)` -> reflectance, Lab, quality rows

Both steps are the jitted functions `correct(raw, calibration)` runs on a whole image, on the
same values, so a strip result is bit for bit the whole-image result (tested at several strip
heights). A calibration with band maps (`Calibration.band_transforms`) reads each strip's rows
with the native rows around them its registered pixels come from (`band_resampling.read_box`),
and keeps the strip's own: the whole-image result to float rounding (the maps are applied in the
strip's own coordinates). Every strip has the same height (the last is padded with rows that are discarded), so
an image compiles once. Memory: about `BYTES_PER_PIXEL` bytes per pixel of a strip, plus the
calibration's patch mask (H x W bytes) and what the process holds anyway.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Iterator
from typing import TYPE_CHECKING

import numpy as np

from . import band_resampling
from .pipeline import correct, patch_ratio, plan

if TYPE_CHECKING:  # for the annotations only: a workflow takes the readers it is given
    from . import io

#: Working memory per pixel of a strip, measured at 16 bands (raw, dark and white on both the
#: numpy and the XLA side, the flat field, the outputs and their float64 preview): a bound for
#: choosing strip heights, not an exact figure.
BYTES_PER_PIXEL = 1500
#: Default memory for one strip's working set.
STRIP_BYTES = 256 << 20
#: Strip heights are multiples of this when larger: OpenEXR compresses 16 scanlines per chunk
#: and TIFF strips are commonly 8, 16 or 32 rows, so reads and writes stay chunk-aligned.
ROW_QUANTUM = 16


def strip_height(height: int, width: int, bands: int, strip_bytes: int = STRIP_BYTES) -> int:
    """Rows per strip so that a strip's working set stays near `strip_bytes`; at least 1, at most
    `height`. Among the heights within that bound (multiples of ROW_QUANTUM when larger), the one
    that pads the last strip least: 1024 rows go in 8 strips of 128, not 7 of 160 with 96 rows of
    padding computed for nothing."""
    per_row = max(1, width * BYTES_PER_PIXEL * max(bands, 16) // 16)
    most = max(1, strip_bytes // per_row)
    if most >= height:
        return int(height)
    if most <= ROW_QUANTUM:
        return int(most)
    most -= most % ROW_QUANTUM
    fewest = -(-height // most)
    candidates = []
    for strips in range(fewest, fewest + 4):
        rows = -(-height // strips)
        rows += -rows % ROW_QUANTUM  # up to a multiple of the quantum
        if rows <= most:
            candidates.append((rows * -(-height // rows) - height, -rows))
    return int(-min(candidates)[1])


def _padded(rows: np.ndarray, height: int) -> np.ndarray:
    """`rows` (n, W, C) padded with zero rows to (height, W, C)."""
    if len(rows) == height:
        return rows
    pad = np.zeros((height - len(rows), *rows.shape[1:]), dtype=rows.dtype)
    return np.concatenate([rows, pad])


def _correct_rows(cube: io.CubeReader, calibration: io.CalibrationFile, row0: int, row1: int, p, *, height: int):
    """Rows row0:row1 of the image corrected with the whole image's p, padded to `height` rows
    (every strip one shape: one plan, one compilation). The calibration file keeps the rows'
    `Calibration` (`io.CalibrationFile.rows`), and with it the plan, for the next input."""
    raw = _padded(cube.read_rows(row0, row1), height)
    return correct(raw, calibration.rows(row0, row1, padded_to=height), p=p)


def _rows_by_the_whole_plan(cube: io.CubeReader, calibration: io.CalibrationFile, row0: int, row1: int, p):
    """Rows row0:row1 corrected by the plan of the whole image (`spherejax._engine.plan.Plan.rows`):
    one plan for every strip of every input of a calibration held in memory."""
    raw = np.ascontiguousarray(cube.read_rows(row0, row1))
    return plan(calibration.calibration(), (*calibration.image_shape, calibration.bands), dtype=raw.dtype).rows(raw, row0, p)


def _registered_rows(cube: io.CubeReader, calibration: io.CalibrationFile, row0: int, row1: int, p):
    """Rows row0:row1 of an image whose calibration has band maps: the native rows they are
    interpolated from (`band_resampling.read_box`, the strip grown by the maps' reach) corrected
    with the calibration's same rows, and the strip's own rows kept."""
    height, width = calibration.image_shape
    n0, n1, _, _ = band_resampling.read_box((row0, row1, 0, width), calibration.band_transforms, (height, width))
    raw = np.ascontiguousarray(cube.read_rows(n0, n1))
    result = correct(raw, calibration.rows(n0, n1), p=p)
    keep = slice(row0 - n0, row1 - n0)
    return dataclasses.replace(result, reflectance=result.reflectance[keep], lab=result.lab[keep],
                               quality=result.quality[keep])


def image_patch_ratio(cube: io.CubeReader, calibration: io.CalibrationFile):
    """The white-patch ratio p (B,) of a whole image, reading only the rows of the patch's pixels
    (and, with band maps, of the pixels around them its registered pixels come from)."""
    r0, r1, c0, c1 = calibration.patch_read_box
    box = cube.read_rows(r0, r1)[:, c0:c1]
    return patch_ratio(box, calibration.patch_calibration)


def correct_strips(
    cube: io.CubeReader, calibration: io.CalibrationFile, *, rows_per_strip: int | None = None
) -> Iterator[tuple[int, dict[str, np.ndarray]]]:
    """Correct an image strip by strip.

    Args:
      cube: the input, (H, W, B) (the calibration's shape).
      calibration: the open calibration file.
      rows_per_strip: strip height; None = `strip_height` of the image.

    Yields:
      (row0, arrays) per strip in order, arrays = {"reflectance": (n, W, 31) float32,
      "lab": (n, W, 3) float32, "quality": (n, W) uint8} for rows row0:row0 + n.

    Raises:
      ValueError: a cube whose shape is not the calibration's; SpherejaxFileError from reading.
    """
    height, width, bands = cube.shape
    if (height, width) != tuple(calibration.image_shape) or bands != calibration.bands:
        raise ValueError(
            f"cube: expected shape {(*calibration.image_shape, calibration.bands)} (the "
            f"calibration's H, W, B), got {cube.shape}"
        )
    step = rows_per_strip or strip_height(height, width, bands)
    if step < 1:
        raise ValueError(f"rows_per_strip: expected at least 1, got {step}")
    step = min(step, height)
    if step == height and calibration.in_memory:
        # One strip of a calibration held in memory: the whole-frame call, which the fused kernel
        # runs on the frame where it lies (the plan's direct route), p from the patch's box as
        # `image_patch_ratio` takes it, so the same numbers.
        strips = [(0, height, lambda: correct(cube.read_rows(0, height), calibration.calibration()))]
    else:
        p = image_patch_ratio(cube, calibration)
        # Every strip of every input through the whole calibration's one plan (`Plan.rows`), or for a
        # calibration read from disk by rows, each strip's rows padded to one shape.
        rows_of = _rows_by_the_whole_plan if calibration.in_memory else functools.partial(_correct_rows, height=step)
        if calibration.band_transforms is not None:
            rows_of = _registered_rows
        strips = [
            (row0, min(row0 + step, height), functools.partial(rows_of, cube, calibration, row0, min(row0 + step, height), p))
            for row0 in range(0, height, step)
        ]
    for row0, row1, correct_strip in strips:
        result = correct_strip()
        rows = row1 - row0
        yield row0, {
            "reflectance": np.asarray(result.reflectance[:rows], dtype=np.float32),
            "lab": np.asarray(result.lab[:rows], dtype=np.float32),
            "quality": np.asarray(result.quality[:rows], dtype=np.uint8),
        }


__all__ = ["BYTES_PER_PIXEL", "STRIP_BYTES", "strip_height", "image_patch_ratio", "correct_strips"]
