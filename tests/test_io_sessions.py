"""spherejax.io.sessions: session folders (manifest and frames), round trips, and every refusal.

Each refusal checks the exception type, that the message is one line starting with the file it
names, the problem (`match=`), and that nothing new or partial is left on disk.
"""

import datetime
import json

import numpy as np
import pytest

import spherejax as sj
from spherejax import io
from spherejax.io import SessionError, SpherejaxFileError
from tests.helpers import listing, refused

H, W = 12, 10
BANDS = list(range(400, 701, 20))
B = len(BANDS)
CREATED = "2026-11-22T10:00:00+00:00"


# --------------------------------------------------------------------------------------- helpers


def counts(rng, shape=(H, W, B)) -> np.ndarray:
    return rng.integers(0, 65536, shape, dtype=np.uint16)


def frame_dict(frame_id, role, **fields):
    return {
        "id": frame_id,
        "role": role,
        "exposure_s": [0.01 + 0.001 * i for i in range(B)],
        "timestamp": CREATED,
        **fields,
    }


def reflectance(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.02, 0.95, 31)


def session_frames(rng):
    """(frame dict, array) for a dark, a white, two samples and one target frame."""
    return [
        (frame_dict("dark", "dark"), counts(rng)),
        (frame_dict("white", "white", metadata={"lamp_hours": 12.5}), counts(rng)),
        (
            frame_dict(
                "train-bg03-a",
                "sample",
                set="training",
                background="bg03",
                regions=[{"name": "grey5", "patch": "grey5", "region": [2, 5, 3, 6]}],
            ),
            counts(rng),
        ),
        (
            frame_dict(
                "test-bg07",
                "sample",
                set="test",
                background="bg07",
                regions=[io.Region("red", "cc-red", (0, 4, 0, 4), reflectance(1))],
            ),
            counts(rng),
        ),
        (
            frame_dict(
                "targets-1",
                "target",
                regions=[
                    {"name": "t001", "region": [0, 3, 0, 3], "reflectance": reflectance(2)},
                    {"name": "t002", "region": [3, 6, 0, 3], "reflectance": reflectance(3)},
                ],
            ),
            counts(rng),
        ),
    ]


def session_fields():
    return dict(
        instrument_id="sim-sphere-1",
        band_centres_nm=np.asarray(BANDS),
        image_shape=(H, W),
        saturation=16383,
        white_patch=[0, 2, 8, 10],
        holder=[2, 12, 0, 10],
        metadata={"simulator": {"seed": 7, "wall_reflectance": 0.97}},
        created=CREATED,
    )


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture
def session_path(tmp_path, rng):
    """A valid session on disk at tmp_path / "session"."""
    path = tmp_path / "session"
    io.write_session(path, frames=session_frames(rng), **session_fields())
    return path


def edit_manifest(session_path, edit):
    manifest_path = session_path / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    edit(manifest)
    manifest_path.write_text(json.dumps(manifest))
    return manifest_path


# -------------------------------------------------------------------------------------- sessions


