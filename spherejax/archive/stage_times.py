"""Where a batch's time goes: seconds per stage of each input (read, hash, correct, each output's
encode and commit), collected only when asked for (`benchmarks/bench_archive.py`).

The batch's code marks its stages with `stage(name)`; outside `collecting()` that is one global
read and nothing else, so the command line pays nothing for it. Inside, each stage's wall seconds
are added to the current thread's record (the pipeline corrects inputs in threads,
`archive.batch`), so that overlapping inputs are not mixed up.

Stage names: "hash" (the input's checksum), "read" (decoding the input's rows, the patch's
included), "correct" (the per-pixel correction of every strip, its outputs fetched to NumPy),
"preview" (the sRGB preview computed), "encode <kind>" (an output's rows handed to its writer,
where OpenImageIO encodes them), "commit <kind>" (an output finished: the encoder's last rows,
its SHA-256 read back, fsync, rename), kind as in `outputs.OUTPUT_KINDS_BY_FORMAT`.
"""

from __future__ import annotations

import collections
import contextlib
import threading
import time
from collections.abc import Iterator

_records: list | None = None  # the finished inputs' records while collecting, else None
_lock = threading.Lock()
_current = threading.local()  # .record: the input this thread is working on


@contextlib.contextmanager
def collecting() -> Iterator[list[dict]]:
    """Collect the stage times of the inputs corrected inside the block: yields the list that
    each finished input's record ({"name": input name, "thread": thread name, "stages":
    {stage: seconds}, "seconds": the input's wall seconds}) is appended to, in the order they
    finish. The seconds of an input not in any stage are its other work (opening, checks,
    clean-up) and, where inputs overlap, time its thread waited for the interpreter."""
    global _records
    records: list[dict] = []
    _records = records
    try:
        yield records
    finally:
        _records = None


@contextlib.contextmanager
def input_record(name: str) -> Iterator[None]:
    """The stages timed inside the block are input `name`'s (one thread's work on one input)."""
    if _records is None:
        yield
        return
    records = _records
    _current.record = {"name": name, "thread": threading.current_thread().name, "stages": collections.Counter(),
                       "inner": []}
    start = time.perf_counter()
    try:
        yield
    finally:
        record, _current.record = _current.record, None
        record["stages"] = dict(record["stages"])
        record["seconds"] = time.perf_counter() - start
        del record["inner"]
        with _lock:
            records.append(record)


@contextlib.contextmanager
def stage(name: str) -> Iterator[None]:
    """Add the block's wall seconds, less those of the stages inside it, to stage `name` of the
    current input (`input_record`)."""
    record = getattr(_current, "record", None) if _records is not None else None
    if record is None:
        yield
        return
    # Stages are exclusive: a stage inside another (the reads inside a strip's correction)
    # counts for itself alone and is taken off the outer one, so the stages add up to the time.
    inner = record["inner"]
    inner.append(0.0)
    start = time.perf_counter()
    try:
        yield
    finally:
        elapsed = time.perf_counter() - start
        record["stages"][name] += elapsed - inner.pop()
        if inner:
            inner[-1] += elapsed


__all__ = ["collecting", "input_record", "stage"]
