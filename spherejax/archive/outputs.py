"""Outputs: their names per format, the writers of each format behind one interface, the output
folders, and the clean-up of an input's outputs (package docstring, "Output names", "Safety")."""

from __future__ import annotations

import collections
import contextlib
import functools
import os
import threading
import pathlib
from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np

from .. import interrupt, io
from ..grid import WAVELENGTHS_NM
from ..io import envi, spectral_layout
from . import stage_times
from .discovery import InputSpec

#: The outputs of one input in each output format (`--format`): "<name>.<kind>" in OUT.
OUTPUT_KINDS_BY_FORMAT = {
    "exr": ("reflectance.exr", "lab.exr", "quality.png", "preview.png"),
    "envi": ("reflectance.img", "reflectance.hdr", "lab.img", "lab.hdr", "quality.png", "preview.png"),
}
OUTPUT_FORMATS = tuple(OUTPUT_KINDS_BY_FORMAT)
#: The outputs of the default format, EXR.
OUTPUT_KINDS = OUTPUT_KINDS_BY_FORMAT["exr"]
#: Every kind of output any format writes (what removing an input's outputs looks for).
ALL_OUTPUT_KINDS = tuple(dict.fromkeys(kind for kinds in OUTPUT_KINDS_BY_FORMAT.values() for kind in kinds))

#: Preview colour of pixels without reflectance (sRGB 8-bit): magenta, never a real colour of a
#: flat-fielded reflectance preview, so bad pixels stand out.
PREVIEW_BAD_PIXEL = (255, 0, 255)


def output_settings(calibration: io.CalibrationFile, output_format: str, exr_compression: str,
                    reflectance_type: str = "float") -> dict:
    """The options that shape an input's outputs beyond the input and the calibration: the Lab
    illuminant in effect (the calibration's or --illuminant), the format and, for EXR, its
    compression and the reflectance's pixel type. Each manifest record carries them and
    `--resume` redoes an input whose record holds other ones (`is_done`)."""
    exr = output_format == "exr"
    return {
        "illuminant": calibration.patch_calibration.illuminant,
        "format": output_format,
        "exr_compression": exr_compression if exr else None,
        "reflectance_type": reflectance_type if exr else None,
    }


@functools.lru_cache(maxsize=1)
def _reflectance_to_linear_srgb() -> np.ndarray:
    """(31, 3) float32: ASTM E308 D65 weights (Y = 1 for the perfect diffuser) times the IEC
    61966-2-1 XYZ -> linear sRGB matrix (colour-science), folded in float64 once."""
    import colour

    from ..colorimetry import tristimulus_weights

    matrix = np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB, dtype=np.float64)
    return ((np.asarray(tristimulus_weights("D65"), dtype=np.float64) / 100.0) @ matrix.T).astype(np.float32)


def srgb_preview(reflectance: np.ndarray) -> np.ndarray:
    """8-bit sRGB of a reflectance cube (H, W, 31) under D65 -> (H, W, 3) uint8.

    XYZ by ASTM E308 (Y = 1 for the perfect diffuser), the IEC 61966-2-1 matrix and encoding,
    clipped to [0, 1] and rounded; non-finite pixels become PREVIEW_BAD_PIXEL. The same as
    colour-science's XYZ -> sRGB path in float64 (tested against it: a level apart in about one
    value in 100,000, where a value lies within float32 rounding of a level's edge), in
    float32 with the two matrices folded into one: 84 -> about 35 ms a megapixel, a tenth of a
    batch's time per input on 2 cores (benchmarks/README.md, bench_archive.py's stages).
    """
    linear = np.asarray(reflectance, dtype=np.float32) @ _reflectance_to_linear_srgb()
    good = np.all(np.isfinite(linear), axis=-1)
    linear[~good] = 0.0
    np.clip(linear, 0.0, 1.0, out=linear)
    # IEC 61966-2-1's encoding (colour.models.eotf_inverse_sRGB), in place in float32.
    dark = linear <= np.float32(0.0031308)
    encoded = np.power(linear, np.float32(1 / 2.4))
    encoded *= np.float32(1.055)
    encoded -= np.float32(0.055)
    np.copyto(encoded, linear * np.float32(12.92), where=dark)
    encoded *= np.float32(255.0)
    rgb = np.rint(encoded).astype(np.uint8)
    rgb[~good] = PREVIEW_BAD_PIXEL
    return rgb


# ----------------------------------------------------------------------------------- writers


