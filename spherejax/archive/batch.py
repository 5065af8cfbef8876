"""The batch: `run_batch` (`spherejax correct -c CAL INPUT... -o OUT`) and its unit of work,
`correct_input`, which corrects ONE input into OUT given paths only (package docstring)."""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import dataclasses
import os
import pathlib
import threading
import time
from collections.abc import Callable, Iterator, Sequence

from .. import interrupt, io
from ..io.corrected import OUTPUT_SET_ATTRIBUTE, output_set_id
from . import inputs as _inputs
from . import stage_times
from .batch_calibration import CalibrationChangedError, CalibrationIdentity, open_for_input, read_once
from .discovery import InputSpec, discover_inputs, no_input_error
from .errors import BatchError
from .inputs import check_unchanged, hash_input, load_calibration, max_input_bytes
from .lock import OutputLock, claim_outputs, record_made, written_by_spherejax
from .manifest import MANIFEST_NAME, FileResult, Manifest, is_done, manifest_state
from .outputs import (
    OUTPUT_FORMATS, OUTPUT_KINDS_BY_FORMAT, correct_into, output_folder, output_settings, release_folder,
    remove_empty_folders, remove_outputs, remove_temporaries,
)


def correct_input(
    source: InputSpec, out_root, calibration_path, *, illuminant: str | None = None,
    rows_per_strip: int | None = None, exr_compression: str = io.DEFAULT_EXR_COMPRESSION,
    output_format: str = "exr", reflectance_type: str = "float", calibration_identity: CalibrationIdentity | None = None,
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
      reflectance_type: of an EXR reflectance, "float" (default) or "half" (`io.EXR_PIXEL_TYPES`).
      calibration_identity: the batch's calibration (`batch_calibration.CalibrationIdentity`, as
        `run_batch` read it): the calibration used must be that one, from before the input is
        read until its outputs go into place. None: the file as found when the input starts.

    Raises (the batch stops; this input has left nothing in OUT):
      CalibrationChangedError: the calibration file is not the batch's, or changed before this
        input's outputs went into place (`batch_calibration`).
      interrupt.Interrupted: a stop request, at a safe point.
    """
    with stage_times.input_record(source.name):
        return _correct_input(
            source, out_root, calibration_path, illuminant=illuminant, rows_per_strip=rows_per_strip,
            exr_compression=exr_compression, output_format=output_format, reflectance_type=reflectance_type,
            identity=calibration_identity,
        )


def _correct_input(
    source: InputSpec, out_root, calibration_path, *, illuminant, rows_per_strip, exr_compression, output_format,
    reflectance_type, identity,
) -> FileResult:
    from .. import __version__

    out_root = pathlib.Path(out_root)
    start = time.perf_counter()
    checksum = calibration_checksum = None
    created: list[pathlib.Path] = []
    in_use = False  # this input's output folders are marked in use (`output_folder`)

    def release() -> None:
        nonlocal in_use
        if in_use:
            release_folder(out_root, source.name)
            in_use = False

    try:
        calibration, identity = open_for_input(calibration_path, illuminant, identity, load_calibration)
        calibration_checksum = identity.checksum
        if source.problem is not None:
            raise ValueError(source.problem)
        with stage_times.stage("hash"):
            checksum, states = hash_input(source, max_input_bytes(calibration))
        with _inputs.open_input(source, calibration) as cube:  # looked up here: tests replace it
            attributes = {
                "spherejax:calibration_checksum": calibration_checksum,
                "spherejax:software_version": __version__,
                "spherejax:source": source.source,
                "spherejax:input_sha256": checksum,
                "spherejax:illuminant": calibration.patch_calibration.illuminant,
                # In every output of this input, the PNGs too: `io.open_corrected` refuses files
                # side by side that are not one correction's (`io.corrected`).
                OUTPUT_SET_ATTRIBUTE: output_set_id(
                    input_sha256=checksum, calibration_checksum=calibration_checksum, software_version=__version__,
                ),
            }
            folder, created = output_folder(out_root, source.name)
            in_use = True
            _note_created(out_root, created)
            stem = pathlib.PurePosixPath(source.name).name

            def before_commit() -> None:
                # The input read is the one hashed, and every row of the calibration read came
                # from the batch's calibration file (`batch_calibration`).
                check_unchanged(source, states)
                identity.check_file(calibration_path)

            written = correct_into(
                cube, calibration, folder, stem, attributes, rows_per_strip, exr_compression, output_format,
                before_commit=before_commit, reflectance_type=reflectance_type,
                record_made=lambda digests: record_made(out_root, digests),  # before they are in place
            )
        release()  # the outputs are in place: their folders are no longer empty
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
            software_version=__version__,
            settings=output_settings(calibration, output_format, exr_compression, reflectance_type),
            megapixels=height * width / 1e6,
            seconds=time.perf_counter() - start, folders_created=tuple(map(str, created)),
        )
    except (interrupt.Interrupted, CalibrationChangedError):
        # Stopped at a safe point, or before its outputs went into place with a calibration
        # that is no longer the batch's: the writers removed their temporary files and nothing
        # was renamed into place; the folders this input created go too. Outputs an earlier run
        # left stay as they are (the manifest says what they are): this run changed nothing of them.
        release()
        remove_empty_folders(created)
        raise
    except Exception as error:  # noqa: BLE001 -- the batch boundary: one bad input never stops it
        changed = identity.change_of(calibration_path) if identity is not None else None
        if changed is not None:
            # The calibration changed under the input (rows of a large one read from a file
            # rewritten in place fail in HDF5's words): not this input's failure but the batch's
            # stop, as above. Nothing of this input was put in place.
            release()
            remove_empty_folders(created)
            raise changed from None
        if source.problem is None:  # (a repeated name's outputs are the other input's)
            remove_outputs(out_root, source)
        release()
        remove_empty_folders(created)
        reason = " ".join(str(error).split()) or type(error).__name__
        if isinstance(error, OSError) and error.strerror:  # "[Errno 13] Permission denied: 'PATH'"
            reason = f"{error.filename or source.source}: {error.strerror}"
        if not isinstance(error, (io.SpherejaxFileError, OSError, ValueError)):
            reason = f"{type(error).__name__}: {reason}"
        return FileResult(
            name=source.name, source=source.source, status="failed", input_sha256=checksum,
            calibration_checksum=calibration_checksum, software_version=__version__,
            reason=reason, seconds=time.perf_counter() - start, folders_created=tuple(map(str, created)),
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
    reflectance_type: str = "float",
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
      reflectance_type: "float" (default) or "half": the EXR reflectance's pixel type
        (`io.EXR_PIXEL_TYPES`; half floats are within 4.9e-4 of each reflectance, package
        docstring). EXR only: ENVI has no half-float type.
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
      BatchError: OUT is not a folder, holds a manifest and resume is False, or is locked; a
        working folder that no longer exists while paths given are relative (named).
      NoInputError (a BatchError): the inputs hold no cube, band files or session (OUT is not
        created). Inputs that are all done already are not that: --resume skips them.
    Raises (inside `interrupt.stop_requests()`, on SIGINT or SIGTERM):
      interrupt.Interrupted: at the next safe point, with `done` (inputs finished, skipped or
        failed) and `total`; the input under way has left nothing in OUT, the lock is released,
        the manifest records every input finished.
    Raises (during the batch):
      CalibrationChangedError (a BatchError): the calibration file was replaced, rewritten or
        removed after the batch read it (`batch_calibration`); the batch stopped as on a signal,
        every input it records was corrected with the calibration it read.
      BatchError: an OSError of OUT's own files (the manifest, the lock file), naming the file.
    On every way out, the output folders the batch created and left empty are removed.
    """
    # Absolute: workers started in other folders read and write these paths themselves.
    _require_working_folder([out_root, calibration_path, *inputs])
    out_root = pathlib.Path(os.path.abspath(out_root))
    calibration_path = pathlib.Path(os.path.abspath(calibration_path))
    if exr_compression not in io.EXR_COMPRESSIONS:
        raise ValueError(f"exr_compression: expected one of {list(io.EXR_COMPRESSIONS)}, got {exr_compression!r}")
    if output_format not in OUTPUT_FORMATS:
        raise ValueError(f"output_format: expected one of {list(OUTPUT_FORMATS)}, got {output_format!r}")
    if reflectance_type not in io.EXR_PIXEL_TYPES:
        raise ValueError(f"reflectance_type: expected one of {list(io.EXR_PIXEL_TYPES)}, got {reflectance_type!r}")
    if reflectance_type != "float" and output_format != "exr":
        raise ValueError(
            f"reflectance_type: expected 'float' with output_format {output_format!r} (half floats are an "
            f"OpenEXR type; ENVI has none), got {reflectance_type!r}"
        )
    # The batch's one read of its calibration: every input must be corrected with this one.
    calibration, identity = read_once(calibration_path, illuminant, load_calibration)
    header = calibration.header
    settings = output_settings(calibration, output_format, exr_compression, reflectance_type)
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
    _open_created(out_root)
    results = None
    try:
        with _naming(out_root, "a temporary file a killed run left cannot be removed"):
            remove_temporaries(out_root)
        with _naming(out_root / MANIFEST_NAME, "cannot be read"):
            last, recorded = manifest_state(out_root)  # one read of the manifest, streamed
        done = last if resume else {}
        # --resume's verification first (read only): an input verified done is left as it is, so
        # claim_outputs need not hash its outputs again; the others' files are proved by theirs.
        verified = []
        try:
            for spec in specs:
                interrupt.check()  # verifying what is done reads every output: a while
                verified.append(resume and is_done(done.get(spec.name), spec, out_root, header["checksum"],
                                                   output_format, settings))
        except interrupt.Interrupted as stopped:
            stopped.done, stopped.total = sum(verified), len(specs)  # those verified are done
            raise
        with _naming(out_root / MANIFEST_NAME, "cannot be read"):
            written = written_by_spherejax(out_root, lock)
        specs = claim_outputs(specs, out_root, calibration_path, output_format, written, verified)
        manifest = Manifest(out_root)
        try:
            if on_start is not None:
                on_start(specs)
            try:
                pending = []
                for spec, is_verified in zip(specs, verified):
                    if is_verified:
                        summary.skipped += 1
                        if on_result is not None:
                            on_result(spec, None)
                        continue
                    pending.append(spec)
                with _naming(lock.path, "cannot record the outputs this run claims"):
                    lock.claim(f"{spec.name}.{kind}" for spec in pending if spec.problem is None
                               for kind in OUTPUT_KINDS_BY_FORMAT[output_format])
                options = {"illuminant": illuminant, "exr_compression": exr_compression, "output_format": output_format,
                           "reflectance_type": reflectance_type, "calibration_identity": identity}
                if executor is None:
                    results = _in_process(pending, out_root, calibration_path, options)
                else:
                    results = executor.map(pending, out_root, calibration_path, **options)
                # The manifest is written here, by the one process that holds the lock, whoever
                # corrected the input; an input is recorded only once its outputs are complete.
                for spec, result in results:
                    _note_created(out_root, result.folders_created)  # from a worker elsewhere, too
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
            except CalibrationChangedError as changed:
                finished = summary.corrected + summary.skipped + len(summary.failed)
                raise CalibrationChangedError(
                    changed.path, f"{changed.problem}; the batch stopped after {finished} of {len(specs)} inputs",
                ) from None
            ended = True
        finally:
            if hasattr(results, "close"):
                # Waits for the inputs under way (`_in_process`): no thread of ours writes into
                # OUT once the lock is released, whatever stopped this loop.
                results.close()
            with _naming(manifest.path, "cannot be closed"):
                manifest.close()
    except (interrupt.Interrupted, CalibrationChangedError):
        ended = True  # a clean stop: every input is recorded or has left nothing
        raise
    finally:
        try:
            _remove_empty_created(out_root)
        finally:
            # A run that ended removes its lock file, claims and all; after any other error the
            # claims stay for the next run (as after a kill): outputs may be in place unrecorded.
            lock.release(keep_claims=not ended)
    return summary


