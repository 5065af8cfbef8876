"""The instrument profile (hw.profile): the issue's example loads, and every bad profile is refused
with one line naming the file, the key and what was expected, before any device is opened."""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import pathlib

import pytest

from spherejax_hw.profile import (
    WHEEL_POSITIONS,
    AcquisitionSettings,
    CameraConfig,
    Layout,
    ProfileError,
    SamplePlan,
    ShutterConfig,
    load_profile,
)

from tests.hw.profiles import BANDS, check_message, example, write

# The profile as the issue's acceptance checks write it (comments included), 8 bands per wheel.
EXAMPLE = """\
[instrument]
id = "sphere-1"
[wheels.a]
port = "/dev/ttyUSB0"     # any pyserial URL
model = "FW212C"
open_slot = 12
[wheels.b]
port = "/dev/ttyUSB1"
model = "FW212C"
open_slot = 12
[shutter]
port = "/dev/ttyUSB2"
model = "SC10"
[camera]
backend = "sim"
[bands]                   # band centre in nm = [wheel, slot]
""" + "".join(
    f'{nm} = ["{"a" if i < 8 else "b"}", {i % 8 + 1}]\n' for i, nm in enumerate(BANDS)
)


@pytest.fixture
def folder(tmp_path) -> pathlib.Path:
    """The profile's folder, one level below tmp_path so that tmp_path is "outside" it."""
    path = tmp_path / "instrument"
    path.mkdir()
    return path


# -- the good profile ------------------------------------------------------------------------------


def test_writer_round_trips_the_example(folder):
    # The catalogue below writes profiles with `dump`; it must give the issue's literal text.
    written = load_profile(write(folder, example()))
    literal = load_profile(write(folder, EXAMPLE, "literal.toml"))
    assert written == dataclasses.replace(literal, path=written.path, lamp_state_file=written.lamp_state_file)


def test_issue_example_loads(folder):
    path = write(folder, EXAMPLE)
    profile = load_profile(path)

    assert profile.path == path
    assert profile.instrument_id == "sphere-1"
    assert list(profile.wheels) == ["a", "b"]
    for name, port in (("a", "/dev/ttyUSB0"), ("b", "/dev/ttyUSB1")):
        wheel = profile.wheels[name]
        assert (wheel.name, wheel.port, wheel.model, wheel.open_slot) == (name, port, "FW212C", 12)
        assert wheel.positions == WHEEL_POSITIONS["FW212C"] == 12
    assert profile.shutter == ShutterConfig(port="/dev/ttyUSB2", model="SC10")
    assert profile.camera == CameraConfig("sim", {})

    assert profile.band_centres_nm == list(range(400, 701, 20))
    assert len(profile.bands) == 16
    assert profile.bands[400] == ("a", 1)
    assert profile.bands[540] == ("a", 8)
    assert profile.bands[560] == ("b", 1)
    assert profile.bands[700] == ("b", 8)
    assert sum(wheel == "a" for wheel, _ in profile.bands.values()) == 8

    assert profile.acquisition == AcquisitionSettings()
    assert profile.acquisition.frames_averaged == 16 and profile.acquisition.dark_frames == 16
    assert profile.acquisition.target_level == 0.8 and profile.acquisition.target_percentile == 99.5
    assert profile.acquisition.warmup_checks == 6 and profile.acquisition.warmup_interval_s == 30.0
    assert profile.layout == Layout() and profile.layout.white_patch is None and profile.layout.holder is None
    assert profile.lamp_state_file == (folder / "profile.lamp.json").resolve()
    assert profile.samples == ()


def test_positions_for_puts_one_filter_in_the_path(folder):
    profile = load_profile(write(folder, EXAMPLE))
    assert profile.positions_for(400) == {"a": 1, "b": 12}
    assert profile.positions_for(540) == {"a": 8, "b": 12}
    assert profile.positions_for(560) == {"a": 12, "b": 1}
    assert profile.positions_for(700) == {"a": 12, "b": 8}
    for band in profile.band_centres_nm:
        assert profile.band_at(profile.positions_for(band)) == band
    with pytest.raises(KeyError):
        profile.positions_for(410)


