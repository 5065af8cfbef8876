"""The batch: `run_batch` (`spherejax correct -c CAL INPUT... -o OUT`) and its unit of work,
`correct_input`, which corrects ONE input into OUT given paths only (package docstring)."""

from __future__ import annotations

import dataclasses
import os
import pathlib
import time
from collections.abc import Callable, Sequence

from .. import interrupt, io
from . import inputs as _inputs
from .discovery import InputSpec, discover_inputs, no_input_error
from .errors import BatchError
from .inputs import check_unchanged, hash_input, load_calibration, max_input_bytes
from .lock import OutputLock, claim_outputs
from .manifest import MANIFEST_NAME, FileResult, Manifest, is_done, manifest_state
from .outputs import (
    OUTPUT_FORMATS, OUTPUT_KINDS_BY_FORMAT, correct_into, output_folder, output_settings, remove_empty_folders,
    remove_outputs, remove_temporaries,
)


def correct_input(
    source: InputSpec, out_root, calibration_path, *, illuminant: str | None = None,
    rows_per_strip: int | None = None, exr_compression: str = io.DEFAULT_EXR_COMPRESSION,
    output_format: str = "exr",
) -> FileResult:
    """Correct one input into OUT and return its `FileResult`; never raises for a bad input.

    Checks the input against the calibration (instrument, bands, size), then reads, corrects and
    writes it strip by strip (`stripwise`), so memory stays bounded whatever the image's size,
    into its four outputs (package docstring). On failure nothing of this input is left in OUT
    (outputs, temporary files and folders it created are removed) and the result says why.

    Args:
      source: from `discover_inputs`.
      out_root: OUT, an existing folder.
      calibration_path: the calibration file (verified once per process).
      illuminant: Lab illuminant ("D65", "A", "F2"); None = the calibration's.
      rows_per_strip: strip height; None = `stripwise.strip_height` (the whole image when small).
      exr_compression: of the EXR outputs, one of `io.EXR_COMPRESSIONS` (all lossless).
      output_format: "exr" (the default) or "envi" (`OUTPUT_KINDS_BY_FORMAT`).
    """
    from .. import __version__

    out_root = pathlib.Path(out_root)
    start = time.perf_counter()
    checksum = calibration_checksum = None
    created: list[pathlib.Path] = []
    try:
        calibration = load_calibration(calibration_path, illuminant)
        calibration_checksum = calibration.header["checksum"]
        if source.problem is not None:
            raise ValueError(source.problem)
        checksum, states = hash_input(source, max_input_bytes(calibration))
        with _inputs.open_input(source, calibration) as cube:  # looked up here: tests replace it
            attributes = {
                "spherejax:calibration_checksum": calibration_checksum,
                "spherejax:software_version": __version__,
                "spherejax:source": source.source,
                "spherejax:input_sha256": checksum,
                "spherejax:illuminant": calibration.patch_calibration.illuminant,
            }
            folder, created = output_folder(out_root, source.name)
            stem = pathlib.PurePosixPath(source.name).name
            written = correct_into(
                cube, calibration, folder, stem, attributes, rows_per_strip, exr_compression, output_format,
                before_commit=lambda: check_unchanged(source, states),
            )
        # An earlier run in the other format left files the manifest will no longer list.
        remove_outputs(out_root, source, keep=OUTPUT_KINDS_BY_FORMAT[output_format])
        outputs = {
            path.resolve().relative_to(out_root.resolve()).as_posix(): digest
            for path, digest in written.items()
        }
        height, width = calibration.image_shape
        return FileResult(
            name=source.name, source=source.source, status="done", input_sha256=checksum,
            outputs=outputs, calibration_checksum=calibration_checksum,
            software_version=__version__, settings=output_settings(calibration, output_format, exr_compression),
            megapixels=height * width / 1e6,
            seconds=time.perf_counter() - start,
        )
    except interrupt.Interrupted:
        # Stopped at a safe point: the writers removed their temporary files and nothing was
        # renamed into place; the folders this input created go too. Outputs an earlier run left
        # stay as they are (the manifest says what they are): this run changed nothing of them.
        remove_empty_folders(created)
        raise
    except Exception as error:  # noqa: BLE001 -- the batch boundary: one bad input never stops it
        if source.problem is None:  # (a repeated name's outputs are the other input's)
            remove_outputs(out_root, source)
        remove_empty_folders(created)
        reason = " ".join(str(error).split()) or type(error).__name__
        if isinstance(error, OSError) and error.strerror:  # "[Errno 13] Permission denied: 'PATH'"
            reason = f"{error.filename or source.source}: {error.strerror}"
        if not isinstance(error, (io.SpherejaxFileError, OSError, ValueError)):
            reason = f"{type(error).__name__}: {reason}"
        return FileResult(
            name=source.name, source=source.source, status="failed", input_sha256=checksum,
            calibration_checksum=calibration_checksum, software_version=__version__,
            reason=reason, seconds=time.perf_counter() - start,
        )


