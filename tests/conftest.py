"""Test configuration: float64 available, strict dtype promotion, one compilation cache for the
command-line processes the tests start, the order of the test files, shared fixtures.

x64 is switched on so every kernel can be tested in float32 and float64 side by side (float32
inputs stay float32 under x64). Strict promotion turns any implicit uint16 -> float or
float32 -> float64 mixing inside spherejax into an error, so dtype handling is explicit.

Every `spherejax` command (or other Python child process) that a test starts would compile its
JAX programs afresh; instead they share one persistent JAX compilation cache, so that a program
one of them compiled is loaded by the next (a `calibrate` takes about half the time with its
programs cached). The cache is a new, empty folder for each test run, removed when the run
ends: nothing carries over from one run to the next. A child process that may be killed, or cut
short by a file-size limit, in the middle of a write reads the cache but never writes it
(`helpers.no_compilation_cache_writes`). The test processes themselves (pytest, or each
pytest-xdist worker) do not use it: within one process JAX's in-memory cache already compiles
each program once, and the workers share almost no programs, so writing every executable out
would only cost time; and a test that counts compilations sees what a first run of spherejax
does.

The suite runs in two pytest-xdist worker processes (pyproject.toml), each test file in one of
them (`--dist loadfile`: a file's module-scoped fixtures are made once). The files with the most
tests marked `slow` are handed out first (`pytest_collection_modifyitems` below), so that no
worker is left running a long file alone at the end.
"""

import atexit
import collections
import os
import shutil
import tempfile

import jax

#: Names the run's cache folder to the processes the run starts (xdist's workers, and through
#: them the tests' child processes): the first process of a run makes the folder, the others
#: find it here.
_RUN_CACHE = "SPHEREJAX_TESTS_COMPILATION_CACHE"


def _compilation_cache_for_child_processes() -> None:
    path = os.environ.get(_RUN_CACHE)
    if not path or not os.path.isdir(path):
        path = tempfile.mkdtemp(prefix="jax-compilation-cache-")
        os.environ[_RUN_CACHE] = path
        atexit.register(shutil.rmtree, path, ignore_errors=True)
    # JAX reads these when a child process imports it (the environment is inherited).
    os.environ["JAX_COMPILATION_CACHE_DIR"] = path
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"


jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
_compilation_cache_for_child_processes()
# Not for this process: an xdist worker inherits the variables above, and JAX has read them.
jax.config.update("jax_compilation_cache_dir", None)

import numpy as np  # noqa: E402
import pytest  # noqa: E402


def pytest_collection_modifyitems(config, items):
    """Test files with more tests marked `slow` first (a stable sort: the order of the tests in a
    file, and of files with as many, is kept), so that pytest-xdist starts the long files early
    (pyproject.toml turns off its own reordering, by number of tests)."""
    slow = collections.Counter(item.path for item in items if item.get_closest_marker("slow"))
    items.sort(key=lambda item: -slow[item.path])


@pytest.fixture(scope="session")
def workspace(tmp_path_factory):
    """A small simulated session (tests/test_cli.py's SMALL design) and its calibration file,
    made once for the run (once per pytest-xdist worker) and shared by tests/test_cli.py and the
    robustness tests. Read-only: a test that changes the session or the file changes a copy."""
    from spherejax import cli, io
    from tests.helpers import SMALL

    root = tmp_path_factory.mktemp("cli")
    io.write_simulated_session(root / "session", seed=5, design=SMALL)
    assert cli.main(["-q", "calibrate", str(root / "session"), "-o", str(root / "cal.h5")]) == 0
    return root


@pytest.fixture(scope="module")
def cal(tmp_path_factory):
    """A calibration file for 40 x 48 pixel, 16-band frames (`tests.batch_support`), made once
    for each test module that asks for it."""
    from spherejax import io
    from tests.batch_support import make_calibration

    rng = np.random.default_rng(0)
    path = tmp_path_factory.mktemp("cal") / "cal.h5"
    calibration, bands, instrument = make_calibration(rng)
    io.save_calibration(path, calibration, instrument_id=instrument, band_centres_nm=bands)
    return path


@pytest.fixture(params=[np.float32, np.float64], ids=["float32", "float64"])
def dtype(request):
    """Each test using it runs in float32 and float64."""
    return request.param


@pytest.fixture(params=[False, True], ids=["eager", "jit"])
def maybe_jit(request):
    """Wrap a function in jax.jit (static keyword arguments allowed) or leave it as is."""
    if not request.param:
        return lambda fn, **static: fn

    def wrap(fn, static_argnames=()):
        return jax.jit(fn, static_argnames=static_argnames)

    return wrap


@pytest.fixture(scope="session")
def corrected_workspace(workspace, tmp_path_factory):
    """One test capture of `workspace` corrected by the command line with its calibration (which
    carries calibrate's noise model): {"raw", "calibration", "output" (N.reflectance.exr)}, for
    the viewer's tests. Read-only, like `workspace`."""
    from spherejax import cli

    raw = sorted((workspace / "session" / "frames").glob("test-*.tif"))[0]
    out = tmp_path_factory.mktemp("viewer") / "out"
    assert cli.main(["-q", "correct", "-c", str(workspace / "cal.h5"), str(raw), "-o", str(out)]) == 0
    return {"raw": raw, "calibration": workspace / "cal.h5", "output": out / f"{raw.stem}.reflectance.exr"}
