"""Documents and numbers read strictly (docs/reliability.md, section 1).

`json.loads` takes an object with a key given twice and keeps the last one: a session manifest
with two "instrument_id" (a hand edit gone wrong, a merge) was read as something its author did
not see. Every JSON document spherejax reads goes through `spherejax.jsontext`, which refuses a
duplicate key in one line naming it; a session manifest refuses NaN and Infinity, which are not
JSON and which spherejax never writes there.

Every number read from the command line has a documented bound at both ends
(`spherejax.cli.number_types`): finite is not enough, since 1e308 is finite and made `study`'s
objective infinite with exit status 0. `study_session` checks its own arguments and refuses a
result whose objective is not finite.
"""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest

from spherejax import cli, io, jsontext, study
from spherejax.cli import number_types as numbers
from tests.helpers import calibration_entries, write_calibration_entries
from tests.robustness.catalogue import Case, Folder, check_case, session_case

# --------------------------------------------------------------------------------------------
# The parser


@pytest.mark.parametrize("text, key", [
    ('{"a": 1, "a": 2}', "a"),
    ('{"frames": [{"id": "x", "file": "f.tif", "id": "y"}]}', "id"),
    ('[1, {"b": {"c": null, "c": null}}]', "c"),
    ('{"tab\\there": 1, "tab\\there": 2}', "tab\there"),  # JSON's escape: a real tab, shown escaped
])
def test_a_key_given_twice_is_refused_naming_it(text, key):
    with pytest.raises(jsontext.JSONTextError) as refused:
        jsontext.loads(text.encode())
    assert refused.value.problem == f"is not valid JSON: the key {key!r} appears twice in one object"
    assert "\n" not in refused.value.problem


def test_keys_that_differ_are_taken_as_before():
    assert jsontext.loads('{"a": 1, "A": 2, "b": {"a": 3}}') == {"a": 1, "A": 2, "b": {"a": 3}}
    assert jsontext.loads('[{"a": 1}, {"a": 2}]') == [{"a": 1}, {"a": 2}]


# --------------------------------------------------------------------------------------------
# The documents that carry one: through the command line, one line, exit 2, nothing written


def _duplicate_key(f: Folder) -> pathlib.Path:
    """The session's manifest with "instrument_id" given twice (the first one wrong)."""
    path = f.session() / "manifest.json"
    text = path.read_text()
    path.write_text(text.replace('"instrument_id"', '"instrument_id": "another-instrument", "instrument_id"', 1))
    return path


def _duplicate_key_in_a_frame(f: Folder) -> pathlib.Path:
    """A frame's entry with "file" given twice: the last one would silently pick another frame."""
    path = f.session() / "manifest.json"
    manifest = json.loads(path.read_text())
    frames = [json.dumps(frame) for frame in manifest["frames"]]
    frames[0] = frames[0][:-1] + ', "file": ' + json.dumps(manifest["frames"][1]["file"]) + "}"
    rest = json.dumps({key: value for key, value in manifest.items() if key != "frames"})
    path.write_text(rest[:-1] + ', "frames": [' + ", ".join(frames) + "]}")
    return path


def _nan_in_the_manifest(f: Folder) -> pathlib.Path:
    path = f.session() / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["metadata"] = {**manifest.get("metadata", {}), "temperature": float("nan")}
    path.write_text(json.dumps(manifest))  # Python's json writes NaN; JSON has no such value
    return path


def _calibration_header_with_a_duplicate_key(f: Folder) -> pathlib.Path:
    entries = calibration_entries(f.workspace / "cal.h5")
    header = bytes(entries["header"]).decode()
    assert header.startswith("{")
    header = '{"format_version": 1, ' + header[1:]  # the real one follows: the last would win
    entries["header"] = np.frombuffer(header.encode(), np.uint8)
    write_calibration_entries(f.tmp / "doubled.h5", entries)
    return f.tmp / "doubled.h5"


