"""`spherejax correct --workers N` bounded by the machine, and the temporary dask folders removed
on every exit path.

`--workers 100000` on a 2-core machine, taken as given, starts no worker while the client's
memory grows by about 15 MB/s, and a run killed meanwhile leaves `dask-scratch-space/scheduler-*`
in the temporary folder. So N must lie in 1..the cores this process may use (refused before any
work, one line, exit status 2), and a LocalCluster's scratch space is a `spherejax-dask-*` folder
of spherejax's own, removed when the run ends, normally or by SIGTERM; a folder a killed run left
is removed by the next run, and nothing else is touched.

The runs that start a real cluster run the command line in a child process with TMPDIR pointed
at a folder of the test's, so that what dask and spherejax leave in "the temporary folder" can be
looked at.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile

import numpy as np
import pytest

from spherejax import cluster, interrupt, io
from tests.batch_support import NAMES, frame, run, wait_until

PREFIX = "spherejax-dask-"  # cluster.SCRATCH_PREFIX
BATCH = 40  # small cubes: enough that a SIGTERM sent once the worker starts finds the run under way


def _cores() -> int:
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    """BATCH cubes; their first three in a folder of their own (`inputs`)."""
    root = tmp_path_factory.mktemp("in")
    rng = np.random.default_rng(12)
    for k in range(BATCH):
        folder = root / ("few" if k < 3 else "rest")
        folder.mkdir(exist_ok=True)
        io.write_frame(folder / f"cube{k:02d}.tif", frame(rng), channel_names=NAMES)
    return root


@pytest.fixture(scope="module")
def inputs(batch):
    return batch / "few"


@pytest.fixture(scope="module")
def jax_cache(tmp_path_factory):
    """The workers' compilation cache, shared by this module's runs (outside their TMPDIR)."""
    return tmp_path_factory.mktemp("jax-cache")


def _start(cal, inputs, out, tmpdir, jax_cache, *extra) -> subprocess.Popen:
    command = [sys.executable, "-m", "spherejax.cli", "-q", "correct", "-c", str(cal), str(inputs), "-o", str(out),
               "--workers", "1", *extra]
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "TMPDIR": str(tmpdir), "SPHEREJAX_COMPILATION_CACHE": str(jax_cache)}
    return subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


# ------------------------------------------------------------------------------ the bound


def test_workers_beyond_the_cores_are_refused_before_any_work(cal, inputs, tmp_path, capsys):
    cores = _cores()
    for asked in (cores + 1, 100000):
        status, out, err = run(["correct", "-c", str(cal), str(inputs), "-o", str(tmp_path / "out"),
                                "--workers", str(asked)], capsys)
        assert status == 2, (asked, err)
        assert out == "" and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
        assert f"--workers: {asked} worker processes asked for" in err
        assert f"gives this process {cores} core" in err and f"expected 1..{cores}" in err, err
        assert not (tmp_path / "out").exists()
    status, _, err = run(["correct", "-c", str(cal), str(inputs), "-o", str(tmp_path / "out"), "--workers", "0"], capsys)
    assert status == 2 and len(err.strip().splitlines()) == 1 and f"expected 1..{cores}" in err, err
    assert not (tmp_path / "out").exists()
    # The rule is in --help.
    with pytest.raises(SystemExit):
        run(["correct", "--help"], capsys)
    helptext = " ".join(capsys.readouterr().out.split())
    assert "N in 1..the cores this process may use" in helptext


def test_the_api_bounds_workers_by_the_cores_this_process_may_use(monkeypatch):
    cores = _cores()
    with pytest.raises(ValueError, match=rf"^--workers: 100000 worker processes asked for, this machine gives "
                                         rf"this process {cores} cores? \(expected 1\.\.{cores}\b"):
        cluster.DaskExecutor(workers=100000)
    assert cluster.DaskExecutor(workers=cores).workers == cores  # nothing starts before `with`
    assert cluster.available_cores() == cores
    with pytest.raises(ValueError, match=rf"--workers: .*'2'.*expected 1\.\.{cores}"):
        cluster.DaskExecutor(workers="2")
    # The process's CPU affinity, not the machine's count, is the bound (taskset, a batch scheduler).
    if hasattr(os, "sched_getaffinity"):
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})
        with pytest.raises(ValueError, match=r"2 worker processes asked for, this machine gives this process 1 core "
                                             r"\(expected 1\.\.1\b"):
            cluster.DaskExecutor(workers=2)
        assert cluster.DaskExecutor(workers=1).workers == 1


# ----------------------------------------------------------------------- the scratch space


def test_a_normal_run_keeps_its_scratch_in_its_own_folder_and_leaves_nothing(cal, inputs, tmp_path, jax_cache):
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    process = _start(cal, inputs, tmp_path / "out", tmpdir, jax_cache)
    scratch = f"{PREFIX}*/dask-scratch-space"
    seen = []

    def scheduler_and_worker_started():
        # Both the scheduler's and the worker's scratch land in spherejax's folder under TMPDIR.
        if any(tmpdir.glob(f"{scratch}/worker-*")) and any(tmpdir.glob(f"{scratch}/scheduler-*")):
            seen.extend(sorted(os.listdir(tmpdir)))
            return True
        return False

    wait_until(process, scheduler_and_worker_started)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 0, err.decode()
    assert len(seen) == 1 and seen[0].startswith(PREFIX), seen
    assert sorted(os.listdir(tmpdir)) == []
    assert cluster.SCRATCH_PREFIX == PREFIX


def test_a_sigterm_stopped_run_leaves_nothing(cal, batch, tmp_path, jax_cache):
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    out = tmp_path / "out"
    process = _start(cal, batch, out, tmpdir, jax_cache)
    wait_until(process, lambda: any(tmpdir.rglob("worker-*")))
    assert process.poll() is None, "the run ended before the signal"
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM, err.decode()
    assert "interrupted" in err.decode()
    assert sorted(os.listdir(tmpdir)) == []


class _FakeCluster:
    """Stands in for LocalCluster (no process started): checks where the scratch goes."""

    def __init__(self, fail_with=None, **kwargs):
        scratch = kwargs.get("local_directory")
        assert scratch is not None and os.path.isdir(scratch), kwargs
        assert kwargs.get("scheduler_kwargs", {}).get("local_directory") == scratch, kwargs
        assert os.path.basename(scratch).startswith(PREFIX), scratch
        if fail_with is not None:
            raise fail_with

    def close(self):
        pass


class _FakeClient:
    def __init__(self, cluster):
        pass

    def register_plugin(self, plugin, name):
        pass

    def close(self):
        pass


@pytest.mark.parametrize("where", ["start", "with-block"])
@pytest.mark.parametrize("error", [RuntimeError("cannot start"), interrupt.Interrupted(signal.SIGTERM)],
                         ids=["error", "interrupted"])
def test_the_scratch_folder_is_removed_on_every_way_out(tmp_path, monkeypatch, where, error):
    """A cluster that fails to start, an error or a stop request in the run: no folder left."""
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmpdir))
    monkeypatch.setenv("SPHEREJAX_COMPILATION_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(cluster, "LocalCluster",
                        lambda **kwargs: _FakeCluster(fail_with=error if where == "start" else None, **kwargs))
    monkeypatch.setattr(cluster, "Client", _FakeClient)
    with pytest.raises(type(error)):
        with cluster.DaskExecutor(workers=1):
            assert [p.name[:len(PREFIX)] for p in tmpdir.iterdir()] == [PREFIX]
            raise error
    assert sorted(os.listdir(tmpdir)) == []


def test_the_next_run_removes_only_abandoned_scratch_folders(cal, inputs, tmp_path, jax_cache, monkeypatch):
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "TMPDIR": str(tmpdir)}
    # A run killed outright (SIGKILL) while its scratch folder existed: abandoned.
    killed = subprocess.run(
        [sys.executable, "-c", "import os, signal; from spherejax import cluster; "
                               "space = cluster.ScratchSpace(); print(space.path, flush=True); os.kill(os.getpid(), signal.SIGKILL)"],
        env=env, capture_output=True, text=True, timeout=120,
    )
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    abandoned = os.path.basename(killed.stdout.strip())
    assert (tmpdir / abandoned / cluster.SCRATCH_LOCK).is_file()
    (tmpdir / abandoned / "dask-scratch-space" / "scheduler-x").mkdir(parents=True)
    # A folder whose owner runs (this process).
    monkeypatch.setattr(tempfile, "tempdir", str(tmpdir))
    live = cluster.ScratchSpace()
    monkeypatch.undo()
    # Folders spherejax did not make, or cannot prove abandoned: kept whatever their names.
    (tmpdir / f"{cluster.SCRATCH_PREFIX}no-lock").mkdir()
    (tmpdir / f"{cluster.SCRATCH_PREFIX}no-lock" / "data").write_text("keep")
    (tmpdir / f"{cluster.SCRATCH_PREFIX}no-marker").mkdir()
    (tmpdir / f"{cluster.SCRATCH_PREFIX}no-marker" / cluster.SCRATCH_LOCK).write_text("someone else's lock\n")
    (tmpdir / "unrelated").mkdir()
    (tmpdir / "unrelated" / cluster.SCRATCH_LOCK).write_bytes(cluster.SCRATCH_MARKER)
    (tmpdir / f"{cluster.SCRATCH_PREFIX}link").symlink_to(tmpdir / "unrelated")
    before = sorted(os.listdir(tmpdir))
    assert abandoned in before
    try:
        process = _start(cal, inputs, tmp_path / "out", tmpdir, jax_cache)
        _, err = process.communicate(timeout=120)
        assert process.returncode == 0, err.decode()
        assert sorted(os.listdir(tmpdir)) == sorted(set(before) - {abandoned})
        assert (tmpdir / f"{cluster.SCRATCH_PREFIX}no-lock" / "data").read_text() == "keep"
        assert (tmpdir / "unrelated" / cluster.SCRATCH_LOCK).read_bytes() == cluster.SCRATCH_MARKER
        assert os.path.isdir(live.path) and os.path.isfile(os.path.join(live.path, cluster.SCRATCH_LOCK))
    finally:
        live.remove()
    assert not os.path.exists(live.path)