@pytest.mark.parametrize(
    ("positions", "band"),
    [
        ({"a": 1, "b": 12}, 400),
        ({"a": 12, "b": 3}, 600),
        ({"a": 12, "b": 12}, None),  # no filter in the path
        ({"a": 1, "b": 1}, None),  # two filters in the path
        ({"a": 9, "b": 12}, None),  # a slot that holds no band
        ({"a": 1}, None),  # a wheel's position unknown
        ({"a": 1, "b": 12, "c": 12}, None),  # a wheel the profile does not define
    ],
)
def test_band_at(folder, positions, band):
    assert load_profile(write(folder, EXAMPLE)).band_at(positions) == band


def test_optional_sections_parse(folder):
    data = example()
    data["camera"] = {"backend": "sim", "seed": 3, "image_shape": [96, 136], "name": "bench"}
    data["acquisition"] = {
        "frames_averaged": 4, "dark_frames": 20, "target_level": 0.7, "target_percentile": 99,
        "warmup_drift_percent": 1, "warmup_interval_s": 0, "warmup_checks": 2, "warmup_timeout_s": 60,
    }
    data["layout"] = {"white_patch": [10, 20, 10, 20], "holder": [40, 160, 30, 240]}
    (folder / "state").mkdir()
    data["lamp"] = {"state_file": "state/lamp.json"}
    data["samples"] = [
        {"id": "s001", "set": "test", "background": "black velvet"},
        {"id": "s002", "set": "training"},
        {"id": "s.003_x-y"},
    ]
    profile = load_profile(write(folder, data))

    assert profile.camera == CameraConfig("sim", {"seed": 3, "image_shape": [96, 136], "name": "bench"})
    assert profile.acquisition == AcquisitionSettings(
        frames_averaged=4, dark_frames=20, target_level=0.7, target_percentile=99.0,
        warmup_drift_percent=1.0, warmup_interval_s=0.0, warmup_checks=2, warmup_timeout_s=60.0,
    )
    assert isinstance(profile.acquisition.target_percentile, float)
    assert profile.layout == Layout(white_patch=(10, 20, 10, 20), holder=(40, 160, 30, 240))
    assert profile.lamp_state_file == (folder / "state" / "lamp.json").resolve()
    assert profile.samples == (
        SamplePlan("s001", "test", "black velvet"),
        SamplePlan("s002", "training", "unknown"),
        SamplePlan("s.003_x-y", "test", "unknown"),
    )


def test_a_registration_target_in_the_plan(folder):
    """role = "registration" marks the plan's registration target, which has no set or
    background; the other entries are samples, as without a role."""
    data = example()
    data["samples"] = [
        {"id": "s001", "set": "training"},
        {"id": "checkerboard", "role": "registration"},
        {"id": "s002", "role": "sample", "background": "black velvet"},
    ]
    assert load_profile(write(folder, data)).samples == (
        SamplePlan("s001", "training", "unknown"),
        SamplePlan("checkerboard", None, None, "registration"),
        SamplePlan("s002", "test", "black velvet"),
    )


def test_bands_come_out_in_increasing_order(folder):
    data = example()
    data["bands"] = dict(reversed(list(data["bands"].items())))
    assert load_profile(write(folder, data)).band_centres_nm == BANDS


def test_mixed_models_and_a_real_camera_with_layout(folder):
    data = example()
    data["wheels"]["b"] = {"port": "loop://", "model": "FW102C", "open_slot": 6, "move_timeout_s": 5}
    data["bands"] = {"400": ["a", 1], "420": ["b", 5], "440": ["b", 1]}
    data["camera"] = {"backend": "pvcam", "camera_name": "PMUSBCam00", "exposure_s": 0.1}
    data["layout"] = {"white_patch": [0, 5, 0, 5], "holder": [10, 100, 10, 100]}
    profile = load_profile(write(folder, data))
    assert profile.wheels["b"].positions == 6
    assert profile.positions_for(420) == {"a": 12, "b": 5}
    assert profile.camera == CameraConfig("pvcam", {"camera_name": "PMUSBCam00", "exposure_s": 0.1})


# -- the catalogue of bad profiles -----------------------------------------------------------------