# ------------------------------------------------------------------ on the way out of a batch


@contextlib.contextmanager
def _naming(path: pathlib.Path, doing: str) -> Iterator[None]:
    """An OSError inside becomes a `BatchError` naming the file it concerns, in one line: "PATH:
    doing: what the system said" (`error.filename` when the system named one, else `path`), never
    a bare "[Errno 28] No space left on device"."""
    try:
        yield
    except OSError as error:
        raise BatchError(error.filename or path, f"{doing}: {error.strerror or error}") from None


def _require_working_folder(paths: Sequence) -> None:
    """Refuse, in one line naming it, a working folder that is gone when relative paths depend on
    it (os.getcwd fails with "[Errno 2]" after the folder was removed, naming nothing)."""
    if all(os.path.isabs(os.fspath(path)) for path in paths):
        return
    try:
        os.getcwd()
    except OSError as error:
        raise BatchError(
            _working_folder_name(), f"the working folder cannot be used: {error.strerror} (removed while this "
                                    "shell was in it?)",
            "an existing working folder for the relative paths given, or absolute paths",
        ) from None


def _working_folder_name() -> str:
    """The working folder's name when os.getcwd no longer gives it: what the kernel still says
    (Linux: /proc/self/cwd, "PATH (deleted)"), else the shell's $PWD, else words."""
    try:
        return os.readlink("/proc/self/cwd").removesuffix(" (deleted)")
    except OSError:
        return os.environ.get("PWD") or "the working folder"