class OutputWriter(Protocol):
    """What writes one output of an input, in any format: rows in order, under temporary names,
    put in place by `commit` (the `atomic_files` rules); leaving the `with` block uncommitted leaves
    nothing."""

    def write_rows(self, row0: int, pixels: np.ndarray) -> None: ...

    def finish(self) -> dict[pathlib.Path, str]:
        """Finish the output's files (fsynced, not yet in place); {path: SHA-256 (hex)} of each
        (an ENVI image is two)."""
        ...

    def commit(self) -> dict[pathlib.Path, str]:
        """Put the output's files in place (`finish`ed first if not yet); {path: SHA-256 (hex)}."""
        ...

    def __enter__(self) -> OutputWriter: ...

    def __exit__(self, *exc_info) -> None: ...


class _TimedReads:
    """A cube whose row reads count as the "read" stage (`stage_times`), as `correct_strips`
    reads it (its shape and `read_rows`): the rest of a strip's time is its correction."""

    def __init__(self, cube: io.CubeReader):
        self.shape = cube.shape
        self._cube = cube

    def read_rows(self, row0: int, row1: int) -> np.ndarray:
        with stage_times.stage("read"):
            return self._cube.read_rows(row0, row1)


class _OneFile:
    """An image writer of one file (`io.open_exr`, `io.open_png`, `io.open_quality_png`, whose
    `commit` gives that file's digest) as an `OutputWriter`."""

    def __init__(self, writer):
        self.writer = writer

    def write_rows(self, row0: int, pixels: np.ndarray) -> None:
        self.writer.write_rows(row0, pixels)

    def finish(self) -> dict[pathlib.Path, str]:
        return {self.writer.path: self.writer.finish()}

    def commit(self) -> dict[pathlib.Path, str]:
        return {self.writer.path: self.writer.commit()}

    def __enter__(self) -> _OneFile:
        return self

    def __exit__(self, *exc_info) -> None:
        self.writer.__exit__(*exc_info)  # uncommitted: the temporary file goes


#: The Lab outputs' channel names (not "L", "a", "b": OpenImageIO takes a channel "a" for alpha).
LAB_CHANNELS = ("L*", "a*", "b*")


def output_openers(
    output_format: str, paths: dict[str, pathlib.Path], shape: tuple[int, int], attributes: dict,
    exr_compression: str, stem: str, reflectance_type: str = "float",
) -> dict[str, Callable[[], OutputWriter]]:
    """{"reflectance", "lab", "quality", "preview": a function opening that output's writer} in
    `output_format`, `paths` by kind (`OUTPUT_KINDS_BY_FORMAT`), images of `shape` (H, W); an
    EXR reflectance of `reflectance_type` (`io.EXR_PIXEL_TYPES`; Lab stays float: half floats
    would round L* to 1/16 near 100)."""
    height, width = shape
    spectral_names = spectral_layout.reflectance_channel_names(WAVELENGTHS_NM.tolist())
    lab_names = list(LAB_CHANNELS)
    if output_format == "exr":
        spectral_attributes = {spectral_layout.LAYOUT_VERSION_ATTRIBUTE: spectral_layout.LAYOUT_VERSION, **attributes}
        openers = {
            "reflectance": lambda: _OneFile(io.open_exr(
                paths["reflectance.exr"], (height, width, len(spectral_names)), channel_names=spectral_names,
                attributes=spectral_attributes, compression=exr_compression, pixel_type=reflectance_type,
            )),
            "lab": lambda: _OneFile(io.open_exr(
                paths["lab.exr"], (height, width, 3), channel_names=lab_names, attributes=attributes,
                compression=exr_compression,
            )),
        }
    else:
        source = attributes.get("spherejax:source", stem)
        openers = {
            "reflectance": lambda: envi.EnviWriter(
                paths["reflectance.hdr"], (height, width, len(spectral_names)),
                description=f"spherejax reflectance factor (0..1) of {source}", band_names=spectral_names,
                wavelengths_nm=WAVELENGTHS_NM.tolist(), attributes=attributes,
            ),
            "lab": lambda: envi.EnviWriter(
                paths["lab.hdr"], (height, width, 3),
                description=f"spherejax CIELAB of {source} under {attributes.get('spherejax:illuminant')}",
                band_names=lab_names, attributes=attributes,
            ),
        }
    # The PNGs carry the output set too (a tEXt chunk), so that every output says which
    # correction it belongs to (`io.corrected`).
    output_set = {name: value for name, value in attributes.items() if name == "spherejax:output_set"}
    openers["quality"] = lambda: _OneFile(io.open_quality_png(paths["quality.png"], (height, width, 1), text=output_set))
    # The preview is for browsing: written fast (`io.open_png`'s `fast`: a tenth of the time,
    # a third of a megabyte larger).
    openers["preview"] = lambda: _OneFile(
        io.open_png(paths["preview.png"], (height, width, 3), channel_names=["R", "G", "B"], fast=True,
                    attributes=output_set)
    )
    return openers