def _without(*keys):
    """Remove the nested key keys[-1] from the table at keys[:-1]."""

    def change(data, folder):
        table = data
        for key in keys[:-1]:
            table = table[key]
        del table[keys[-1]]

    return change


def _set(*keys, value):
    def change(data, folder):
        table = data
        for key in keys[:-1]:
            table = table.setdefault(key, {})
        table[keys[-1]] = copy.deepcopy(value)

    return change


def _rename(*keys, to):
    def change(data, folder):
        table = data
        for key in keys[:-1]:
            table = table[key]
        table[to] = table.pop(keys[-1])

    return change


def _all(*changes):
    def change(data, folder):
        for one in changes:
            one(data, folder)

    return change


def _lamp_symlink_to_outside_file(data, folder):
    outside = folder.parent / "elsewhere.json"
    outside.write_text("{}")
    (folder / "lamp.json").symlink_to(outside)
    data["lamp"] = {"state_file": "lamp.json"}


def _lamp_in_symlinked_folder(data, folder):
    outside = folder.parent / "elsewhere"
    outside.mkdir()
    (folder / "state").symlink_to(outside, target_is_directory=True)
    data["lamp"] = {"state_file": "state/lamp.json"}


# (id, change, offending key, a fragment of the message saying what was expected)
BAD = [
    # required keys missing
    ("missing-instrument", _without("instrument"), "instrument", "a table"),
    ("missing-instrument.id", _without("instrument", "id"), "instrument.id", "a non-empty string"),
    ("missing-wheels", _without("wheels"), "wheels", "a table"),
    ("empty-wheels", _set("wheels", value={}), "wheels", "[wheels.NAME] tables"),
    ("missing-wheels.a.port", _without("wheels", "a", "port"), "wheels.a.port", "serial port"),
    ("missing-wheels.b.port", _without("wheels", "b", "port"), "wheels.b.port", "serial port"),
    ("missing-wheels.a.model", _without("wheels", "a", "model"), "wheels.a.model", "FW102C"),
    ("missing-wheels.a.open_slot", _without("wheels", "a", "open_slot"), "wheels.a.open_slot", "a slot 1..12"),
    ("missing-shutter", _without("shutter"), "shutter", "a table"),
    ("missing-shutter.port", _without("shutter", "port"), "shutter.port", "serial port"),
    ("missing-shutter.model", _without("shutter", "model"), "shutter.model", "SC10"),
    ("missing-camera", _without("camera"), "camera", "a table"),
    ("missing-camera.backend", _without("camera", "backend"), "camera.backend", "sim"),
    ("missing-bands", _without("bands"), "bands", "a table"),
    ("empty-bands", _set("bands", value={}), "bands", "NM = [WHEEL, SLOT]"),
    # unknown keys (typos)
    ("typo-top-level", _rename("instrument", to="instrumnet"), "instrumnet", "one of"),
    ("typo-top-level-section", _set("acquisiton", value={"frames_averaged": 4}), "acquisiton", "acquisition"),
    ("typo-top-level-scalar", _set("id", value="sphere-1"), "id", "one of"),
    ("typo-in-wheel", _rename("wheels", "a", "open_slot", to="open_solt"), "wheels.a.open_solt", "open_slot"),
    ("typo-in-wheel-b", _set("wheels", "b", "baud", value=9600), "wheels.b.baud", "port"),
    ("typo-in-instrument", _set("instrument", "name", value="x"), "instrument.name", "id"),
    ("typo-in-shutter", _set("shutter", "prot", value="/dev/x"), "shutter.prot", "port"),
    ("typo-in-acquisition", _set("acquisition", "frames", value=4), "acquisition.frames", "frames_averaged"),
    ("typo-in-layout", _set("layout", "white", value=[0, 1, 0, 1]), "layout.white", "white_patch"),
    ("typo-in-lamp", _set("lamp", "statefile", value="x.json"), "lamp.statefile", "state_file"),
    ("typo-in-sample", _set("samples", value=[{"id": "s1", "backgroud": "velvet"}]), "samples[0].backgroud", "background"),
    # the band -> (wheel, slot) mapping
    ("two-bands-one-slot", _set("bands", "420", value=["a", 1]), "bands.420", "one band per slot"),
    ("two-bands-one-slot-b", _set("bands", "700", value=["b", 1]), "bands.700", "one band per slot"),
    ("slot-13-on-FW212C", _set("bands", "420", value=["a", 13]), "bands.420", "a slot 1..12 of its FW212C"),
    ("slot-0", _set("bands", "420", value=["a", 0]), "bands.420", "a slot 1..12"),
    ("slot-7-on-FW102C",
     _all(_set("wheels", "b", value={"port": "/dev/ttyUSB1", "model": "FW102C", "open_slot": 6}),
          _set("bands", value={"400": ["a", 1], "560": ["b", 1], "580": ["b", 7]})),
     "bands.580", "a slot 1..6 of its FW102C"),
    ("band-on-open-slot", _set("bands", "400", value=["a", 12]), "bands.400", "a slot holding a filter"),
    ("band-on-undefined-wheel", _set("bands", "400", value=["c", 1]), "bands.400", "['a', 'b']"),
    ("band-key-blue", _set("bands", "blue", value=["a", 9]), "bands.blue", "an integer wavelength in nm"),
    ("band-key-40", _set("bands", "40", value=["a", 9]), "bands.40", "an integer wavelength in nm"),
    ("band-key-0400", _set("bands", "0400", value=["a", 9]), "bands.0400", "an integer wavelength in nm"),
    ("band-key-fraction", _set("bands", "410.5", value=["a", 9]), "bands.410.5", "an integer wavelength in nm"),
    ("band-value-one-item", _set("bands", "400", value=["a"]), "bands.400", "[wheel, slot]"),
    ("band-value-swapped", _set("bands", "400", value=[1, "a"]), "bands.400", "[wheel, slot]"),
    ("band-value-string", _set("bands", "400", value="a1"), "bands.400", "[wheel, slot]"),
    ("band-value-bool-slot", _set("bands", "400", value=["a", True]), "bands.400", "[wheel, slot]"),
    ("band-value-float-slot", _set("bands", "400", value=["a", 1.0]), "bands.400", "[wheel, slot]"),
    # wrong types and values
    ("port-is-int", _set("wheels", "b", "port", value=5), "wheels.b.port", "serial port"),
    ("port-is-empty", _set("wheels", "a", "port", value=""), "wheels.a.port", "serial port"),
    ("open_slot-is-string", _set("wheels", "a", "open_slot", value="12"), "wheels.a.open_slot", "a slot 1..12"),
    ("open_slot-is-bool", _set("wheels", "a", "open_slot", value=True), "wheels.a.open_slot", "a slot 1..12"),
    ("open_slot-is-float", _set("wheels", "a", "open_slot", value=12.0), "wheels.a.open_slot", "a slot 1..12"),
    ("open_slot-0", _set("wheels", "a", "open_slot", value=0), "wheels.a.open_slot", "a slot 1..12 of the FW212C"),
    ("open_slot-13", _set("wheels", "b", "open_slot", value=13), "wheels.b.open_slot", "a slot 1..12 of the FW212C"),
    ("open_slot-7-FW102C", _set("wheels", "b", value={"port": "p", "model": "FW102C", "open_slot": 7}),
     "wheels.b.open_slot", "a slot 1..6 of the FW102C"),
    ("move_timeout-bool", _set("wheels", "a", "move_timeout_s", value=True), "wheels.a.move_timeout_s", "seconds > 0"),
    ("unknown-wheel-model", _set("wheels", "a", "model", value="FW103C"), "wheels.a.model", "FW212C"),
    ("lower-case-wheel-model", _set("wheels", "b", "model", value="fw212c"), "wheels.b.model", "FW212C"),
    ("unknown-shutter-model", _set("shutter", "model", value="SC20"), "shutter.model", "SC10"),
    ("unknown-camera-backend", _set("camera", "backend", value="andor"), "camera.backend", "pvcam"),
    ("wheel-not-a-table", _set("wheels", "a", value="FW212C"), "wheels.a", "a table"),
    ("camera-not-a-table", _set("camera", value="sim"), "camera", "a table"),
    ("instrument.id-empty", _set("instrument", "id", value=""), "instrument.id", "a non-empty string"),
    ("instrument.id-int", _set("instrument", "id", value=1), "instrument.id", "a non-empty string"),
    # [acquisition] out of range
    ("frames_averaged-0", _set("acquisition", "frames_averaged", value=0), "acquisition.frames_averaged", "an integer >= 1"),
    ("frames_averaged-float", _set("acquisition", "frames_averaged", value=1.5), "acquisition.frames_averaged", "an integer >= 1"),
    ("dark_frames-negative", _set("acquisition", "dark_frames", value=-1), "acquisition.dark_frames", "an integer >= 1"),
    ("target_level-1", _set("acquisition", "target_level", value=1.0), "acquisition.target_level", "(0, 1)"),
    ("target_level-0", _set("acquisition", "target_level", value=0), "acquisition.target_level", "(0, 1)"),
    ("target_level-nan", _set("acquisition", "target_level", value=math.nan), "acquisition.target_level", "(0, 1)"),
    ("target_level-string", _set("acquisition", "target_level", value="0.8"), "acquisition.target_level", "(0, 1)"),
    ("target_percentile-0", _set("acquisition", "target_percentile", value=0), "acquisition.target_percentile", "(0, 100]"),
    ("target_percentile-101", _set("acquisition", "target_percentile", value=101), "acquisition.target_percentile", "(0, 100]"),
    ("warmup_drift_percent-0", _set("acquisition", "warmup_drift_percent", value=0), "acquisition.warmup_drift_percent", "> 0"),
    ("warmup_drift_percent-bool", _set("acquisition", "warmup_drift_percent", value=True), "acquisition.warmup_drift_percent", "> 0"),
    ("warmup_interval_s-negative", _set("acquisition", "warmup_interval_s", value=-1), "acquisition.warmup_interval_s", ">= 0"),
    ("warmup_checks-0", _set("acquisition", "warmup_checks", value=0), "acquisition.warmup_checks", "an integer >= 1"),
    ("warmup_timeout_s-0", _set("acquisition", "warmup_timeout_s", value=0), "acquisition.warmup_timeout_s", "> 0"),
    ("warmup_timeout_s-inf", _set("acquisition", "warmup_timeout_s", value=math.inf), "acquisition.warmup_timeout_s", "> 0"),
    ("acquisition-not-a-table", _set("acquisition", value=16), "acquisition", "a table"),
    # [layout] rectangles
    ("layout-rows-reversed", _set("layout", "white_patch", value=[20, 10, 10, 20]), "layout.white_patch", "r0 < r1"),
    ("layout-empty-columns", _set("layout", "holder", value=[40, 160, 30, 30]), "layout.holder", "c0 < c1"),
    ("layout-three-numbers", _set("layout", "white_patch", value=[10, 20, 10]), "layout.white_patch", "[r0, r1, c0, c1]"),
    ("layout-negative", _set("layout", "holder", value=[-1, 160, 30, 240]), "layout.holder", "[r0, r1, c0, c1]"),
    ("layout-floats", _set("layout", "holder", value=[1.0, 160.0, 30.0, 240.0]), "layout.holder", "integers"),
    ("layout-string", _set("layout", "white_patch", value="10:20,10:20"), "layout.white_patch", "[r0, r1, c0, c1]"),
    ("pvcam-without-layout", _set("camera", "backend", value="pvcam"), "layout", "white_patch and holder"),
    ("pvcam-half-layout", _all(_set("camera", "backend", value="pvcam"), _set("layout", "white_patch", value=[0, 1, 0, 1])),
     "layout", "white_patch and holder"),
    # [camera] options: only those the backend's constructor takes (hw.camera.PROFILE_OPTIONS),
    # each of the right type; before, these ended in a TypeError once the devices were open
    ("camera-option-unknown", _set("camera", "noise", value=0.5), "camera.noise", "an option of the 'sim' backend: one of ['image_shape', 'name', 'seed']"),
    ("camera-option-of-the-other-backend", _all(_set("camera", "backend", value="pvcam"), _set("camera", "seed", value=1)),
     "camera.seed", "an option of the 'pvcam' backend: one of ['camera_name', 'exposure_s']"),
    ("pvcam-name-not-camera_name", _all(_set("camera", "backend", value="pvcam"), _set("camera", "name", value="PMUSBCam00")),
     "camera.name", "camera_name"),
    ("sim-option-set-by-acquire", _set("camera", "light_path", value="a"), "camera.light_path", "one of ['image_shape', 'name', 'seed']"),
    ("camera-seed-string", _set("camera", "seed", value="3"), "camera.seed", "an integer 0..4294967295"),
    ("camera-seed-negative", _set("camera", "seed", value=-1), "camera.seed", "an integer 0..4294967295"),
    ("camera-seed-bool", _set("camera", "seed", value=True), "camera.seed", "an integer"),
    ("camera-image_shape-three", _set("camera", "image_shape", value=[96, 136, 1]), "camera.image_shape", "[height, width]"),
    ("camera-image_shape-zero", _set("camera", "image_shape", value=[0, 136]), "camera.image_shape", "integers >= 1"),
    ("camera-name-empty", _set("camera", "name", value=""), "camera.name", "a non-empty string"),
    ("pvcam-exposure-zero", _all(_set("camera", "backend", value="pvcam"), _set("camera", "exposure_s", value=0)),
     "camera.exposure_s", "seconds > 0"),
    ("pvcam-exposure-nan", _all(_set("camera", "backend", value="pvcam"), _set("camera", "exposure_s", value=math.nan)),
     "camera.exposure_s", "seconds > 0"),
    ("pvcam-camera_name-int", _all(_set("camera", "backend", value="pvcam"), _set("camera", "camera_name", value=3)),
     "camera.camera_name", "a PVCAM camera name"),
    # lamp.state_file must stay in the profile's folder
    ("lamp-parent", _set("lamp", "state_file", value="../x.json"), "lamp.state_file", "inside the profile's folder"),
    ("lamp-parent-inside", _set("lamp", "state_file", value="state/../../x.json"), "lamp.state_file", "inside the profile's folder"),
    ("lamp-absolute", _set("lamp", "state_file", value="/tmp/lamp.json"), "lamp.state_file", "inside the profile's folder"),
    ("lamp-empty", _set("lamp", "state_file", value=""), "lamp.state_file", "inside the profile's folder"),
    ("lamp-not-a-string", _set("lamp", "state_file", value=5), "lamp.state_file", "a file name"),
    ("lamp-symlink-outside", _lamp_symlink_to_outside_file, "lamp.state_file", "a file inside it"),
    ("lamp-symlinked-folder-outside", _lamp_in_symlinked_folder, "lamp.state_file", "a file inside it"),
    # [[samples]]
    ("sample-duplicate-id", _set("samples", value=[{"id": "s1"}, {"id": "s2"}, {"id": "s1"}]), "samples[2].id", "a unique sample id"),
    ("sample-id-dark", _set("samples", value=[{"id": "dark"}]), "samples[0].id", "a unique sample id"),
    ("sample-id-white", _set("samples", value=[{"id": "s1"}, {"id": "white"}]), "samples[1].id", "a unique sample id"),
    ("sample-id-path", _set("samples", value=[{"id": "../s1"}]), "samples[0].id", "letters, digits"),
    ("sample-id-missing", _set("samples", value=[{"set": "test"}]), "samples[0].id", "letters, digits"),
    ("sample-bad-set", _set("samples", value=[{"id": "s1", "set": "validation"}]), "samples[0].set", "training"),
    ("sample-empty-background", _set("samples", value=[{"id": "s1", "background": ""}]), "samples[0].background", "non-empty"),
    ("samples-a-table", _set("samples", value={"id": "s1"}), "samples", "[[samples]] tables"),
    ("samples-not-tables", _set("samples", value=["s1", "s2"]), "samples[0]", "a table"),
    ("sample-bad-role", _set("samples", value=[{"id": "s1", "role": "target"}]), "samples[0].role", "'registration'"),
    ("registration-with-set", _set("samples", value=[{"id": "cb", "role": "registration", "set": "test"}]),
     "samples[0].set", "no set on the registration target"),
    ("registration-with-background", _set("samples", value=[{"id": "cb", "role": "registration", "background": "grey"}]),
     "samples[0].background", "no background on the registration target"),
    ("registration-twice", _set("samples", value=[{"id": "cb", "role": "registration"}, {"id": "s1"},
                                                  {"id": "star", "role": "registration"}]),
     "samples[2].role", 'at most one [[samples]] entry with role = "registration"'),
    ("registration-id-taken", _set("samples", value=[{"id": "s1"}, {"id": "s1", "role": "registration"}]),
     "samples[1].id", "a unique sample id"),
]