CASES = [
    session_case("manifest-duplicate-key-calibrate", _duplicate_key, "the key 'instrument_id' appears twice"),
    session_case("manifest-duplicate-key-evaluate", _duplicate_key, "the key 'instrument_id' appears twice",
                 command="evaluate"),
    session_case("manifest-duplicate-key-in-a-frame", _duplicate_key_in_a_frame, "the key 'file' appears twice"),
    session_case("manifest-nan", _nan_in_the_manifest, "NaN is not a JSON value"),
    Case("calibration-header-duplicate-key", "evaluate",
         lambda f: (["evaluate", str(f.session()), "-c", str(_calibration_header_with_a_duplicate_key(f)),
                     "--out", str(f.tmp / "evaluation")], str(f.tmp / "doubled.h5")),
         "the key 'format_version' appears twice"),
]


@pytest.mark.parametrize("case", CASES, ids=[case.id for case in CASES])
def test_a_document_with_a_key_given_twice_is_refused_in_one_line(case, workspace, cal, tmp_path, capsys):
    check_case(case, workspace, cal, tmp_path, capsys)


def test_the_lamp_state_and_an_earlier_runs_record_are_read_strictly(tmp_path):
    """Variants elsewhere: the instrument's lamp record (hw.lamp) and the record by which an
    earlier evaluate's tables are known to be spherejax's (io.ownership.earlier_run: a record
    with a key given twice proves nothing)."""
    from spherejax_hw.lamp import Lamp, LampStateError

    lamp = tmp_path / "lamp.json"
    lamp.write_text('{"hours": 10.0, "ignitions": 1, "hours": 0.0}')
    with pytest.raises(LampStateError, match="the key 'hours' appears twice"):
        Lamp(lamp).is_on
    record = tmp_path / "metrics.json"
    record.write_text('{"band_centres_nm": [], "markov_kappa": 1, "metrics": {}, "metrics": {}}')
    assert not io.ownership.earlier_run(record, {"band_centres_nm", "markov_kappa", "metrics"})
    record.write_text('{"band_centres_nm": [], "markov_kappa": 1, "metrics": {}}')
    assert io.ownership.earlier_run(record, {"band_centres_nm", "markov_kappa", "metrics"})


def test_a_batch_manifest_line_with_a_key_given_twice_is_no_record(tmp_path):
    """OUT's manifest is read line by line; a line with a key given twice is damage, like a torn
    line: it records nothing (so its outputs are not taken for spherejax's either)."""
    from spherejax import archive

    out = tmp_path / "out"
    out.mkdir()
    good = {"name": "a", "status": "failed", "source": "a.tif", "reason": "x", "outputs": {}}
    doubled = json.dumps(good)[:-1] + ', "name": "b"}'
    (out / archive.MANIFEST_NAME).write_text(json.dumps(good) + "\n" + doubled + "\n")
    assert list(archive.read_manifest(out)) == ["a"]


# --------------------------------------------------------------------------------------------
# Numbers: bounded at both ends, at the command line and in the API


@pytest.mark.parametrize("argv, option", [
    (["study", "S", "--response-weight", "1e308"], "--response-weight"),
    (["study", "S", "--response-weight", "1e7"], "--response-weight"),
    (["study", "S", "--max-steps", str(10**12)], "--max-steps"),
    (["calibrate", "S", "-o", "c.h5", "--gain", "1e308"], "--gain"),
    (["calibrate", "S", "-o", "c.h5", "--gain", "1e-300"], "--gain"),
    (["calibrate", "S", "-o", "c.h5", "--read-noise", "1e300"], "--read-noise"),
    (["calibrate", "S", "-o", "c.h5", "--white-reflectance-u", "2"], "--white-reflectance-u"),
    (["measure", "-c", "c.h5", "i.tif", "--region", "a=0,1,0,1", "--gain", "3e38"], "--gain"),
    (["measure", "-c", "c.h5", "i.tif", "--region", "a=0,1,0,1", "--read-noise", "1e5"], "--read-noise"),
    (["measure", "-c", "c.h5", "i.tif", "--region", "a=0,1,0,1", "--reference", "1e30,0,0"], "--reference"),
    (["measure", "-c", "c.h5", "i.tif", "--region", "a=0,1,0,1", "--reference", "50,0,-1e308"], "--reference"),
])
def test_a_finite_number_beyond_its_options_bound_is_refused_in_one_line(argv, option, tmp_path, capsys, monkeypatch):
    """1e308 is finite: it passed, and `study` exited 0 with an infinite objective; a gain of
    3e38 is infinite in the float32 a noise model holds; a reference L* of 1e30 gave ΔE00 NaN with
    exit status 0. Each option's bounds are in --help."""
    monkeypatch.chdir(tmp_path)
    status = cli.main(argv)
    err = capsys.readouterr().err
    assert status == 2, err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"spherejax: error: {option}") and "expected" in lines[0], err
    assert list(tmp_path.iterdir()) == []