def test_session_round_trip(tmp_path, rng):
    frames = session_frames(rng)
    path = tmp_path / "session"
    written = io.write_session(path, frames=frames, **session_fields())
    loaded = io.load_session(path)
    assert listing(tmp_path) == sorted(
        ["session", "session/manifest.json", "session/frames"]
        + [f"session/frames/{f['id']}.tif" for f, _ in frames]
    )

    for session in (written, loaded):
        assert session.path == path
        assert session.instrument_id == "sim-sphere-1"
        assert session.software_version == sj.__version__
        assert session.created == CREATED
        np.testing.assert_array_equal(session.band_centres_nm, BANDS)
        assert session.band_centres_nm.dtype == np.int64
        assert session.image_shape == (H, W) and session.bands == B
        assert session.saturation == 16383
        assert session.white_patch == (0, 2, 8, 10) and session.holder == (2, 12, 0, 10)
        assert session.metadata == {"simulator": {"seed": 7, "wall_reflectance": 0.97}}
        assert [f.id for f in session.frames] == [f["id"] for f, _ in frames]
        for (given, array), info in zip(frames, session.frames):
            assert info.file == f"frames/{given['id']}.tif"
            np.testing.assert_array_equal(info.exposure_s, given["exposure_s"])
            out = session.read(info)
            assert out.dtype == np.uint16
            np.testing.assert_array_equal(out, array)
            np.testing.assert_array_equal(session.read(info.id), array)
        np.testing.assert_array_equal(session.dark(), frames[0][1])
        np.testing.assert_array_equal(session.white(), frames[1][1])
    assert loaded.to_manifest() == written.to_manifest()
    assert loaded.to_manifest() == json.loads((path / "manifest.json").read_text())

    sample = loaded.frame("test-bg07")
    assert (sample.role, sample.set, sample.background) == ("sample", "test", "bg07")
    (red,) = sample.regions
    assert (red.name, red.patch, red.region) == ("red", "cc-red", (0, 4, 0, 4))
    np.testing.assert_array_equal(red.reflectance, reflectance(1))  # bit for bit through JSON
    grey = loaded.frame("train-bg03-a").regions[0]
    assert grey.reflectance is None
    target = loaded.frame("targets-1")
    assert [r.patch for r in target.regions] == ["t001", "t002"]  # patch defaults to the name
    np.testing.assert_array_equal(target.regions[1].reflectance, reflectance(3))
    assert loaded.frame("white").metadata == {"lamp_hours": 12.5}
    assert loaded.frame("dark").set is None and loaded.frame("dark").regions == ()
    assert io.read_frame_metadata(loaded.frame_path("dark"))["channel_names"] == [
        f"{nm}nm" for nm in BANDS
    ]


def test_session_queries(session_path):
    session = io.load_session(session_path)
    assert [f.id for f in session.frames_with(role="sample")] == ["train-bg03-a", "test-bg07"]
    assert [f.id for f in session.frames_with(set="training")] == ["train-bg03-a"]
    assert [f.id for f in session.frames_with(role="target")] == ["targets-1"]
    assert len(session.frames_with()) == 5
    with pytest.raises(ValueError, match="role: expected one of"):
        session.frames_with(role="samples")
    with refused(SessionError, session_path / "manifest.json", "has no frame 'nope'"):
        session.frame("nope")

    patch = session.white_patch_mask()
    assert patch.dtype == bool and patch.shape == (H, W) and patch.sum() == 4 and patch[0, 8]
    holder = session.holder_mask()
    assert holder.sum() == 10 * W and not holder[1].any()

    region = session.frame("train-bg03-a").regions[0]
    mask = region.mask((H, W))
    assert mask.sum() == 9 and mask[2, 3] and not mask[5, 3]
    cube = session.read("train-bg03-a")
    mean = region.mean(cube)
    assert mean.shape == (B,) and mean.dtype == np.float64
    np.testing.assert_allclose(mean, cube[mask].mean(axis=0))
    stacked = np.stack([cube, cube]).astype(np.float32)
    assert region.mean(stacked).shape == (2, B) and region.mean(stacked).dtype == np.float32


def test_write_session_into_an_empty_folder(tmp_path, rng):
    path = tmp_path / "session"
    path.mkdir()
    session = io.write_session(path, frames=session_frames(rng), **session_fields())
    assert len(session.frames) == 5
    assert [p for p in listing(tmp_path) if "/" not in p] == ["session"]


def test_write_session_default_created_is_utc_now(tmp_path, rng):
    fields = session_fields()
    del fields["created"]
    session = io.write_session(tmp_path / "s", frames=session_frames(rng), **fields)
    created = datetime.datetime.fromisoformat(session.created)
    assert created.utcoffset() == datetime.timedelta(0)


def test_write_session_refuses_a_non_empty_folder(tmp_path, rng):
    path = tmp_path / "session"
    path.mkdir()
    (path / "notes.txt").write_text("keep me")
    with refused(SessionError, path, "already exists and is not an empty folder"):
        io.write_session(path, frames=session_frames(rng), **session_fields())
    assert listing(tmp_path) == ["session", "session/notes.txt"]
    assert (path / "notes.txt").read_text() == "keep me"


def _unsafe_id(frames):
    frames[2][0]["id"] = "../escape"


def _float_array(frames):
    frames[1] = (frames[1][0], frames[1][1].astype(np.float32))


def _wrong_shape(frames):
    frames[1] = (frames[1][0], frames[1][1][:, :, :3])


def _sample_without_set(frames):
    del frames[2][0]["set"]