@pytest.mark.parametrize(("change", "key", "expected"), [case[1:] for case in BAD], ids=[case[0] for case in BAD])
def test_bad_profile_is_refused(folder, change, key, expected):
    data = example()
    change(data, folder)
    path = write(folder, data)
    with pytest.raises(ProfileError) as caught:
        load_profile(path)
    assert isinstance(caught.value, ValueError)  # the CLI reports ValueError as bad input
    check_message(caught.value, path, key, expected)


def test_every_required_key_is_in_the_catalogue():
    ids = {case[0] for case in BAD}
    for key in ("instrument.id", "wheels", "wheels.a.port", "wheels.a.model", "wheels.a.open_slot",
                "shutter", "shutter.port", "shutter.model", "camera.backend", "bands"):
        assert f"missing-{key}" in ids


@pytest.mark.parametrize(
    "text",
    [
        "[instrument\nid = 'x'\n",  # unterminated table header
        "this is not toml at all\n",
        EXAMPLE + '400 = ["b", 2]\n',  # a key defined twice
        "",  # empty: valid TOML, every section missing
    ],
    ids=["bad-header", "prose", "duplicate-key", "empty"],
)
def test_not_toml_or_empty(folder, text):
    path = write(folder, text)
    with pytest.raises(ProfileError) as caught:
        load_profile(path)
    if text:
        message = check_message(caught.value, path, None, "an instrument profile (TOML)")
        assert "not valid TOML" in message
    else:
        check_message(caught.value, path, "instrument", "a table")