def correct_into(
    cube: io.CubeReader, calibration: io.CalibrationFile, folder: pathlib.Path, stem: str,
    attributes: dict, rows_per_strip: int | None, exr_compression: str, output_format: str = "exr",
    before_commit: Callable[[], None] | None = None, reflectance_type: str = "float",
    record_made: Callable[[dict[pathlib.Path, str]], None] | None = None,
) -> dict[pathlib.Path, str]:
    """Correct `cube` strip by strip (`stripwise.correct_strips`) into its outputs in
    `output_format` (`OUTPUT_KINDS_BY_FORMAT`), each written under a temporary name and renamed
    into place once complete; on a failure the temporary files go and the outputs already
    renamed are removed. `before_commit` runs once every strip is written and before anything
    is renamed: raising there leaves nothing. Then every output is finished (complete and
    fsynced under its temporary name) and `record_made` gets {path: SHA-256 (hex)} of them all
    before the first is renamed into place: what it records (the batch's claims,
    `lock.record_made`) is then known before the file exists at its name, so that a run killed
    between the renames and the manifest line leaves files proved its own, by their bytes.
    Returns {path: SHA-256 (hex)} of every file written."""
    from ..stripwise import correct_strips

    kinds = OUTPUT_KINDS_BY_FORMAT[output_format]
    paths = {kind: folder / f"{stem}.{kind}" for kind in kinds}
    for path in paths.values():
        if path.is_symlink() or path.is_dir():
            raise io.SpherejaxFileError(path, "is a link or a folder", "a file spherejax may replace")
    height, width, _ = cube.shape
    openers = output_openers(output_format, paths, (height, width), attributes, exr_compression, stem, reflectance_type)
    committed: dict[pathlib.Path, str] = {}
    names = {output: next(kind for kind in kinds if kind.startswith(f"{output}.")) for output in openers}
    with contextlib.ExitStack() as stack:
        writers: dict[str, OutputWriter] = {}
        strips = correct_strips(_TimedReads(cube), calibration, rows_per_strip=rows_per_strip)
        while True:
            with stage_times.stage("correct"):  # less the reads, which count as "read"
                strip = next(strips, None)
            if strip is None:
                break
            row0, arrays = strip
            interrupt.check()  # a safe point: leaving here removes the temporary files (ExitStack)
            if not writers:
                # Opened once the first strip is corrected: an input that fails before (in its
                # header, or its patch rows) leaves no file to abandon (libpng complains on
                # stderr about a PNG closed without rows).
                for output, open_writer in openers.items():
                    writers[output] = stack.enter_context(open_writer())
            with stage_times.stage("preview"):
                preview = srgb_preview(arrays["reflectance"])
            rows = {"reflectance": arrays["reflectance"], "lab": arrays["lab"],
                    "quality": arrays["quality"][..., None], "preview": preview}
            for output, writer in writers.items():
                with stage_times.stage(f"encode {names[output]}"):
                    writer.write_rows(row0, rows[output])
        # The last safe point: from here the outputs go into place together.
        interrupt.check()
        if before_commit is not None:
            before_commit()
        finished: dict[pathlib.Path, str] = {}
        for output, writer in writers.items():
            with stage_times.stage(f"commit {names[output]}"):
                finished.update(writer.finish())
        if record_made is not None:
            record_made(finished)
        try:
            for output, writer in writers.items():
                with stage_times.stage(f"commit {names[output]}"):
                    committed.update(writer.commit())
        except BaseException:
            for path in committed:
                path.unlink(missing_ok=True)
            raise
    return committed


# ------------------------------------------------------------------------- folders and clean-up


#: The output folders the inputs under way in this process use, and how many use each: an input
#: that fails removes the folders it created only while no other input uses them (the in-process
#: batch corrects two at once: `batch._in_process`). Guarded by `_folders_lock`, which also makes
#: creating a folder and removing it one step each.
_folders_in_use: collections.Counter = collections.Counter()
_folders_lock = threading.Lock()


def output_folder(out_root: pathlib.Path, name: str) -> tuple[pathlib.Path, list[pathlib.Path]]:
    """The folder of `name`'s outputs, created inside OUT, and the folders that were created.

    Each existing component is resolved before anything is created below it, so a link inside
    OUT can never make mkdir or a write land outside OUT. The folders are marked in use until
    `release_folder(out_root, name)`; a folder another input (or process) creates at the same
    moment is used as found, not reported as created.
    """
    parts = pathlib.PurePosixPath(name).parts
    if not parts or pathlib.PurePosixPath(name).is_absolute() or ".." in parts:
        raise io.SpherejaxFileError(out_root / name, "would be written outside OUT", f"a path inside {out_root}")
    with _folders_lock:
        folder, created = _make_folders(out_root.resolve(), parts[:-1], out_root / name)
        _folders_in_use.update(_folders_of(out_root, name))
    return folder, created