#: The output folders the inputs of each batch running in this process created, by OUT (resolved):
#: `run_batch` opens the entry and removes those left empty on its way out; `_correct_input` adds
#: to it (in a dask worker, which runs no batch, the folders travel back in the FileResult).
_created_by_batch: dict[pathlib.Path, set[pathlib.Path]] = {}
_created_lock = threading.Lock()


def _open_created(out_root: pathlib.Path) -> None:
    """Start recording the folders the batch writing into OUT creates (`_note_created`)."""
    with _created_lock:
        _created_by_batch[out_root.resolve()] = set()


def _note_created(out_root, folders) -> None:
    """Record `folders`, just made in OUT by an input, for the batch of this process writing there
    (none runs in a dask worker: its folders come back in its FileResult)."""
    if folders:
        with _created_lock:
            batch = _created_by_batch.get(pathlib.Path(out_root).resolve())
            if batch is not None:
                batch.update(map(pathlib.Path, folders))


def _remove_empty_created(out_root: pathlib.Path) -> None:
    """Remove every output folder this batch created that is empty now, deepest first.

    An input that fails or stops removes the folders it made, but only while no other input under
    way uses them (`outputs.remove_empty_folders`); with two inputs under way in one folder (the
    frames of a session, `_in_process`; or two dask workers), the one that made it may fail while
    the other uses it, and the other did not make it: both leave it. Here every input is over, so
    whatever is still empty goes. Only folders made in this run: a folder the user made stays,
    empty or not; os.rmdir removes nothing that holds a file."""
    with _created_lock:
        created = _created_by_batch.pop(out_root.resolve(), set())
    for folder in sorted(created, key=lambda path: len(path.parts), reverse=True):
        with contextlib.suppress(OSError):  # not empty, or gone: either way nothing of ours to remove
            folder.rmdir()