def test_not_utf8(folder):
    path = folder / "profile.toml"
    path.write_bytes(b'[instrument]\nid = "\xff\xfe"\n')
    with pytest.raises(ProfileError) as caught:
        load_profile(path)
    check_message(caught.value, path, None, "TOML")


def test_missing_file(folder):
    path = folder / "nope.toml"
    with pytest.raises(ProfileError) as caught:
        load_profile(path)
    message = check_message(caught.value, path, None, "an instrument profile (TOML)")
    assert "no such file" in message


def test_a_folder_is_not_a_profile(folder):
    with pytest.raises(ProfileError) as caught:
        load_profile(folder)
    check_message(caught.value, folder, None, "TOML")


def test_lamp_symlink_inside_the_folder_is_allowed(folder):
    (folder / "state").mkdir()
    (folder / "lamp.json").symlink_to(folder / "state" / "lamp.json")
    data = example()
    data["lamp"] = {"state_file": "lamp.json"}
    profile = load_profile(write(folder, data))
    assert profile.lamp_state_file == (folder / "state" / "lamp.json").resolve()


def test_default_lamp_state_file_follows_the_profile_name(folder):
    path = write(folder, EXAMPLE, "bench 2.toml")
    assert load_profile(path).lamp_state_file == (folder / "bench 2.lamp.json").resolve()


