"""Security (docs/reliability.md, "Nothing read is run"): nothing read is unpickled or evaluated, paths from manifests and
profiles stay in their folders, and the lock, the manifest and temporary files cannot be turned
into writes outside OUT."""

from __future__ import annotations

import ast
import hashlib
import json
import pathlib
import shutil
import uuid

import numpy as np
import pytest

import spherejax
from spherejax_hw import profile as hw_profile
from spherejax import archive, cli, io
from tests.helpers import calibration_entries
from tests.hw.support import write_profile
from tests.batch_support import NAMES, frame

ROOT = pathlib.Path(__file__).resolve().parents[2]
SOURCES = sorted([*(ROOT / "spherejax").rglob("*.py"), *(ROOT / "hw").rglob("*.py")])

UNSAFE_MODULES = {"pickle", "cPickle", "marshal", "shelve", "dill", "cloudpickle", "joblib"}
UNSAFE_CALLS = {"eval", "exec"}


def test_the_scan_sees_the_sources():
    assert len(SOURCES) > 30 and ROOT / "spherejax" / "io" / "__init__.py" in SOURCES


@pytest.mark.parametrize("source", SOURCES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_no_pickle_or_eval_where_files_are_read(source):
    """No unpickling module imported, no eval/exec, every np.load with allow_pickle=False, and
    no yaml.load: reading a file never runs code from it."""
    tree = ast.parse(source.read_text(), filename=str(source))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            assert not {alias.name.split(".")[0] for alias in node.names} & UNSAFE_MODULES, ast.dump(node)
        elif isinstance(node, ast.ImportFrom):
            assert (node.module or "").split(".")[0] not in UNSAFE_MODULES, ast.dump(node)
        elif isinstance(node, ast.Call):
            func = node.func
            if isinstance(func, ast.Name):
                assert func.id not in UNSAFE_CALLS, f"{source}:{node.lineno}"
            if isinstance(func, ast.Attribute) and func.attr == "load":
                owner = ast.unparse(func.value)
                assert owner != "yaml", f"{source}:{node.lineno}"
                if owner in ("np", "numpy"):
                    keywords = {k.arg: ast.unparse(k.value) for k in node.keywords}
                    assert keywords.get("allow_pickle") == "False", f"{source}:{node.lineno}: np.load without allow_pickle=False"
            for keyword in node.keywords:
                if keyword.arg == "allow_pickle":
                    assert ast.unparse(keyword.value) == "False", f"{source}:{node.lineno}"


class _Touch:
    """Unpickling this creates `marker`: the proof that a file's pickle was run."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (pathlib.Path.touch, (pathlib.Path(self.marker),))


def test_a_calibration_file_carrying_a_pickle_is_refused_unopened(workspace, tmp_path):
    arrays = calibration_entries(workspace / "cal.h5")  # written as an old .npz below
    marker = tmp_path / "pwned"
    payload = np.empty(1, dtype=object)
    payload[0] = _Touch(marker)
    arrays["coeffs"] = payload
    np.savez(tmp_path / "evil.npz", **arrays)  # object arrays are stored as pickles
    with pytest.raises(ValueError) as raised:
        io.load_calibration(tmp_path / "evil.npz")
    assert "evil.npz" in str(raised.value) and "\n" not in str(raised.value)
    assert not marker.exists()


@pytest.mark.parametrize("path", ["/etc/passwd", "../outside.tif", "frames/../../outside.tif", "frames/../../../x"])
def test_session_manifest_paths_stay_in_the_session(workspace, tmp_path, path):
    session = tmp_path / "session"
    shutil.copytree(workspace / "session", session)
    (tmp_path / "outside.tif").write_bytes((session / "frames" / "dark.tif").read_bytes())
    manifest = json.loads((session / "manifest.json").read_text())
    manifest["frames"][0]["file"] = path
    (session / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="inside the folder"):
        io.load_session(session)


@pytest.mark.parametrize("state_file", ["/tmp/lamp.json", "../lamp.json", "sub/../../lamp.json"])
def test_profile_paths_stay_in_the_profiles_folder(tmp_path, state_file):
    profile = write_profile(tmp_path, extra=f'[lamp]\nstate_file = "{state_file}"\n')
    with pytest.raises(ValueError) as raised:
        hw_profile.load_profile(profile)
    assert "state_file" in str(raised.value) and "\n" not in str(raised.value)


def _victim(tmp_path) -> tuple[pathlib.Path, str]:
    victim = tmp_path / "victim.txt"
    victim.write_text("precious data outside OUT\n")
    return victim, hashlib.sha256(victim.read_bytes()).hexdigest()


@pytest.mark.parametrize("planted", [archive.LOCK_NAME, archive.MANIFEST_NAME])
def test_a_link_planted_as_the_lock_or_manifest_is_not_followed(cal, tmp_path, capsys, planted):
    io.write_frame(tmp_path / "a.tif", frame(np.random.default_rng(0)), channel_names=NAMES)
    victim, digest = _victim(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / planted).symlink_to(victim)
    argv = ["-q", "correct", "-c", str(cal), str(tmp_path / "a.tif"), "-o", str(out)]
    if planted == archive.MANIFEST_NAME:
        argv.append("--resume")
    status = cli.main(argv)
    err = capsys.readouterr().err
    assert status == cli.EXIT_BAD_INPUT, err
    assert err.count("\n") == 1 and planted in err and "symbolic link" in err and "Traceback" not in err
    assert hashlib.sha256(victim.read_bytes()).hexdigest() == digest
    assert (out / planted).is_symlink()


def test_a_tampered_manifest_cannot_remove_or_overwrite_files_outside_out(cal, tmp_path, capsys):
    """--resume reads OUT's manifest, which anyone may edit: outputs it names outside OUT are
    neither checked, removed nor rewritten."""
    (tmp_path / "in").mkdir()
    io.write_frame(tmp_path / "in" / "a.tif", frame(np.random.default_rng(0)), channel_names=NAMES)
    out = tmp_path / "out"
    argv = ["-q", "correct", "-c", str(cal), str(tmp_path / "in"), "-o", str(out)]
    assert cli.main(argv) == 0
    victim, digest = _victim(tmp_path)
    lines = (out / archive.MANIFEST_NAME).read_text().splitlines()
    record = json.loads(lines[-1])
    record["input"] = "../victim"
    record["outputs"] = {"../victim.txt": "0" * 64, **record["outputs"]}
    record["status"] = "failed"
    (out / archive.MANIFEST_NAME).write_text("\n".join([*lines, json.dumps(record)]) + "\n")
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name != archive.MANIFEST_NAME}
    assert cli.main([*argv, "--resume"]) == 0, capsys.readouterr().err
    assert hashlib.sha256(victim.read_bytes()).hexdigest() == digest
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name != archive.MANIFEST_NAME} == before


def test_temporary_files_never_write_through_a_planted_link(tmp_path, monkeypatch):
    """Temporary names are created with O_EXCL: a link waiting at the very name (here made
    predictable on purpose) fails the write, and the file it points at is untouched."""
    victim, digest = _victim(tmp_path)
    fixed = uuid.UUID(int=0)
    monkeypatch.setattr(uuid, "uuid4", lambda: fixed)
    target = tmp_path / "out.tif"
    (tmp_path / f".out.tif.{fixed.hex[:12]}.tmp").symlink_to(victim)
    with pytest.raises(io.SpherejaxFileError) as raised:
        io.write_frame(target, frame(np.random.default_rng(0)), channel_names=NAMES)
    assert "out.tif" in str(raised.value)
    (tmp_path / f".c.npz.{fixed.hex[:12]}.tmp").symlink_to(victim)
    with pytest.raises(io.SpherejaxFileError):
        io.save_calibration(
            tmp_path / "c.npz",
            spherejax.Calibration(dark=np.zeros((4, 4, 16), np.float32), white=np.ones((4, 4, 16), np.float32),
                                  patch=np.ones((4, 4), bool), coeffs=np.asarray(spherejax.identity_coeffs(16)),
                                  wiener=np.zeros((31, 16), np.float32)),
            instrument_id="x", band_centres_nm=list(range(400, 701, 20)),
        )
    assert hashlib.sha256(victim.read_bytes()).hexdigest() == digest
    assert not target.exists() and not (tmp_path / "c.npz").exists()
