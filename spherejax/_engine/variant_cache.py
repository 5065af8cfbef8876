"""The fused kernel's variant timings, measured once per machine and kept in spherejax's cache
folder, so that every process on the machine runs the same variant.

Why kept, not measured in every process. The variants round differently (the AVX2 code sums in
another order than the AVX-512 and generic code: reflectance within about 2.4e-7, Lab within
1.2e-4), and on a loaded 2-core machine a measurement made in each process picked AVX2 in about
one run in eight where AVX-512 was the choice otherwise. Outputs of one archive then differed in
their last bits between runs, between a resumed batch and an uninterrupted one, and between dask
workers and the process that started them. Measured once and read by every process after, the
choice is one per machine: the same bits from every run on it.

Where: `$SPHEREJAX_CACHE_DIR`, else `$XDG_CACHE_HOME/spherejax`, else `~/.cache/spherejax`, file
`fused-kernel-variants.json`, holding one entry per machine key (the CPU's identity as
/proc/cpuinfo gives it, the variants it runs and the spherejax version). The file is spherejax's:
it is replaced only when its first key says it is one spherejax wrote (`FORMAT`), never through a
link, and written whole (`spherejax.atomic_files`: a temporary file renamed over it). The
measurement runs under an exclusive lock on a lock file beside it, so that processes starting
together (dask workers, a test run's workers) wait for one measurement instead of making their own.

Where the folder cannot be used (read-only, a foreign file in the way, no home), nothing is
measured: the widest variant the CPU runs is taken, which is the same in every process. Say why
once, at DEBUG.
"""

from __future__ import annotations

import json
import logging
import os
import pathlib
import stat
from collections.abc import Callable, Mapping

from .. import jsontext
from ..atomic_files import write_atomic

#: The file's first key and value: what makes it a file spherejax wrote.
FORMAT = "spherejax fused kernel variant timings"

#: Environment variable naming the cache folder (for tests, and for machines whose home is shared).
CACHE_DIR = "SPHEREJAX_CACHE_DIR"

FILE_NAME = "fused-kernel-variants.json"

_log = logging.getLogger(__name__)


def cache_folder() -> pathlib.Path:
    """The folder the timings are kept in (see the module docstring)."""
    if os.environ.get(CACHE_DIR):
        return pathlib.Path(os.environ[CACHE_DIR])
    if os.environ.get("XDG_CACHE_HOME"):
        return pathlib.Path(os.environ["XDG_CACHE_HOME"]) / "spherejax"
    return pathlib.Path.home() / ".cache" / "spherejax"


def machine_key(supported: tuple[str, ...], version: str) -> str:
    """One line naming this machine's CPU as /proc/cpuinfo gives it (vendor, family, model,
    stepping, model name; the first processor's), the variants it runs and the spherejax
    version: a CPU, a virtual machine that hides features or a new kernel build measures anew."""
    fields = {}
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as cpuinfo:
            for line in cpuinfo:
                if not line.strip():
                    break  # the first processor only
                name, _, value = line.partition(":")
                fields[name.strip()] = value.strip()
    except OSError:
        pass
    cpu = " / ".join(fields.get(k, "?") for k in ("vendor_id", "cpu family", "model", "stepping", "model name"))
    return f"{cpu} | runs {','.join(supported)} | spherejax {version}"


def _read(path: pathlib.Path) -> dict | None:
    """The entries of spherejax's file at `path`; {} if there is none; None if something else
    is there (a link, a folder, a file spherejax did not write), which is then left alone."""
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except FileNotFoundError:
        return {}
    except OSError:
        return None
    if not stat.S_ISREG(os.fstat(descriptor).st_mode):  # a folder or a FIFO: not ours
        os.close(descriptor)
        return None
    with os.fdopen(descriptor, "rb") as stored:
        try:
            document = jsontext.loads(stored.read(1 << 20))  # strict: a key given twice is damage
        except ValueError:
            return None
    if not isinstance(document, dict) or document.get("format") != FORMAT or not isinstance(document.get("machines"), dict):
        return None
    return document["machines"]


def _write(path: pathlib.Path, machines: dict) -> None:
    """The whole file, through a temporary file in its folder renamed over it (`atomic_files`)."""
    text = json.dumps({"format": FORMAT, "machines": machines}, indent=1, sort_keys=True)
    write_atomic(path, text + "\n")


def _valid(times) -> bool:
    return isinstance(times, dict) and all(
        isinstance(name, str) and isinstance(t, (int, float)) and t > 0 for name, t in times.items()
    )


def timings(key: str, supported: tuple[str, ...], measure: Callable[[], Mapping[str, float]]) -> dict[str, float] | None:
    """The machine's timings of each variant in `supported` (seconds a probe call), read from the
    cache or measured now with `measure()` and kept; None where the cache folder cannot be used
    (the caller then takes the widest variant, the same in every process)."""
    folder = cache_folder()
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        lock_descriptor = os.open(folder / (FILE_NAME + ".lock"), os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
    except OSError as error:
        _log.debug("fused kernel variants: cache folder %s not usable (%s); the widest variant runs", folder, error)
        return None
    try:
        import fcntl  # POSIX; the kernel is built for x86-64 Linux only

        fcntl.flock(lock_descriptor, fcntl.LOCK_EX)
        path = folder / FILE_NAME
        machines = _read(path)
        if machines is None:
            _log.debug("fused kernel variants: %s is not a file spherejax wrote; left alone, the widest variant runs", path)
            return None
        times = machines.get(key)
        if _valid(times) and set(times) == set(supported):
            return {name: float(t) for name, t in times.items()}
        times = {name: float(t) for name, t in measure().items()}
        try:
            _write(path, {**machines, key: times})
        except OSError as error:
            _log.debug("fused kernel variants: could not keep the timings in %s (%s); the widest variant runs", path, error)
            return None
        return times
    finally:
        os.close(lock_descriptor)  # releases the lock


__all__ = ["CACHE_DIR", "FILE_NAME", "FORMAT", "cache_folder", "machine_key", "timings"]