def test_relative_profile_path(folder, monkeypatch):
    write(folder, EXAMPLE)
    monkeypatch.chdir(folder)
    profile = load_profile("profile.toml")
    assert profile.lamp_state_file == (folder / "profile.lamp.json").resolve()
    data = example()
    data["bands"]["420"] = ["a", 1]
    write(folder, data)
    with pytest.raises(ProfileError, match=r"^profile\.toml: bands\.420: "):
        load_profile("profile.toml")


# -- the command line ------------------------------------------------------------------------------

CLI_CASES = [case for case in BAD if case[0] in {
    "missing-instrument.id", "missing-wheels.a.port", "typo-in-wheel", "two-bands-one-slot", "slot-13-on-FW212C",
    "port-is-int", "band-on-undefined-wheel", "lamp-parent", "sample-id-dark", "pvcam-without-layout",
    "camera-option-unknown", "camera-option-of-the-other-backend", "camera-seed-string",
}]


@pytest.mark.parametrize(("change", "key", "expected"), [case[1:] for case in CLI_CASES], ids=[case[0] for case in CLI_CASES])
def test_cli_refuses_a_bad_profile_before_anything_is_created(tmp_path, folder, capsys, change, key, expected):
    from spherejax import cli

    data = example()
    change(data, folder)
    path = write(folder, data)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))

    code = cli.main(["acquire", "--profile", str(path), "-o", str(tmp_path / "s"), "--yes", "--emulate"])

    out, err = capsys.readouterr()
    assert code == 2
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("spherejax: error: "), err
    assert f"{path}: {key}: " in lines[0] and expected in lines[0], err
    assert "Traceback" not in err and out == ""
    assert not (tmp_path / "s").exists()
    assert not (tmp_path / "s.partial").exists()
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


