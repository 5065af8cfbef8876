"""io.ownership.refuse_overlaps: an output is never an input, the calibration or another output,
however the path is spelled."""

from __future__ import annotations

import os

import pytest

from spherejax.io import SpherejaxFileError, refuse_overlaps


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "a.tif").write_bytes(b"cube")
    (tmp_path / "cal.h5").write_bytes(b"calibration")
    (tmp_path / "sub").mkdir()
    (tmp_path / "link.tif").symlink_to(tmp_path / "a.tif")
    os.link(tmp_path / "a.tif", tmp_path / "hard.tif")
    return tmp_path


def inputs(folder):
    return {"the input cube": folder / "a.tif", "the calibration": folder / "cal.h5"}


@pytest.mark.parametrize("spelling, what", [
    ("a.tif", "the input cube"), ("sub/../a.tif", "the input cube"), ("link.tif", "the input cube"),
    ("hard.tif", "the input cube"), ("cal.h5", "the calibration"),
])
def test_an_output_that_is_an_input_is_refused_naming_both(folder, spelling, what):
    output = folder / spelling
    with pytest.raises(SpherejaxFileError) as raised:
        refuse_overlaps({"OUT.csv": output}, inputs(folder))
    message = str(raised.value)
    assert message.startswith(f"{output}: OUT.csv is also {what} (")
    assert "expected OUT.csv a file of its own" in message and "\n" not in message


def test_a_relative_spelling_of_an_input_is_refused(folder, monkeypatch):
    monkeypatch.chdir(folder / "sub")
    with pytest.raises(SpherejaxFileError, match="--cgats FILE is also the input cube"):
        refuse_overlaps({"--cgats FILE": "../a.tif"}, inputs(folder))


def test_two_outputs_that_are_one_file_are_refused(folder):
    with pytest.raises(SpherejaxFileError, match="--cgats FILE is also OUT.csv"):
        refuse_overlaps({"OUT.csv": folder / "r.csv", "--cgats FILE": folder / "sub" / ".." / "r.csv"}, inputs(folder))


def test_distinct_files_pass_whether_or_not_they_exist(folder):
    (folder / "old.csv").write_text("an earlier result")
    refuse_overlaps({"OUT.csv": folder / "old.csv", "OUT.json": folder / "new.json", "--cgats FILE": folder / "qc.txt"},
                    inputs(folder))


def test_a_dangling_link_to_an_input_path_is_refused(folder):
    """A link whose target is the input's path resolves to it, present or not."""
    (folder / "later.tif").symlink_to(folder / "missing.tif")
    with pytest.raises(SpherejaxFileError, match="is also the input cube"):
        refuse_overlaps({"OUT.csv": folder / "later.tif"}, {"the input cube": folder / "missing.tif"})