def _file_given(frames):
    frames[0][0]["file"] = "dark.tif"


def _nan_metadata(frames):
    frames[0][0]["metadata"] = {"gain": float("nan")}


@pytest.mark.parametrize(
    "spoil, match, file",
    [
        (_unsafe_id, r"frames\[2\]\.id is \"\.\./escape\"", "manifest.json"),
        (_float_array, "frame 'white' is an array of shape .* dtype float32", "frames/white.tif"),
        (_wrong_shape, r"frame 'white' is an array of shape \(12, 10, 3\)", "frames/white.tif"),
        (_sample_without_set, r"frames\[2\]\.set is missing", "manifest.json"),
        (_file_given, r"frames\[0\] names a file", "manifest.json"),
        (_nan_metadata, "cannot be stored as JSON", "manifest.json"),
    ],
)
def test_write_session_refuses_bad_input_before_writing(tmp_path, rng, spoil, match, file):
    frames = session_frames(rng)
    spoil(frames)
    path = tmp_path / "session"
    with refused(SessionError, path / file, match):
        io.write_session(path, frames=frames, **session_fields())
    assert listing(tmp_path) == []


def test_write_session_failure_removes_the_partial_folder(tmp_path, rng, monkeypatch):
    written = []
    real_write_frame = io.write_frame

    def write_two_then_fail(path, array, **kwargs):
        if len(written) == 2:
            raise SpherejaxFileError(path, "could not be written: No space left on device")
        written.append(path)
        real_write_frame(path, array, **kwargs)

    monkeypatch.setattr(io.sessions, "write_frame", write_two_then_fail)
    path = tmp_path / "session"
    third_frame = path / "frames" / "train-bg03-a.tif"
    with refused(SessionError, third_frame, "No space left", says_expected=False):
        io.write_session(path, frames=session_frames(rng), **session_fields())
    assert len(written) == 2
    assert listing(tmp_path) == []


def test_load_session_missing_folder(tmp_path):
    path = tmp_path / "nope"
    with refused(SessionError, path, "no such folder"):
        io.load_session(path)


def test_load_session_missing_manifest(session_path):
    (session_path / "manifest.json").unlink()
    with refused(SessionError, session_path / "manifest.json", "no such file"):
        io.load_session(session_path)


@pytest.mark.parametrize(
    "text, match",
    [
        ('{"format": "spherejax-session",\n  "frames": [', "is not valid JSON: .*line 2"),
        ("[1, 2]", r"holds \[1, 2\] \(expected a JSON object"),
    ],
    ids=["not-json", "not-an-object"],
)
def test_load_session_manifest_not_json_object(session_path, text, match):
    manifest_path = session_path / "manifest.json"
    manifest_path.write_text(text)
    with refused(SessionError, manifest_path, match):
        io.load_session(session_path)


def _set(*keys, value):
    """An edit that sets manifest[k0][k1]... = value."""

    def edit(manifest):
        target = manifest
        for key in keys[:-1]:
            target = target[key]
        target[keys[-1]] = value

    return edit


def _delete(*keys):
    def edit(manifest):
        target = manifest
        for key in keys[:-1]:
            target = target[key]
        del target[keys[-1]]

    return edit


def _replace_document(manifest):
    manifest.clear()
    manifest["frames"] = "not a session"


