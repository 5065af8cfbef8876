"""`spherejax correct --workers N`: a dask LocalCluster on loopback gives the in-process result."""

import subprocess
import sys

import numpy as np
import pytest

from spherejax import archive, cluster, io

from .batch_support import NAMES, frame, make_calibration, outputs_of, run


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    """Six good cube files and one that is not an image, with their calibration."""
    root = tmp_path_factory.mktemp("cluster")
    rng = np.random.default_rng(5)
    calibration, bands, instrument = make_calibration(rng)
    io.save_calibration(root / "cal.h5", calibration, instrument_id=instrument, band_centres_nm=bands)
    inputs = root / "in"
    inputs.mkdir()
    for k in range(6):
        io.write_frame(inputs / f"cube{k}.tif", frame(rng), channel_names=NAMES)
    (inputs / "broken.tif").write_bytes(b"not a TIFF")
    return root


@pytest.mark.slow
@pytest.mark.parametrize("output_format", archive.OUTPUT_FORMATS)
def test_two_local_workers_match_the_in_process_run(batch, tmp_path, capsys, monkeypatch, output_format):
    monkeypatch.setenv("SPHEREJAX_COMPILATION_CACHE", str(tmp_path / "jax-cache"))
    common = ["-q", "correct", "-c", str(batch / "cal.h5"), str(batch / "in"), "--format", output_format]
    status, out, _ = run([*common, "-o", str(tmp_path / "serial")], capsys)
    assert status == 1 and "6 corrected, 0 skipped (already done), 1 failed" in out
    status, out, err = run([*common, "-o", str(tmp_path / "dask"), "--workers", "2"], capsys)
    assert status == 1 and "6 corrected, 0 skipped (already done), 1 failed" in out, err
    assert outputs_of(tmp_path / "dask") == outputs_of(tmp_path / "serial")
    records = archive.read_manifest(tmp_path / "dask")
    assert sorted(r["status"] for r in records.values()) == ["done"] * 6 + ["failed"]
    # Each worker compiled `correct` into the shared persistent cache.
    assert any((tmp_path / "jax-cache").iterdir())


def test_a_local_cluster_starts_when_port_8787_is_taken():
    """Something else holds dask's default dashboard port (a notebook's cluster, another
    `correct --workers` run): the cluster still starts, with no warning (a warning on stderr would
    break the command line's one-line messages; pytest turns it into an error here). Before the
    fix the scheduler's HTTP server went to 8787, and a second run warned "Port 8787 is already
    in use" (seen when two test processes started clusters at once)."""
    import socket

    holder = socket.socket()
    try:
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            holder.bind(("", 8787))
        except OSError:  # held already (another process): the case under test either way
            pass
        else:
            holder.listen()
        with cluster.DaskExecutor(workers=1) as executor:
            assert executor.client.submit(sum, [1, 2, 3]).result(timeout=60) == 6
            assert executor.cluster.scheduler.http_server.port != 8787
    finally:
        holder.close()


def test_executor_arguments():
    with pytest.raises(ValueError, match="exactly one of workers"):
        cluster.DaskExecutor()
    with pytest.raises(ValueError, match="--workers: expected a positive number of worker processes, got 0"):
        cluster.DaskExecutor(workers=0)
    assert cluster.DaskExecutor(scheduler="tcp://127.0.0.1:9").connect_timeout_s == cluster.SCHEDULER_TIMEOUT_S == 20.0
    assert cluster.DaskExecutor(scheduler="tcp://127.0.0.1:9", connect_timeout_s=2.5).connect_timeout_s == 2.5


def test_unreachable_scheduler_is_one_line(batch, tmp_path, capsys, monkeypatch):
    # Nothing listens on port 9: a short connect timeout instead of the default 20 s.
    monkeypatch.setattr(cluster, "SCHEDULER_TIMEOUT_S", 1.0)
    status, _, err = run(["correct", "-c", str(batch / "cal.h5"), str(batch / "in"), "-o", str(tmp_path / "o"),
                          "--scheduler", "tcp://127.0.0.1:9"], capsys)
    assert status == 2 and len(err.strip().splitlines()) == 1 and "--scheduler" in err
    assert not (tmp_path / "o").exists()


def test_worker_setup_keeps_freed_memory(tmp_path):
    """Each worker process gets the command line's allocator setting before its first JAX work
    (spherejax._engine.allocator), checked in a fresh process as a worker would run the plugin."""
    code = (
        "import sys, types; from spherejax import cluster; from spherejax._engine import allocator; "
        "cluster.JaxWorkerSetup(sys.argv[1], pin=False).setup(types.SimpleNamespace(name='0')); "
        "print(allocator._applied)"
    )
    done = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == ("True" if sys.platform.startswith("linux") else "False")
