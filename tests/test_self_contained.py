"""The repository stands on its own: nothing in it reads or cites files a user of the project
does not have.

The project was started with notes and reference data in a folder beside the checkout; a clone
has nothing beside it. So (a) no tracked file may name that folder or its notes (what they held
now lives in docs/ and tests/data/), and (b) a copy of the working tree in an empty folder runs
the tests that read reference data.
"""

from __future__ import annotations

import os
import pathlib
import re
import shutil
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]

#: References to files outside the repository: the sibling folder and the notes it held, and
#: "issue N" pointers into a tracker a user cannot read. docs/ says in words where its pages came
#: from, so nothing is exempt; only this file, which has to spell the patterns, is skipped.
FORBIDDEN = re.compile(
    r"\.\./shared|shared/data|DESIGN\.md|INSTRUMENT\.md|STYLE\.md|\b[Ii]ssue \d+"
)
SELF = pathlib.Path(__file__).resolve().relative_to(ROOT).as_posix()

def _git(*args: str) -> bytes:
    return subprocess.run(["git", *args], cwd=ROOT, check=True, capture_output=True).stdout


def _working_tree_files() -> list[str]:
    """Tracked files plus untracked ones git does not ignore, as they are on disk now (uncommitted
    changes included, which a `git clone` of HEAD would miss)."""
    names = _git("ls-files", "-z") + _git("ls-files", "-z", "--others", "--exclude-standard")
    files = {name.decode() for name in names.split(b"\0") if name}
    # A tracked file deleted in the working tree is listed but has nothing to copy.
    return sorted(name for name in files if (ROOT / name).is_file() and not (ROOT / name).is_symlink())


def _references() -> dict[str, list[str]]:
    found = {}
    for name in _working_tree_files():
        if name == SELF:
            continue
        text = (ROOT / name).read_bytes().decode("utf-8", errors="replace")
        lines = [f"{n}: {line.strip()}" for n, line in enumerate(text.splitlines(), 1) if FORBIDDEN.search(line)]
        if lines:
            found[name] = lines
    return found


def test_no_file_cites_what_a_clone_lacks():
    found = _references()
    assert found == {}, "cite docs/design.md, docs/instrument.md or tests/data/ instead"


def test_reference_data_is_in_the_repository():
    from tests import helpers

    assert helpers.SHARMA_CSV.is_relative_to(ROOT) and helpers.SHARMA_CSV.is_file()
    assert (helpers.SHARMA_CSV.parent / "README.md").read_text().count("doi:10.1002/col.20070") == 1
    _, lab1, _, expected = helpers.sharma_pairs()
    assert lab1.shape == (34, 3) and expected.shape == (34,)


def test_a_copy_with_nothing_beside_it_passes_the_reference_data_tests(tmp_path):
    copy = tmp_path / "spherejax"
    for name in _working_tree_files():
        target = copy / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, target)
    assert not (copy.parent / "shared").exists() and sorted(os.listdir(tmp_path)) == ["spherejax"]

    env = {**os.environ, "PYTHONPATH": str(copy), "PYTHONDONTWRITEBYTECODE": "1"}
    # The copy's own modules must be the ones imported, not the editable install of this checkout.
    where = subprocess.run(
        [sys.executable, "-c", "import spherejax, tests.helpers as h; print(spherejax.__file__); print(h.SHARMA_CSV)"],
        cwd=copy, env=env, capture_output=True, text=True, timeout=120,
    )
    assert where.returncode == 0, where.stderr
    module, csv = where.stdout.split()
    assert pathlib.Path(module).is_relative_to(copy) and pathlib.Path(csv).is_relative_to(copy), where.stdout

    run = subprocess.run(
        # The tests that read the Sharma table (the rest of the file reads no data, and takes minutes),
        # in that one process (-n 0: no pytest-xdist workers for five tests).
        [sys.executable, "-m", "pytest", "tests/test_delta_e.py::TestSharma2005", "-q", "-p", "no:cacheprovider", "-n", "0"],
        cwd=copy, env=env, capture_output=True, text=True, timeout=300,
    )
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    assert re.search(r"\d+ passed", run.stdout) and "skipped" not in run.stdout, run.stdout[-2000:]