def release_folder(out_root: pathlib.Path, name: str) -> None:
    """`name`'s output folders are no longer used by this input (`output_folder`)."""
    with _folders_lock:
        _folders_in_use.subtract(_folders_of(out_root, name))
        for folder in [folder for folder, count in _folders_in_use.items() if count <= 0]:
            del _folders_in_use[folder]


def _folders_of(out_root: pathlib.Path, name: str) -> list[pathlib.Path]:
    """The folders that hold `name`'s outputs below OUT, outermost first, named as `_make_folders`
    names them (OUT resolved, then the parts): the keys of `_folders_in_use`."""
    root, parts = out_root.resolve(), pathlib.PurePosixPath(name).parts
    return [root.joinpath(*parts[:depth]) for depth in range(1, len(parts))]


def _make_folders(root: pathlib.Path, parts, target) -> tuple[pathlib.Path, list[pathlib.Path]]:
    """`root`/parts, each component made if missing and checked if found (`output_folder`):
    (the folder, the folders made). `target`: the output named in messages."""
    folder, created = root, []
    for part in parts:
        folder = folder / part
        if not (folder.exists() or folder.is_symlink()):
            try:
                folder.mkdir()
            except FileExistsError:
                pass  # made meanwhile by another process (a dask worker): checked below, as found
            except OSError as error:
                raise io.SpherejaxFileError(folder, f"cannot be created: {error.strerror}") from None
            else:
                created.append(folder)
                continue
        if not folder.resolve().is_relative_to(root):
            raise io.SpherejaxFileError(
                target, f"would be written outside OUT: {folder} resolves to {folder.resolve()}",
                f"outputs inside {root}",
            )
        if not folder.is_dir():
            raise io.SpherejaxFileError(folder, "is not a folder: outputs cannot go there", "a folder")
    return folder, created


def remove_outputs(out_root: pathlib.Path, spec: InputSpec, keep: Sequence[str] = ()) -> None:
    """Remove the outputs of `spec` an earlier run left, but those of the kinds in `keep`: all of
    them for a failed input (the manifest says it failed), those of the other format for one just
    corrected (the manifest lists what it wrote). Only files proved spherejax's before any work
    (`InputSpec.owned`: their bytes recorded at that name, `lock.claim_outputs`) are removed: any
    other file of the same name is the user's. Nothing is touched outside OUT."""
    root = out_root.resolve()
    path = root / spec.name
    if ".." in pathlib.PurePosixPath(spec.name).parts or not path.parent.resolve().is_relative_to(root):
        return
    for kind in ALL_OUTPUT_KINDS:
        if kind in keep or f"{spec.name}.{kind}" not in spec.owned:
            continue
        output = path.parent / f"{path.name}.{kind}"
        if output.is_file() or output.is_symlink():
            output.unlink(missing_ok=True)


def remove_empty_folders(created: list[pathlib.Path]) -> None:
    """Remove the output folders an input created, deepest first, while they are empty and no
    other input under way in this process uses them (`output_folder`: one that has not written
    into it yet would find it gone). Call after `release_folder`."""
    with _folders_lock:
        for folder in reversed(created):
            if _folders_in_use[folder] > 0:  # keyed as output_folder names them: OUT resolved, then the parts
                break
            try:
                folder.rmdir()  # only if still empty: never another input's outputs
            except OSError:
                break


def remove_temporaries(out_root: pathlib.Path) -> int:
    """Remove the temporary files a killed run left in OUT (only ours: io's naming)."""
    removed = 0
    for dirpath, _, filenames in os.walk(out_root):
        for filename in filenames:
            if io.is_temp_sibling(filename):
                os.unlink(os.path.join(dirpath, filename))
                removed += 1
    return removed


__all__ = [
    "ALL_OUTPUT_KINDS", "LAB_CHANNELS", "OUTPUT_FORMATS", "OUTPUT_KINDS", "OUTPUT_KINDS_BY_FORMAT", "PREVIEW_BAD_PIXEL",
    "OutputWriter", "correct_into", "output_folder", "output_openers", "output_settings", "release_folder",
    "remove_empty_folders",
    "remove_outputs", "remove_temporaries", "srgb_preview",
]
