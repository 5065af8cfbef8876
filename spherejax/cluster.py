"""Scale-out of `spherejax correct` on dask.distributed.

The task is one input (`archive.correct_input`): workers read the input and write its outputs on
the shared file system themselves and return only a small `FileResult`, so no pixel array ever
passes through the scheduler. The client keeps the lock and the manifest (`archive.run_batch`).

- `--workers N`: a LocalCluster of N single-threaded worker processes on loopback. Each worker is
  pinned to one core before JAX starts, because XLA sizes its CPU thread pool from the cores a
  process may use and ignores the usual thread flags (docs/design.md, "Performance model"): one process per core with one
  XLA thread each, never N processes each spawning threads for all cores.
  N must lie in 1..C, C the cores this process may use (`available_cores`: its CPU affinity where
  the system has one, else the machine's count), checked before anything starts (ValueError, a
  one-line exit status 2 on the command line). No overcommit: a second worker pinned to a core
  only time-slices it with the first, while adding a process, its JAX runtime, its compilation
  and its inputs' buffers to memory -- slower, never faster. An unbounded N (100000) would
  start no worker at all and grow the client's memory until the machine gave out.
- Scratch space: a LocalCluster's scheduler and workers keep their scratch files (dask's
  `dask-scratch-space/scheduler-*`, `worker-*`) in a folder spherejax creates and owns,
  `<tempdir>/spherejax-dask-XXXXXXXX` (`SCRATCH_PREFIX`, tempfile.gettempdir() so TMPDIR
  applies), removed when the cluster stops: normal end, an error, `interrupt.Interrupted`
  (SIGINT / SIGTERM), a cluster that fails to start, and at interpreter exit for one never
  closed. A run killed outright (SIGKILL, a lost machine) cannot remove it; the next `--workers`
  run removes such folders, only those provably abandoned: the owner holds an exclusive flock on
  the folder's `SCRATCH_LOCK` file, written with `SCRATCH_MARKER` once locked, for as long as it
  runs, so a folder of this prefix, owned by this user, whose lock file holds the marker and can
  be locked is one whose owner is gone. Anything else is left alone: a folder without the lock
  file or its marker (not spherejax's, or a run killed in the microseconds between making the
  folder and locking it: an empty folder), a live run's folder, another user's.
- `--scheduler ADDRESS`: a running cluster. Its workers are used as they were started; run them
  with `--nworkers <cores> --nthreads 1` (or one worker with all cores), never both.
- Every worker shares a persistent JAX compilation cache, so the first file a worker corrects
  compiles (or loads) `correct` once and later files reuse it.

dask.distributed starts its worker processes with "spawn" (its default), so JAX is never forked
after it has started.
"""

from __future__ import annotations

import logging
import operator
import os
import pathlib
import shutil
import stat
import sys
import tempfile
import weakref
from collections.abc import Iterator

try:
    import fcntl
except ImportError:  # no flock (Windows): scratch folders are still removed by their own run
    fcntl = None

from distributed import Client, LocalCluster, WorkerPlugin, wait

from . import archive, interrupt
from ._engine.allocator import keep_freed_memory

#: Where workers keep compiled executables unless SPHEREJAX_COMPILATION_CACHE says otherwise.
DEFAULT_CACHE = pathlib.Path.home() / ".cache" / "spherejax" / "jax-compilation"

#: How long `--scheduler ADDRESS` keeps trying to reach the scheduler before giving up.
SCHEDULER_TIMEOUT_S = 20.0

#: The name of the temporary folder a LocalCluster keeps its scratch space in starts so.
SCRATCH_PREFIX = "spherejax-dask-"

#: In each such folder: the file its owner holds an exclusive flock on for as long as it runs ...
SCRATCH_LOCK = "spherejax-owner.lock"

#: ... and writes this line into (then its pid) once it holds the lock.
SCRATCH_MARKER = b"spherejax dask scratch space, locked by its owner while it runs\n"


def available_cores() -> int:
    """The cores this process may run on: its CPU affinity where the system has one (a batch
    scheduler's or taskset's allotment), else the machine's count."""
    if hasattr(os, "sched_getaffinity"):
        try:
            return max(1, len(os.sched_getaffinity(0)))
        except OSError:
            pass
    return max(1, os.cpu_count() or 1)


def check_workers(workers) -> int:
    """`workers` if it is a whole number in 1..`available_cores()`; ValueError (one line naming
    the value and the expected range) otherwise. No overcommit: the module docstring says why."""
    cores = available_cores()
    expected = f"expected 1..{cores}, one single-threaded worker process per core"
    try:
        if isinstance(workers, bool):
            raise TypeError
        workers = operator.index(workers)
    except TypeError:
        raise ValueError(f"--workers: {workers!r} is not a whole number of worker processes ({expected})") from None
    if workers < 1:
        raise ValueError(f"--workers: expected a positive number of worker processes, got {workers} "
                         f"(this machine gives this process {cores} core{'s' if cores != 1 else ''}: {expected})")
    if workers > cores:
        raise ValueError(f"--workers: {workers} worker processes asked for, this machine gives this process "
                         f"{cores} core{'s' if cores != 1 else ''} ({expected})")
    return workers