MANIFEST_REFUSALS = {
    "not-a-session": (_replace_document, "is not a spherejax-session file: format is missing"),
    "other-format": (_set("format", value="spherejax-calibration"), "is not a spherejax-session"),
    "newer-version": (
        _set("format_version", value=2),
        "is spherejax-session format version 2, newer than spherejax 0.1.0 reads "
        r"\(expected format version 1 or older",
    ),
    "version-mistyped": (_set("format_version", value="1"), 'format_version is "1"'),
    "missing-field": (_delete("saturation"), r"saturation is missing \(expected a number > 0"),
    "missing-frame-field": (
        _delete("frames", 2, "background"),
        r"frames\[2\]\.background is missing",
    ),
    "mistyped-field": (
        _set("image_shape", value="12x10"),
        r'image_shape is "12x10" \(expected \[H, W\]',
    ),
    "bool-for-int": (_set("image_shape", value=[True, 10]), r"image_shape is \[true, 10\]"),
    "bands-not-increasing": (
        _set("band_centres_nm", value=[400, 400] + BANDS[2:]),
        "band_centres_nm is .*increasing",
    ),
    "exposures-vs-bands": (
        _set("frames", 0, "exposure_s", value=[0.01] * (B - 1)),
        rf"frames\[0\]\.exposure_s is .*\(expected {B} exposure times",
    ),
    "negative-exposure": (
        _set("frames", 1, "exposure_s", value=[-0.01] * B),
        r"frames\[1\]\.exposure_s is \[-0\.01",
    ),
    "unknown-role": (_set("frames", 2, "role", value="smaple"), r'frames\[2\]\.role is "smaple"'),
    "unknown-set": (
        _set("frames", 2, "set", value="train"),
        r'frames\[2\]\.set is "train" .*"training"',
    ),
    "bad-timestamp": (
        _set("frames", 0, "timestamp", value="yesterday"),
        r'frames\[0\]\.timestamp is "yesterday" \(expected an ISO 8601',
    ),
    "escaping-path": (
        _set("frames", 0, "file", value="../x.tif"),
        r'frames\[0\]\.file is "\.\./x\.tif" \(expected a relative path inside',
    ),
    "inner-escape": (
        _set("frames", 0, "file", value="frames/../../x.tif"),
        r"frames\[0\]\.file is",
    ),
    "absolute-path": (_set("frames", 0, "file", value="/etc/passwd"), "a relative path inside"),
    "empty-region": (
        _set("frames", 2, "regions", 0, "region", value=[2, 2, 3, 6]),
        r"frames\[2\]\.regions\[0\]\.region is \[2, 2, 3, 6\] \(expected .*non-empty rectangle",
    ),
    "region-out-of-image": (
        _set("frames", 2, "regions", 0, "region", value=[2, H + 1, 3, 6]),
        rf"region is \[2, {H + 1}, 3, 6\] .*inside the {H} x {W} image",
    ),
    "white-patch-outside": (_set("white_patch", value=[0, 2, 8, W + 2]), "white_patch is"),
    "target-without-reflectance": (
        _delete("frames", 4, "regions", 1, "reflectance"),
        r"frames\[4\]\.regions\[1\]\.reflectance is missing .*required for a target",
    ),
    "short-reflectance": (
        _set("frames", 3, "regions", 0, "reflectance", value=[0.5] * 30),
        r"frames\[3\]\.regions\[0\]\.reflectance is .*\(expected 31 finite",
    ),
    "regions-on-dark": (
        _set("frames", 0, "regions", value=[{"name": "a", "region": [0, 1, 0, 1]}]),
        "none on a dark frame",
    ),
    "repeated-region-names": (
        _set("frames", 4, "regions", 1, "name", value="t001"),
        r"frames\[4\]\.regions repeat names",
    ),
    "repeated-ids": (
        _set("frames", 3, "id", value="train-bg03-a"),
        r"frame ids \['train-bg03-a'\] repeat",
    ),
    "two-darks": (_set("frames", 1, "role", value="dark"), "lists 2 dark frames"),
    "no-white": (_set("frames", 1, "role", value="target"), "lists 0 white frames"),
    "unknown-field": (
        _set("frames", 0, "exposure", value=0.01),
        r"frames\[0\] has unknown fields \['exposure'\]",
    ),
    "unknown-top-field": (
        _set("white_pach", value=[0, 2, 8, 10]),
        r"the top level has unknown fields \['white_pach'\]",
    ),
    "not-an-object": (_set("frames", 1, value="white"), r'frames\[1\] is "white"'),
}


@pytest.mark.parametrize("edit, match", MANIFEST_REFUSALS.values(), ids=MANIFEST_REFUSALS.keys())
def test_load_session_refuses_manifest(session_path, edit, match):
    manifest_path = edit_manifest(session_path, edit)
    with refused(SessionError, manifest_path, match):
        io.load_session(session_path)


def test_load_session_missing_frame_file(session_path):
    frame_path = session_path / "frames" / "white.tif"
    frame_path.unlink()
    with refused(SessionError, frame_path, "no such file .*frame 'white'"):
        io.load_session(session_path)