@dataclasses.dataclass
class BatchSummary:
    """Counts of a run and every failed input's `FileResult`."""

    corrected: int = 0
    skipped: int = 0
    failed: list[FileResult] = dataclasses.field(default_factory=list)
    taken_over: str | None = None

    def line(self) -> str:
        return f"{self.corrected} corrected, {self.skipped} skipped (already done), {len(self.failed)} failed"


def run_batch(
    inputs: Sequence,
    out_root,
    calibration_path,
    *,
    resume: bool = False,
    illuminant: str | None = None,
    exr_compression: str = io.DEFAULT_EXR_COMPRESSION,
    output_format: str = "exr",
    on_start: Callable[[list[InputSpec]], None] | None = None,
    on_result: Callable[[InputSpec, FileResult | None], None] | None = None,
    on_warning: Callable[[str], None] | None = None,
    executor=None,
) -> BatchSummary:
    """Correct every input into OUT, in process (`spherejax correct`).

    Args:
      inputs: files and folders (package docstring).
      out_root: OUT; created if missing.
      calibration_path: the calibration file.
      resume: continue a batch already in OUT, skipping verified inputs.
      illuminant: Lab illuminant; None = the calibration's.
      exr_compression: of the EXR outputs (`io.EXR_COMPRESSIONS`, all lossless).
      output_format: "exr" (default: OpenEXR, the reflectance in the spectral layout) or "envi"
        (ENVI reflectance and Lab); `OUTPUT_KINDS_BY_FORMAT` lists the files of each.
      on_start: called with the inputs found, before the first is corrected.
      on_result: called per input with its FileResult, or None when it was skipped.
      on_warning: called with one line per folder not followed and per input named twice
        (`discover_inputs`).
      executor: None corrects in this process; otherwise an object whose
        map(specs, out_root, calibration_path, **options) calls `correct_input` with those
        keyword options and yields (spec, FileResult) in any order, e.g.
        `spherejax.cluster.DaskExecutor`. Paths reach it absolute: a worker may run elsewhere.
        When a stop is asked for (`spherejax.interrupt`) it stops submitting, yields the inputs
        already under way as they finish and raises `interrupt.Interrupted`.

    Raises (before anything is written):
      CalibrationFileError: a calibration that cannot be read.
      BatchError: OUT is not a folder, holds a manifest and resume is False, or is locked.
      NoInputError (a BatchError): the inputs hold no cube, band files or session (OUT is not
        created). Inputs that are all done already are not that: --resume skips them.
    Raises (inside `interrupt.stop_requests()`, on SIGINT or SIGTERM):
      interrupt.Interrupted: at the next safe point, with `done` (inputs finished, skipped or
        failed) and `total`; the input under way has left nothing in OUT, the lock is released,
        the manifest records every input finished.
    """
    # Absolute: workers started in other folders read and write these paths themselves.
    out_root = pathlib.Path(os.path.abspath(out_root))
    calibration_path = pathlib.Path(os.path.abspath(calibration_path))
    if exr_compression not in io.EXR_COMPRESSIONS:
        raise ValueError(f"exr_compression: expected one of {list(io.EXR_COMPRESSIONS)}, got {exr_compression!r}")
    if output_format not in OUTPUT_FORMATS:
        raise ValueError(f"output_format: expected one of {list(OUTPUT_FORMATS)}, got {output_format!r}")
    calibration = load_calibration(calibration_path, illuminant)
    header = calibration.header
    settings = output_settings(calibration, output_format, exr_compression)
    if out_root.exists() and not out_root.is_dir():
        raise BatchError(out_root, "is not a folder", "an output folder (OUT)")
    if not resume and (out_root / MANIFEST_NAME).exists():
        raise BatchError(
            out_root, f"already holds a batch ({MANIFEST_NAME})",
            "--resume to continue it, or a new OUT",
        )
    specs = discover_inputs(inputs, out_root, warn=on_warning)
    if not specs:  # refused before OUT (or its lock) is created: a typo in INPUT leaves nothing
        raise no_input_error(inputs)
    try:
        out_root.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise BatchError(out_root, f"cannot be created: {error.strerror}", "a writable OUT") from None

    lock = OutputLock(out_root)
    lock.acquire()
    summary = BatchSummary(taken_over=lock.taken_over)
    ended = False
    try:
        remove_temporaries(out_root)
        last, recorded = manifest_state(out_root)  # one read of the manifest, streamed
        done = last if resume else {}
        specs = claim_outputs(specs, out_root, calibration_path, output_format, recorded | lock.claimed)
        manifest = Manifest(out_root)
        try:
            if on_start is not None:
                on_start(specs)
            try:
                pending = []
                for spec in specs:
                    interrupt.check()  # verifying what is done reads every output: a while
                    if resume and is_done(done.get(spec.name), spec, out_root, header["checksum"], output_format, settings):
                        summary.skipped += 1
                        if on_result is not None:
                            on_result(spec, None)
                        continue
                    pending.append(spec)
                lock.claim(f"{spec.name}.{kind}" for spec in pending if spec.problem is None
                           for kind in OUTPUT_KINDS_BY_FORMAT[output_format])
                options = {"illuminant": illuminant, "exr_compression": exr_compression, "output_format": output_format}
                if executor is None:
                    results = _in_process(pending, out_root, calibration_path, options)
                else:
                    results = executor.map(pending, out_root, calibration_path, **options)
                # The manifest is written here, by the one process that holds the lock, whoever
                # corrected the input; an input is recorded only once its outputs are complete.
                for spec, result in results:
                    manifest.append(result)
                    if result.status == "done":
                        summary.corrected += 1
                    else:
                        summary.failed.append(result)
                    if on_result is not None:
                        on_result(spec, result)
            except interrupt.Interrupted as stopped:
                stopped.done = summary.corrected + summary.skipped + len(summary.failed)
                stopped.total = len(specs)
                raise
            ended = True
        finally:
            manifest.close()
    except interrupt.Interrupted:
        ended = True  # a clean stop: every input is recorded or has left nothing
        raise
    finally:
        # A run that ended removes its lock file, claims and all; after any other error the
        # claims stay for the next run (as after a kill): outputs may be in place unrecorded.
        lock.release(keep_claims=not ended)
    return summary


def _in_process(pending: list[InputSpec], out_root: pathlib.Path, calibration_path: pathlib.Path, options: dict):
    """(spec, FileResult) of each input corrected in this process, stopping at the safe point
    before each input when a stop is asked for (`correct_input` has its own, inside)."""
    for spec in pending:
        interrupt.check()
        yield spec, correct_input(spec, out_root, calibration_path, **options)


__all__ = ["BatchSummary", "correct_input", "run_batch"]
