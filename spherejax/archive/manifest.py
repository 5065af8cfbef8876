"""OUT/manifest.jsonl: one record per finished input, `FileResult`, and what `--resume` reads of it
(package docstring, "Safety").

The file is an `io.journal.Journal` keyed by "name": one JSON line per record, appended with one
write and fsync, a torn last line ended before the next record and skipped on reading. The last
record of a name wins. Reading is a safe point (`interrupt.check` between chunks)."""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Iterator
from typing import Annotated

from .. import interrupt
from ..io.documents import Checksum, Document, Expect, NonEmptyStr, Sha256, check_document, choice, located
from ..io.hashing import sha256_file
from ..io.journal import Journal
from .discovery import InputSpec
from .errors import BatchError, link_or
from .inputs import input_checksum
from .outputs import OUTPUT_KINDS_BY_FORMAT

MANIFEST_NAME = "manifest.jsonl"


@dataclasses.dataclass(frozen=True)
class FileResult:
    """What became of one input: a manifest record (`to_json`, `from_json`) plus timing for
    progress (`megapixels`, `seconds`) and the output folders its correction created
    (`folders_created`, paths, for the batch to remove those left empty), never recorded.

    status is "done" or "failed" (with a one-line `reason`); outputs maps each output's path
    relative to OUT to its SHA-256 (hex); settings are the options that shape the outputs
    (`output_settings`), which `--resume` compares.
    """

    name: str
    source: str
    status: str
    input_sha256: str | None = None
    outputs: dict = dataclasses.field(default_factory=dict)
    calibration_checksum: str | None = None
    software_version: str | None = None
    reason: str | None = None
    settings: dict | None = None
    megapixels: float = 0.0
    seconds: float = 0.0
    folders_created: tuple[str, ...] = ()

    def to_json(self) -> dict:
        """The manifest line of this result: `source` is its "input"; settings and reason only
        when set."""
        record = {
            "name": self.name,
            "input": self.source,
            "input_sha256": self.input_sha256,
            "outputs": self.outputs,
            "calibration_checksum": self.calibration_checksum,
            "software_version": self.software_version,
            "status": self.status,
        }
        if self.settings is not None:
            record["settings"] = self.settings
        if self.reason is not None:
            record["reason"] = self.reason
        return record

    @classmethod
    def from_json(cls, record, path) -> FileResult | None:
        """The result a manifest line (read as JSON) records, or None when it is not a record
        as `to_json` writes it (another writer's line, a damaged file: redone, never trusted).
        `path`: the manifest, for the check's messages."""
        try:
            checked = check_document(_Record, _validatable(record), error=located(BatchError, path))
        except BatchError:
            return None
        if len(checked.outputs) != len(record["outputs"]):
            return None  # two output names alike but for their escapes: not a line spherejax wrote
        # The names as written: under a locale that is not UTF-8 an input's name carries the lone
        # surrogates Python decodes its bytes to (os.fsdecode), which pydantic's strings cannot
        # hold; they were checked in a form without them (`_validatable`), and are kept as they are.
        return cls(
            name=record["name"], source=record["input"], status=checked.status, input_sha256=checked.input_sha256,
            outputs=dict(zip(record["outputs"], checked.outputs.values())),
            calibration_checksum=checked.calibration_checksum, software_version=checked.software_version,
            reason=checked.reason, settings=checked.settings,
        )