def test_load_session_refuses_a_link_out_of_the_folder(session_path, rng):
    outside = session_path.parent / "outside.tif"
    io.write_frame(outside, counts(rng))
    frame_path = session_path / "frames" / "white.tif"
    frame_path.unlink()
    frame_path.symlink_to(outside)
    with refused(SessionError, frame_path, "outside the session folder"):
        io.load_session(session_path)


@pytest.mark.parametrize(
    "shape, match",
    [((H + 2, W, B), rf"is {H + 2} x {W} pixels"), ((H, W, B - 1), rf"has {B - 1} channels")],
    ids=["size", "channels"],
)
def test_load_session_refuses_a_frame_of_the_wrong_shape(session_path, rng, shape, match):
    frame_path = session_path / "frames" / "test-bg07.tif"
    io.write_frame(frame_path, counts(rng, shape))
    with refused(SessionError, frame_path, match):
        io.load_session(session_path)


def test_load_session_refuses_a_corrupt_frame(session_path):
    frame_path = session_path / "frames" / "dark.tif"
    frame_path.write_text("not a tiff")
    with refused(SessionError, frame_path, "is not a readable image"):
        io.load_session(session_path)


def test_session_read_checks_the_frame_again(session_path, rng):
    session = io.load_session(session_path)
    frame_path = session.frame_path("white")
    io.write_frame(frame_path, counts(rng, (H, W, 3)))  # replaced after loading
    with refused(SessionError, frame_path, "has 3 channels"):
        session.white()


# ---------------------------------------------------------------------------- registration frame


def _with_registration(rng, *ids, **fields):
    """session_frames with a registration-target frame per id, after the samples."""
    frames = session_frames(rng)
    for frame_id in ids:
        frames.insert(4, (frame_dict(frame_id, "registration", metadata={"frames_averaged": 16}, **fields), counts(rng)))
    return frames


def test_session_with_a_registration_frame(tmp_path, rng):
    frames = _with_registration(rng, "checkerboard")
    path = tmp_path / "session"
    written = io.write_session(path, frames=frames, **session_fields())
    loaded = io.load_session(path)
    assert loaded.to_manifest() == written.to_manifest() == json.loads((path / "manifest.json").read_text())
    registration = loaded.registration_frame()
    assert (registration.id, registration.role) == ("checkerboard", "registration")
    assert registration.regions == () and registration.set is None and registration.background is None
    assert registration.metadata == {"frames_averaged": 16}
    np.testing.assert_array_equal(registration.exposure_s, frames[4][0]["exposure_s"])
    np.testing.assert_array_equal(loaded.read(registration), frames[4][1])
    assert loaded.frames_with(role="registration") == (registration,)
    # What iterates by role is unchanged: the registration frame is no sample nor target.
    assert [f.id for f in loaded.frames_with(role="sample")] == ["train-bg03-a", "test-bg07"]
    assert [f.id for f in loaded.frames_with(role="target")] == ["targets-1"]
    assert [f.id for f in loaded.frames_with(set="training")] == ["train-bg03-a"]
    assert io.read_frame_metadata(loaded.frame_path(registration))["attributes"]["spherejax:role"] == "registration"


def test_a_session_without_a_registration_frame_has_none(session_path):
    assert io.load_session(session_path).registration_frame() is None


def test_write_session_refuses_a_second_registration_frame(tmp_path, rng):
    path = tmp_path / "session"
    with refused(SessionError, path / "manifest.json",
                 r"lists 2 registration frames \(expected at most one with role 'registration'\)"):
        io.write_session(path, frames=_with_registration(rng, "checkerboard", "siemens-star"), **session_fields())
    assert listing(tmp_path) == []


def _two_registration_frames(manifest):
    for frame in manifest["frames"][2:4]:  # the two samples, their regions removed
        frame.update(role="registration")
        del frame["regions"]


@pytest.mark.parametrize(
    "edit, match",
    [
        (_set("frames", 3, "role", value="registration"),
         r"frames\[3\]\.regions lists 1 regions \(expected none on a registration frame"),
        (_two_registration_frames, r"lists 2 registration frames \(expected at most one with role 'registration'\)"),
    ],
    ids=["regions", "second"],
)
def test_load_session_refuses_registration_frames(session_path, edit, match):
    manifest_path = edit_manifest(session_path, edit)
    with refused(SessionError, manifest_path, match):
        io.load_session(session_path)
