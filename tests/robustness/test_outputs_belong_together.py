"""The outputs `open_corrected` puts in one Dataset are one correction's (`spherejax.io.corrected`):
a Lab, quality mask or preview beside the reflectance that another input, another calibration or
another illuminant made is refused in one line naming both files; outputs of one correction open
as they did, and so do older outputs that carry no output set."""

from __future__ import annotations

import os
import pathlib
import shutil

import numpy as np
import pytest

import spherejax
from spherejax import archive, io
from spherejax.io.corrected import OUTPUT_SET_ATTRIBUTE

from tests.batch_support import frame, make_calibration, read_exr


@pytest.fixture(scope="module")
def batches(cal, tmp_path_factory):
    """Two inputs a and b corrected into OUT (EXR) and ENVI, and a again with another calibration
    and under illuminant A."""
    root = tmp_path_factory.mktemp("together")
    rng = np.random.default_rng(21)
    (root / "in").mkdir()
    for name in ("a", "b"):
        io.write_frame(root / "in" / f"{name}.tif", frame(rng))
    other = root / "other.h5"
    calibration, bands, instrument = make_calibration(np.random.default_rng(77))
    io.save_calibration(other, calibration, instrument_id=instrument, band_centres_nm=bands)
    archive.run_batch([root / "in"], root / "exr", cal)
    archive.run_batch([root / "in"], root / "envi", cal, output_format="envi")
    archive.run_batch([root / "in" / "a.tif"], root / "other_cal", other)
    archive.run_batch([root / "in" / "a.tif"], root / "under_a", cal, illuminant="A")
    return root


def _copy_of(batches: pathlib.Path, tmp_path: pathlib.Path, name: str) -> pathlib.Path:
    target = tmp_path / name
    shutil.copytree(batches / name, target)
    return target / "in"


def _refused(path, other: pathlib.Path, reflectance: pathlib.Path):
    with pytest.raises(io.SpherejaxFileError) as refused:
        spherejax.open_corrected(path)
    message = str(refused.value)
    assert "\n" not in message
    assert message.startswith(f"{other}: is not an output of the correction {reflectance} is from"), message
    return message


@pytest.mark.parametrize("kind", ["lab.exr", "quality.png", "preview.png"])
def test_another_inputs_output_beside_the_reflectance_is_refused(batches, tmp_path, kind):
    folder = _copy_of(batches, tmp_path, "exr")
    shutil.copyfile(folder / f"b.{kind}", folder / f"a.{kind}")
    for given in (folder / "a", folder / "a.reflectance.exr", folder / f"a.{kind}"):
        _refused(given, folder / f"a.{kind}", folder / "a.reflectance.exr")


@pytest.mark.parametrize("kind", ["lab", "quality.png"])
def test_another_inputs_output_beside_an_envi_reflectance_is_refused(batches, tmp_path, kind):
    folder = _copy_of(batches, tmp_path, "envi")
    if kind == "lab":
        for suffix in ("hdr", "img"):
            shutil.copyfile(folder / f"b.lab.{suffix}", folder / f"a.lab.{suffix}")
        other = folder / "a.lab.hdr"
    else:
        shutil.copyfile(folder / f"b.{kind}", folder / f"a.{kind}")
        other = folder / f"a.{kind}"
    _refused(folder / "a", other, folder / "a.reflectance.hdr")


@pytest.mark.parametrize(("made", "kind"), [("other_cal", "lab.exr"), ("other_cal", "quality.png"),
                                             ("other_cal", "preview.png"), ("under_a", "lab.exr")])
def test_the_same_inputs_output_of_another_correction_is_refused(batches, tmp_path, made, kind):
    """Another calibration, or Lab under another illuminant: the same input, another correction."""
    folder = _copy_of(batches, tmp_path, "exr")
    shutil.copyfile(batches / made / f"a.{kind}", folder / f"a.{kind}")
    message = _refused(folder / "a", folder / f"a.{kind}", folder / "a.reflectance.exr")
    assert ("spherejax:illuminant is A, the reflectance's D65" in message) == (made == "under_a")


def test_what_the_illuminant_does_not_change_goes_with_either(batches, tmp_path):
    """The reflectance, quality mask and preview do not depend on the Lab illuminant: those of a
    run under A are the same correction's as those of a run under D65 (the PNGs the same bytes)."""
    folder = _copy_of(batches, tmp_path, "exr")
    for kind in ("quality.png", "preview.png"):
        assert (batches / "under_a" / f"a.{kind}").read_bytes() == (folder / f"a.{kind}").read_bytes()
    shutil.copyfile(batches / "under_a" / "a.lab.exr", folder / "a.lab.exr")
    shutil.copyfile(batches / "under_a" / "a.reflectance.exr", folder / "a.reflectance.exr")
    dataset = spherejax.open_corrected(folder / "a")
    assert dataset.attrs["spherejax:illuminant"] == "A"