def test_every_bound_is_in_the_help():
    helps = {(name, a.option_strings[-1]): a.help for name, p in _subparsers().items() for a in p._actions
             if isinstance(a.type, numbers.NumberType) and a.option_strings[-1] != "--workers"}
    for (name, option), text in helps.items():
        kind = next(a.type for a in _subparsers()[name]._actions if a.option_strings and a.option_strings[-1] == option)
        low_high = kind.kind.split()[-1]  # "0..65536", "1..100000", "0..9223372036854775807"
        assert ".." in low_high, (name, option, kind.kind)
        assert low_high.split("..")[1] in text.replace("2**24", "16777216").replace("2**63 - 1", "9223372036854775807"), \
            (name, option, text)


def _subparsers():
    import argparse

    parser = cli.build_parser()
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def test_the_command_lines_bounds_are_the_apis():
    assert numbers.RESPONSE_WEIGHT_MAX == study.RESPONSE_WEIGHT_MAX
    assert numbers.MAX_STEPS_MAX == study.MAX_STEPS_MAX


@pytest.mark.parametrize("options, problem", [
    ({"response_weight": 1e308}, "response_weight"),
    ({"response_weight": float("nan")}, "response_weight"),
    ({"response_weight": -1.0}, "response_weight"),
    ({"response_weight": True}, "response_weight"),
    ({"max_steps": 0}, "max_steps"),
    ({"max_steps": 10**12}, "max_steps"),
    ({"max_steps": 2.5}, "max_steps"),
])
def test_study_session_refuses_arguments_out_of_range_before_any_work(options, problem):
    """Checked first: no session is even looked at (None would fail at once otherwise)."""
    with pytest.raises(ValueError, match=f"^{problem}: expected"):
        study.study_session(None, None, **options)


def test_study_session_refuses_an_objective_that_is_not_finite(workspace, monkeypatch):
    """Whatever makes it so (colours that overflow), study.json never records inf as a result."""
    import jax.numpy as jnp

    session = io.load_session(workspace / "session")
    calibration, _ = io.load_calibration(workspace / "cal.h5")
    monkeypatch.setattr(study, "_objective", lambda params, problem: jnp.sum(params["coeffs"]) * jnp.inf)
    with pytest.raises(ValueError, match=r"the objective is (inf|nan) at the start .* expected a finite mean"):
        study.study_session(session, calibration, max_steps=1)


def test_the_kernel_timings_cache_with_a_key_given_twice_is_not_spherejaxs(tmp_path):
    """The engine's cache of kernel timings (`_engine.variant_cache`) is a document spherejax
    reads too: one with "machines" given twice is not the file it wrote, and is left alone."""
    from spherejax._engine import variant_cache

    path = tmp_path / "timings.json"
    path.write_text(json.dumps({"format": variant_cache.FORMAT, "machines": {}})[:-1] + ', "machines": {"m": {}}}')
    assert variant_cache._read(path) is None
    path.write_text(json.dumps({"format": variant_cache.FORMAT, "machines": {"m": {}}}))
    assert variant_cache._read(path) == {"m": {}}