#: Inputs an in-process batch works on at once, each in its own thread (`_in_process`).
INPUTS_IN_FLIGHT = 2


def _in_process(pending: list[InputSpec], out_root: pathlib.Path, calibration_path: pathlib.Path, options: dict,
                in_flight: int = INPUTS_IN_FLIGHT):
    """(spec, FileResult) of each input corrected in this process, in the order of `pending`.

    Why threads. One input's work is a chain that leaves a core idle most of the time: hashing
    and decoding the input, the correction, then encoding and writing four outputs, each step
    mostly inside a library that runs on one core. With `in_flight` inputs under way at once, in
    as many threads, those steps of different inputs overlap (one input's EXR being encoded
    while the next one is decoded and corrected), so that both cores of a 2-core machine are
    busy. That works because the steps that take the time release Python's GIL: OpenImageIO's
    reads and writes, zlib and hashlib on large buffers, the fused CPU kernel and XLA, os.fsync.
    Threads rather than processes: a process would load the calibration and compile the
    correction again, and the outputs would cross process boundaries.

    Memory: at most `in_flight` inputs are read, corrected and written at once, each bounded by
    its strips (`stripwise`), and a finished input's result waits for the ones before it.
    Order: results come in the order of `pending`, so the manifest's lines are in input order,
    as with one input at a time. Every input is corrected by `correct_input`, whole, in one
    thread: its outputs' atomic commits, its clean-up on failure and its safe points are those
    of a single input.

    Stopping: before each input is started, and inside every input at its own safe points, a
    stop that was asked for raises `interrupt.Interrupted` (`interrupt.check` reads a flag the
    main thread's handler sets, so it works in any thread). Inputs that finish are yielded in
    order; once any input stops, none is started, the others under way are waited for (each
    stops at its next safe point, leaving nothing, or finishes), the finished ones are yielded,
    and the stop is raised: no thread is left writing into OUT after this generator ends, also
    when its consumer stops early (the `finally`). An input that finds the calibration file
    changed (`batch_calibration.CalibrationChangedError`) stops the batch the same way.
    """
    if in_flight <= 1 or len(pending) <= 1:
        for spec in pending:
            interrupt.check()
            yield spec, correct_input(spec, out_root, calibration_path, **options)
        return
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=in_flight, thread_name_prefix="spherejax-input")
    under_way: collections.deque = collections.deque()
    upcoming = iter(pending)
    stopped: interrupt.Interrupted | CalibrationChangedError | None = None
    try:
        while True:
            while stopped is None and len(under_way) < in_flight:
                spec = next(upcoming, None)
                if spec is None:
                    break
                try:
                    interrupt.check()
                except interrupt.Interrupted as stop:
                    stopped = stop
                    break
                under_way.append((spec, pool.submit(correct_input, spec, out_root, calibration_path, **options)))
            if not under_way:
                break
            spec, future = under_way.popleft()
            try:
                result = future.result()
            except (interrupt.Interrupted, CalibrationChangedError) as stop:
                stopped = stopped or stop  # the batch stops: no input starts after this one
                continue
            yield spec, result
        if stopped is not None:
            raise stopped
    finally:
        # Normally empty here; after an error or a consumer that stopped early, the inputs
        # under way finish (or stop at a safe point) before OUT's lock can be released.
        pool.shutdown(wait=True, cancel_futures=True)


__all__ = ["BatchSummary", "correct_input", "run_batch"]