@pytest.mark.parametrize("emulate", [True, False], ids=["emulate", "real-devices"])
@pytest.mark.parametrize(
    ("camera", "key", "expected"),
    [
        ({"backend": "pvcam", "exposure": 0.1}, "camera.exposure", "an option of the 'pvcam' backend"),
        ({"backend": "sim", "noise": 0.5}, "camera.noise", "an option of the 'sim' backend"),
        ({"backend": "sim", "shutter_open": True}, "camera.shutter_open", "an option of the 'sim' backend"),
    ],
    ids=["pvcam-unknown", "sim-unknown", "sim-set-by-acquire"],
)
def test_cli_refuses_a_camera_option_before_any_device_is_opened(tmp_path, folder, capsys, monkeypatch, emulate, camera, key, expected):
    """A [camera] option the backend does not take: one line naming the key, exit status 2,
    nothing opened or written (not a TypeError traceback from the backend's constructor)."""
    from spherejax_hw import acquire
    from spherejax import cli

    def connect(*args, **kwargs):
        raise AssertionError("a device was opened")

    monkeypatch.setattr(acquire, "connect", connect)
    data = example()
    data["camera"] = camera
    data["layout"] = {"white_patch": [0, 5, 0, 5], "holder": [10, 100, 10, 100]}
    path = write(folder, data)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))

    code = cli.main(["acquire", "--profile", str(path), "-o", str(tmp_path / "s"), "--yes", *(["--emulate"] if emulate else [])])

    out, err = capsys.readouterr()
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err and out == ""
    assert err.startswith(f"spherejax: error: {path}: {key}: is not a known key (expected {expected}"), err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_cli_refuses_a_missing_profile(tmp_path, capsys):
    from spherejax import cli

    missing = tmp_path / "nope.toml"
    code = cli.main(["acquire", "--profile", str(missing), "-o", str(tmp_path / "s"), "--yes", "--emulate"])
    out, err = capsys.readouterr()
    assert code == 2
    assert err.splitlines() == [err.rstrip("\n")] and err.startswith(f"spherejax: error: {missing}: no such file")
    assert "Traceback" not in err and out == ""
    assert list(tmp_path.iterdir()) == []


def test_cli_refuses_not_toml(tmp_path, capsys):
    from spherejax import cli

    path = tmp_path / "profile.toml"
    path.write_text("[wheels.a\nport = 1\n")
    code = cli.main(["acquire", "--profile", str(path), "-o", str(tmp_path / "s"), "--yes", "--emulate"])
    out, err = capsys.readouterr()
    assert code == 2
    assert len(err.splitlines()) == 1 and err.startswith(f"spherejax: error: {path}: is not valid TOML")
    assert "Traceback" not in err and out == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["profile.toml"]


def test_no_stray_files_left_by_symlink_cases(folder):
    # The symlink helpers create their targets outside the folder; loading never writes anything.
    data = example()
    _lamp_symlink_to_outside_file(data, folder)
    path = write(folder, data)
    with pytest.raises(ProfileError):
        load_profile(path)
    assert sorted(os.listdir(folder)) == ["lamp.json", "profile.toml"]
    assert (folder.parent / "elsewhere.json").read_text() == "{}"
