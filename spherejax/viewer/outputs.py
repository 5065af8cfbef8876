"""The files the viewer writes: its regions as `spherejax measure` writes them (CSV and
CGATS.17, through `spherejax.measurement_files`: the same columns, keywords and number
formatting), and the window's screenshot (`spherejax view --screenshot`), a PNG marked as
spherejax's by its tEXt chunk Software = `SCREENSHOT_SOFTWARE`.

A file at an output's name is replaced only when it proves spherejax wrote it: a CSV or CGATS
file by its first bytes (`measurement_files.not_a_measurement_file`: an earlier `measure` or
export), a screenshot by its mark; a user's own file, a folder or a link there is refused in one
line and left as it is. An input of the
capture (its reflectance, Lab, quality mask or preview, the raw cube, the calibration) is never
an output. Each set of files is put in place together, whole or not at all
(`measurement_files.write_files`).
"""

from __future__ import annotations

import datetime
import pathlib
from collections.abc import Sequence

from .. import measurement_files
from ..io import ownership
from ..io.ownership import refuse_overlaps
from ..measurement_files import RegionResult


#: The tEXt Software of a screenshot spherejax wrote (the one PNG at that name it may replace).
SCREENSHOT_SOFTWARE = "spherejax view"


def not_a_screenshot(path) -> str | None:
    """None if `path` is a PNG spherejax view wrote (its mark), else why it is not."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            software = image.text.get("Software") if image.format == "PNG" else None
    except (OSError, UnidentifiedImageError, ValueError):
        return "a file that is not a PNG spherejax view wrote"
    return None if software == SCREENSHOT_SOFTWARE else "a file spherejax view did not write"


def write_screenshot(path, png: bytes, *, inputs: dict) -> pathlib.Path:
    """Put the screenshot's PNG bytes at `path`, whole (`check_screenshot_path` first)."""
    check_screenshot_path(path, inputs=inputs)
    measurement_files.write_files({pathlib.Path(path): png})
    return pathlib.Path(path)


def check_screenshot_path(path, *, inputs: dict) -> None:
    """Refuse, in one line, a screenshot path that is not a .png, is an input, or is taken by a
    file spherejax view did not write (SpherejaxFileError; ValueError for the name)."""
    path = pathlib.Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"--screenshot {str(path)!r}: expected a file name ending in .png")
    refuse_overlaps({"--screenshot FILE": path}, {words: p for words, p in inputs.items() if p is not None})
    ownership.refuse_in_the_way({"--screenshot FILE": path}, replaceable=not_a_screenshot,
                                expected="--screenshot FILE a new file, or a screenshot spherejax view wrote, to replace")


def write_region_files(results: Sequence[RegionResult], *, inputs: dict, input_path, instrument_id: str | None,
                       csv_path=None, cgats_path=None) -> list[pathlib.Path]:
    """Write the regions' CSV and/or CGATS.17 files; returns the paths written.

    Args:
      results: the regions, in order, measured under one illuminant.
      inputs: {words: path} of the files the capture was read from (never overwritten).
      input_path: what the files name as measured (the reflectance file, or the raw cube).
      instrument_id: the calibration's, or None.
      csv_path, cgats_path: where to write; at least one.

    Raises:
      ValueError: no region, or no path. SpherejaxFileError: an output's name is taken by a file
        spherejax did not write, or is one of `inputs`; a file could not be written.
    """
    if not results:
        raise ValueError("no region to export: draw a rectangle or polygon in the regions layer first")
    outputs = {label: pathlib.Path(path) for label, path in (("CSV", csv_path), ("CGATS", cgats_path)) if path is not None}
    if not outputs:
        raise ValueError("no file to export to: expected a CSV or CGATS path")
    refuse_overlaps(outputs, {words: path for words, path in inputs.items() if path is not None})
    kinds = {"CSV": "csv", "CGATS": "cgats"}
    for label, path in outputs.items():
        ownership.refuse_in_the_way(
            {label: path}, replaceable=lambda found, kind=kinds[label]: measurement_files.not_a_measurement_file(found, kind),
            expected=f"{label} a new file, or one spherejax measure wrote, to replace",
        )
    files = {}
    if "CSV" in outputs:
        files[outputs["CSV"]] = measurement_files.csv_text(results).encode()
    if "CGATS" in outputs:
        created = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        files[outputs["CGATS"]] = measurement_files.cgats_text(
            results, input_path=input_path, instrument_id=instrument_id, created=created,
        ).encode()
    measurement_files.write_files(files)
    return list(files)


__all__ = ["SCREENSHOT_SOFTWARE", "check_screenshot_path", "not_a_screenshot", "write_region_files", "write_screenshot"]