def _remove_scratch(path: str, fd: int | None) -> None:
    """Remove a scratch folder (then release its lock) and the sys.path entries dask added for it."""
    shutil.rmtree(path, ignore_errors=True)
    if fd is not None:
        os.close(fd)  # closing releases the flock
    sys.path[:] = [entry for entry in sys.path if not (entry == path or entry.startswith(path + os.sep))]


class ScratchSpace:
    """A temporary folder `<tempdir>/SCRATCH_PREFIX...` for a LocalCluster's scratch files, locked
    by this process (module docstring) until `remove()`, which is idempotent and also runs at
    interpreter exit or when the object is collected."""

    def __init__(self):
        self.path = tempfile.mkdtemp(prefix=SCRATCH_PREFIX)
        fd = None
        try:
            if fcntl is not None:
                fd = os.open(os.path.join(self.path, SCRATCH_LOCK),
                             os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o600)
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                # Written only once locked: a lock file holding the marker had been locked.
                os.write(fd, SCRATCH_MARKER + f"{os.getpid()}\n".encode())
        except BaseException:
            _remove_scratch(self.path, fd)
            raise
        self._finalizer = weakref.finalize(self, _remove_scratch, self.path, fd)

    def remove(self) -> None:
        self._finalizer()


def remove_abandoned_scratch(root=None) -> list[str]:
    """Remove the scratch folders under `root` (default tempfile.gettempdir()) that a killed
    run left behind, and only those provably abandoned (module docstring); return their paths."""
    if fcntl is None:
        return []
    root = tempfile.gettempdir() if root is None else os.fspath(root)
    removed = []
    try:
        entries = [entry for entry in os.scandir(root) if entry.name.startswith(SCRATCH_PREFIX)]
    except OSError:
        return removed
    for entry in entries:
        try:
            info = entry.stat(follow_symlinks=False)
            if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid():
                continue
            fd = os.open(os.path.join(entry.path, SCRATCH_LOCK), os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
        except OSError:  # gone, not ours, or no lock file: not provably abandoned
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:  # held: its owner runs
                continue
            lock = os.fstat(fd)
            if not stat.S_ISREG(lock.st_mode) or lock.st_uid != os.getuid():
                continue
            if not os.read(fd, len(SCRATCH_MARKER) + 32).startswith(SCRATCH_MARKER):
                continue  # never locked by a spherejax run, or not yet
            try:  # still the folder whose lock we hold (another cleaner may have been first)
                if os.stat(os.path.join(entry.path, SCRATCH_LOCK), follow_symlinks=False).st_ino != lock.st_ino:
                    continue
            except OSError:
                continue
            shutil.rmtree(entry.path, ignore_errors=True)  # under our lock: no owner can appear
            removed.append(entry.path)
        finally:
            os.close(fd)
    return removed


class JaxWorkerSetup(WorkerPlugin):
    """Runs in every worker before its first task: optional pinning to one core, glibc keeping
    freed memory (`allocator.keep_freed_memory`, as the command line's own process does), and
    the persistent compilation cache."""

    def __init__(self, cache_dir: str, pin: bool):
        self.cache_dir = cache_dir
        self.pin = pin

    def setup(self, worker):
        if self.pin and hasattr(os, "sched_setaffinity"):
            cores = sorted(os.sched_getaffinity(0))
            index = abs(hash(str(worker.name))) if not str(worker.name).isdigit() else int(worker.name)
            os.sched_setaffinity(0, {cores[index % len(cores)]})
        keep_freed_memory()  # before the worker's first JAX work
        import jax

        jax.config.update("jax_compilation_cache_dir", self.cache_dir)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def cache_dir() -> str:
    path = pathlib.Path(os.environ.get("SPHEREJAX_COMPILATION_CACHE", DEFAULT_CACHE))
    path.mkdir(parents=True, exist_ok=True)
    return str(path)


class DaskExecutor:
    """Maps `archive.correct_input` over inputs on a dask cluster; a context manager that starts
    (and stops) a LocalCluster for `workers`, or connects to `scheduler`, trying for
    `connect_timeout_s` seconds (default `SCHEDULER_TIMEOUT_S`).

    `workers` must lie in 1..`available_cores()` (ValueError here, before anything starts). A
    LocalCluster keeps its scratch files in a `ScratchSpace` removed on every way out of the
    `with` block, after first removing the abandoned ones of killed runs (module docstring)."""

    def __init__(self, *, workers: int | None = None, scheduler: str | None = None,
                 connect_timeout_s: float | None = None):
        if (workers is None) == (scheduler is None):
            raise ValueError("DaskExecutor: give exactly one of workers (a local cluster) or scheduler (an address)")
        if workers is not None:
            workers = check_workers(workers)
        self.workers, self.scheduler = workers, scheduler
        self.connect_timeout_s = SCHEDULER_TIMEOUT_S if connect_timeout_s is None else connect_timeout_s
        self.cluster = self.client = self.scratch = None

    def __enter__(self):
        try:
            if self.workers is not None:
                remove_abandoned_scratch()
                self.scratch = ScratchSpace()
                self.cluster = LocalCluster(
                    n_workers=self.workers, threads_per_worker=1, processes=True,
                    # The scheduler serves HTTP (its health and metrics routes) whatever the
                    # dashboard; dashboard_address=None means dask's default port 8787, and when
                    # something holds that port (another cluster, a notebook's, a second run)
                    # dask warns on stderr, which breaks the command line's one-line messages.
                    # A free port on loopback, and no dashboard: a batch has no one to show it to.
                    host="127.0.0.1", dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR,
                    local_directory=self.scratch.path,  # the workers' (through their nannies)
                    scheduler_kwargs={"local_directory": self.scratch.path, "dashboard": False},
                )
                self.client = Client(self.cluster)
            else:
                try:
                    self.client = Client(self.scheduler, timeout=f"{self.connect_timeout_s}s")
                except (OSError, TimeoutError) as error:
                    raise ValueError(f"--scheduler: cannot reach the dask scheduler at {self.scheduler} ({error})") from None
            self.client.register_plugin(JaxWorkerSetup(cache_dir(), pin=self.workers is not None), name="spherejax-jax")
        except BaseException:  # a cluster that fails to start (or a stop request) leaves nothing behind
            self.__exit__(*sys.exc_info())
            raise
        return self

    def __exit__(self, *exc):
        try:
            if self.client is not None:
                self.client.close()
        finally:
            try:
                if self.cluster is not None:
                    self.cluster.close()
            finally:
                if self.scratch is not None:
                    self.scratch.remove()
                self.cluster = self.client = self.scratch = None
        return False

    def map(self, specs: list, out_root, calibration_path, **options) -> Iterator[tuple[object, object]]:
        """Yield (spec, FileResult) as workers finish; a worker that dies yields a failure.
        `options` are `archive.correct_input`'s keyword arguments.

        At most one input per worker thread is submitted at a time, so a stop request
        (`spherejax.interrupt`) has little under way to wait for: submitting stops, the inputs
        already on workers are let finish (a task cannot be stopped mid-write from here, and one
        cancelled while running would go on writing into OUT after the lock is released) and
        yielded, so the manifest records them, and then `interrupt.Interrupted` is raised.

        A worker that finds the calibration file is not the batch's
        (`archive.CalibrationChangedError`, raised by `correct_input` with the batch's
        `calibration_identity`, having left nothing in OUT) stops the batch the same way: nothing
        more is submitted, the inputs under way finish (or find the change themselves) and are
        yielded, and the first such error is raised.
        """
        waiting = list(enumerate(specs))
        waiting.reverse()  # popped from the end: submitted in order
        running: dict = {}
        window = max(1, sum(self.client.nthreads().values()))
        changed: archive.CalibrationChangedError | None = None
        try:
            while waiting or running:
                stopping = interrupt.requested() is not None or changed is not None
                while waiting and len(running) < window and not stopping:
                    k, spec = waiting.pop()
                    future = self.client.submit(
                        archive.correct_input, spec, str(out_root), str(calibration_path),
                        pure=False, key=f"spherejax-correct-{k}", **options,
                    )
                    running[future] = spec
                if not running:
                    break
                # A short timeout, so a stop request is seen while every worker is busy.
                try:
                    finished = wait(list(running), timeout=0.2, return_when="FIRST_COMPLETED").done
                except TimeoutError:
                    finished = ()
                for future in finished:
                    spec = running.pop(future)
                    try:
                        result = future.result()
                    except archive.CalibrationChangedError as error:  # the batch stops; this input left nothing
                        changed = changed or error
                        continue
                    except Exception as error:  # noqa: BLE001 -- a lost worker fails its input, not the batch
                        result = archive.failed_result(spec, f"worker failed: {' '.join(str(error).split())}")
                    yield spec, result
            interrupt.check()
            if changed is not None:
                raise changed
        finally:
            # Only when the caller stopped iterating early (an error of its own): nothing more
            # of ours should land in OUT; inputs not started are dropped.
            for future in running:
                future.cancel()