def _validatable(value):
    """`value` (a manifest line read as JSON) with every string's lone surrogates written as
    backslash escapes, for the record check only: same structure, same keys in the same order."""
    if isinstance(value, str):
        return value.encode("utf-8", "backslashreplace").decode("utf-8")
    if isinstance(value, dict):
        return {_validatable(key): _validatable(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_validatable(item) for item in value]
    return value


_Status = choice("done", "failed")


class _Record(Document):
    """What `FileResult.from_json` accepts: one line of OUT/manifest.jsonl as `FileResult.to_json`
    writes it (the JSON form of a FileResult, not another record type)."""

    name: NonEmptyStr
    input: NonEmptyStr
    status: _Status
    input_sha256: Sha256 | None
    outputs: Annotated[dict[str, Sha256], Expect("an object: output path -> SHA-256")]
    calibration_checksum: Checksum | None
    software_version: NonEmptyStr | None
    settings: Annotated[dict | None, Expect("an object: the settings that shape the outputs")] = None
    reason: NonEmptyStr | None = None


def failed_result(source: InputSpec, reason: str) -> FileResult:
    """A FileResult for an input whose correction never reported back (e.g. a lost worker)."""
    from .. import __version__

    return FileResult(name=source.name, source=source.source, status="failed",
                      software_version=__version__, reason=" ".join(reason.split()))


# ----------------------------------------------------------------------------------- reading


def _journal(out_root) -> Journal:
    return Journal(pathlib.Path(out_root) / MANIFEST_NAME, key="name", safe_point=interrupt.check)


def manifest_records(out_root) -> Iterator[dict]:
    """Every line of OUT's manifest that is a JSON object with a name, in order, as read. Lines
    that are not whole JSON objects (a run killed during its last write) are left out. Streamed:
    a manifest truncated up to gigabytes (sparse, no newline) is never read whole."""
    return _journal(out_root).records()


def manifest_state(out_root) -> tuple[dict[str, dict], set[str]]:
    """One pass over OUT's manifest: (the last record of each input name, every output path any
    record lists). Lines that are not whole JSON objects are ignored."""
    last: dict[str, dict] = {}
    owned: set[str] = set()
    for record in manifest_records(out_root):
        last[record["name"]] = record
        outputs = record.get("outputs")
        if isinstance(outputs, dict):
            owned.update(name for name in outputs if isinstance(name, str))
    return last, owned


def read_manifest(out_root) -> dict[str, dict]:
    """The last manifest record of each input name (lines that are not whole JSON objects are
    ignored)."""
    return manifest_state(out_root)[0]


def recorded_outputs(out_root) -> set[str]:
    """Every output path (relative to OUT) any record of OUT's manifest lists: the files in OUT
    that spherejax wrote, and so the only ones it may replace or remove (package docstring,
    Safety)."""
    return manifest_state(out_root)[1]


def output_digest(path: pathlib.Path) -> str | None:
    """The SHA-256 (hex) of an output in OUT, or None when it cannot be read as a regular file
    (missing, a link, a FIFO: refused at once, never waited on)."""
    try:
        return sha256_file(path)
    except OSError:
        return None


def is_done(record: dict | None, spec: InputSpec, out_root: pathlib.Path, calibration_checksum: str,
            output_format: str = "exr", settings: dict | None = None) -> bool:
    """True if `record` (a manifest line as read, `read_manifest`) says `spec` is done with this
    calibration, this version of spherejax and these `settings` (`output_settings`; None: not
    compared), its input is unchanged and every output of `output_format` is recorded and there
    with its checksum (a batch resumed in another format, illuminant or compression redoes its
    inputs)."""
    from .. import __version__

    if not record or spec.problem is not None:
        return False
    result = FileResult.from_json(record, out_root / MANIFEST_NAME)
    if result is None:
        return False  # a line another writer or a damaged file left is redone, not trusted
    if result.status != "done":
        return False
    if result.calibration_checksum != calibration_checksum:
        return False
    # Each output names the version that wrote it (spherejax:software_version): another version
    # writes other bytes, and may compute other numbers.
    if result.software_version != __version__:
        return False
    if settings is not None and result.settings != settings:
        return False
    expected = {f"{spec.name}.{kind}" for kind in OUTPUT_KINDS_BY_FORMAT[output_format]}
    if set(result.outputs) != expected:
        return False
    try:
        if result.input_sha256 != input_checksum(spec):
            return False
    except OSError:
        return False
    return all(output_digest(out_root / name) == digest for name, digest in result.outputs.items())


# --------------------------------------------------------------------------------- appending


class Manifest:
    """OUT/manifest.jsonl opened for appending (`io.journal`): one write + fsync per record.

    Raises BatchError when it cannot be opened: a symbolic link planted as OUT's manifest must not
    make us append to the file it points at, outside OUT (tests/robustness/test_security.py); a
    FIFO in its place made `--resume` wait forever for a reader.
    """

    def __init__(self, out_root: pathlib.Path):
        self.path = out_root / MANIFEST_NAME
        try:
            self._writer = _journal(out_root).open()
        except OSError as error:
            raise BatchError(self.path, f"cannot be opened: {link_or(error)}", "a regular file inside OUT") from None

    def append(self, result: FileResult) -> None:
        """Record `result` (its `to_json`), on disk when this returns.

        Raises BatchError naming the manifest when the write or its fsync fails (a full disk): the
        input's outputs are in place unrecorded, and stay claimed in OUT's lock for `--resume`.
        """
        try:
            self._writer.append(result.to_json())
        except OSError as error:
            raise BatchError(
                self.path, f"cannot record {result.source}: {error.strerror or error}",
                "room on its disk: the outputs in place stay claimed by OUT's lock; run again with --resume",
            ) from None

    def close(self) -> None:
        self._writer.close()


__all__ = [
    "MANIFEST_NAME", "FileResult", "Manifest", "failed_result", "is_done", "manifest_records", "manifest_state",
    "output_digest", "read_manifest", "recorded_outputs",
]