def test_one_corrections_outputs_open_and_carry_one_output_set(batches):
    folder = batches / "exr" / "in"
    dataset = spherejax.open_corrected(folder / "a")
    assert set(dataset.data_vars) == {"reflectance", "lab", "quality"}
    output_set = dataset.attrs[OUTPUT_SET_ATTRIBUTE]
    assert output_set.startswith("sha256:")
    assert read_exr(folder / "a.lab.exr")[2][OUTPUT_SET_ATTRIBUTE] == output_set
    from PIL import PngImagePlugin

    for png in ("a.quality.png", "a.preview.png"):
        with PngImagePlugin.PngImageFile(folder / png) as image:
            assert image.text[OUTPUT_SET_ATTRIBUTE] == output_set
    assert read_exr(batches / "exr" / "in" / "b.reflectance.exr")[2][OUTPUT_SET_ATTRIBUTE] != output_set
    envi = spherejax.open_corrected(batches / "envi" / "in" / "a")
    assert envi.attrs[OUTPUT_SET_ATTRIBUTE] == output_set  # the same correction, in another format
    np.testing.assert_array_equal(envi["lab"].values, dataset["lab"].values)


def test_a_rerun_writes_the_same_bytes(batches, cal, tmp_path):
    """The output set is made of what makes the outputs, never a time: a rerun's bytes are the same."""
    archive.run_batch([batches / "in"], tmp_path / "again", cal)
    for name in sorted(os.listdir(batches / "exr" / "in")):
        assert (tmp_path / "again" / "in" / name).read_bytes() == (batches / "exr" / "in" / name).read_bytes(), name


def _older_outputs(folder: pathlib.Path, stem: str, input_sha256: str, reflectance: np.ndarray) -> None:
    """Outputs as spherejax wrote them before the output set: the same attributes in both EXRs,
    none in the quality PNG."""
    attributes = {"spherejax:calibration_checksum": "sha256:" + "1" * 64, "spherejax:software_version": "0.9.0",
                  "spherejax:source": f"{stem}.tif", "spherejax:input_sha256": input_sha256,
                  "spherejax:illuminant": "D65"}
    names = [f"T.{nm}nm" for nm in range(400, 701, 10)]
    io.write_exr(folder / f"{stem}.reflectance.exr", reflectance, channel_names=names,
                 attributes={"spectralLayoutVersion": "1.0", **attributes})
    io.write_exr(folder / f"{stem}.lab.exr", reflectance[..., :3].copy(), channel_names=["L*", "a*", "b*"],
                 attributes=attributes)
    io.write_quality_png(folder / f"{stem}.quality.png", np.zeros(reflectance.shape[:2], np.uint8))


def test_older_outputs_without_an_output_set_still_open(tmp_path):
    reflectance = np.random.default_rng(3).uniform(0, 1, (8, 10, 31)).astype(np.float32)
    _older_outputs(tmp_path, "a", "sha256:" + "a" * 64, reflectance)
    dataset = spherejax.open_corrected(tmp_path / "a")
    assert set(dataset.data_vars) == {"reflectance", "lab", "quality"}
    assert OUTPUT_SET_ATTRIBUTE not in dataset.attrs
    np.testing.assert_array_equal(dataset["reflectance"].values, reflectance)


def test_older_outputs_of_another_input_are_refused_by_the_input_they_name(tmp_path):
    """No output set on either side: the attributes both carry are compared (the input's SHA-256)."""
    reflectance = np.random.default_rng(3).uniform(0, 1, (8, 10, 31)).astype(np.float32)
    _older_outputs(tmp_path, "a", "sha256:" + "a" * 64, reflectance)
    (tmp_path / "b").mkdir()
    _older_outputs(tmp_path / "b", "a", "sha256:" + "b" * 64, reflectance)
    shutil.copyfile(tmp_path / "b" / "a.lab.exr", tmp_path / "a.lab.exr")
    message = _refused(tmp_path / "a", tmp_path / "a.lab.exr", tmp_path / "a.reflectance.exr")
    assert "spherejax:input_sha256" in message


def test_an_older_output_of_another_input_beside_a_new_one_is_refused(batches, tmp_path):
    """A Lab with no output set beside a reflectance that has one (or the other way round) is
    checked for what it carries: another input's is refused."""
    folder = _copy_of(batches, tmp_path, "exr")
    reflectance = np.zeros((40, 48, 31), np.float32)
    (tmp_path / "old").mkdir()
    _older_outputs(tmp_path / "old", "a", "sha256:" + "a" * 64, reflectance)
    shutil.copyfile(tmp_path / "old" / "a.lab.exr", folder / "a.lab.exr")
    message = _refused(folder / "a", folder / "a.lab.exr", folder / "a.reflectance.exr")
    assert "spherejax:input_sha256 is sha256:aaaa" in message
    shutil.copyfile(tmp_path / "old" / "a.reflectance.exr", folder / "b.reflectance.exr")
    _refused(folder / "b", folder / "b.lab.exr", folder / "b.reflectance.exr")
