"""Scale-out of `spherejax correct` on dask.distributed.

The task is one input (`archive.correct_input`): workers read the input and write its outputs on
the shared file system themselves and return only a small `FileResult`, so no pixel array ever
passes through the scheduler. The client keeps the lock and the manifest (`archive.run_batch`).

- `--workers N`: a LocalCluster of N single-threaded worker processes on loopback. Each worker is
  pinned to one core before JAX starts, because XLA sizes its CPU thread pool from the cores a
  process may use and ignores the usual thread flags (docs/design.md, "Performance model"): one process per core with one
  XLA thread each, never N processes each spawning threads for all cores.
- `--scheduler ADDRESS`: a running cluster. Its workers are used as they were started; run them
  with `--nworkers <cores> --nthreads 1` (or one worker with all cores), never both.
- Every worker shares a persistent JAX compilation cache, so the first file a worker corrects
  compiles (or loads) `correct` once and later files reuse it.

dask.distributed starts its worker processes with "spawn" (its default), so JAX is never forked
after it has started.
"""

from __future__ import annotations

import logging
import os
import pathlib
from collections.abc import Iterator

from distributed import Client, LocalCluster, WorkerPlugin, wait

from . import archive, interrupt
from .allocator import keep_freed_memory

#: Where workers keep compiled executables unless SPHEREJAX_COMPILATION_CACHE says otherwise.
DEFAULT_CACHE = pathlib.Path.home() / ".cache" / "spherejax" / "jax-compilation"

#: How long `--scheduler ADDRESS` keeps trying to reach the scheduler before giving up.
SCHEDULER_TIMEOUT_S = 20.0


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
    `connect_timeout_s` seconds (default `SCHEDULER_TIMEOUT_S`)."""

    def __init__(self, *, workers: int | None = None, scheduler: str | None = None,
                 connect_timeout_s: float | None = None):
        if (workers is None) == (scheduler is None):
            raise ValueError("DaskExecutor: give exactly one of workers (a local cluster) or scheduler (an address)")
        if workers is not None and workers < 1:
            raise ValueError(f"--workers: expected a positive number of worker processes, got {workers}")
        self.workers, self.scheduler = workers, scheduler
        self.connect_timeout_s = SCHEDULER_TIMEOUT_S if connect_timeout_s is None else connect_timeout_s
        self.cluster = self.client = None

    def __enter__(self):
        if self.workers is not None:
            self.cluster = LocalCluster(
                n_workers=self.workers, threads_per_worker=1, processes=True,
                host="127.0.0.1", dashboard_address=None, silence_logs=logging.ERROR,
            )
            self.client = Client(self.cluster)
        else:
            try:
                self.client = Client(self.scheduler, timeout=f"{self.connect_timeout_s}s")
            except (OSError, TimeoutError) as error:
                raise ValueError(f"--scheduler: cannot reach the dask scheduler at {self.scheduler} ({error})") from None
        self.client.register_plugin(JaxWorkerSetup(cache_dir(), pin=self.workers is not None), name="spherejax-jax")
        return self

    def __exit__(self, *exc):
        if self.client is not None:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()
        return False

    def map(self, specs: list, out_root, calibration_path, **options) -> Iterator[tuple[object, object]]:
        """Yield (spec, FileResult) as workers finish; a worker that dies yields a failure.
        `options` are `archive.correct_input`'s keyword arguments.

        At most one input per worker thread is submitted at a time, so a stop request
        (`spherejax.interrupt`) has little under way to wait for: submitting stops, the inputs
        already on workers are let finish (a task cannot be stopped mid-write from here, and one
        cancelled while running would go on writing into OUT after the lock is released) and
        yielded, so the manifest records them, and then `interrupt.Interrupted` is raised.
        """
        waiting = list(enumerate(specs))
        waiting.reverse()  # popped from the end: submitted in order
        running: dict = {}
        window = max(1, sum(self.client.nthreads().values()))
        try:
            while waiting or running:
                stopping = interrupt.requested() is not None
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
                    except Exception as error:  # noqa: BLE001 -- a lost worker fails its input, not the batch
                        result = archive.failed_result(spec, f"worker failed: {' '.join(str(error).split())}")
                    yield spec, result
            interrupt.check()
        finally:
            # Only when the caller stopped iterating early (an error of its own): nothing more
            # of ours should land in OUT; inputs not started are dropped.
            for future in running:
                future.cancel()
