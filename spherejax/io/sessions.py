"""Sessions: a folder of frames with a manifest (format "spherejax-session", the package
docstring), read (`load_session`) and written (`write_session`, `write_simulated_session`)."""

from __future__ import annotations

import collections
import dataclasses
import os
import pathlib
import re
import shutil
from collections.abc import Mapping, Sequence
from typing import Annotated

import numpy as np
import pydantic

from .. import jsontext
from ..grid import N_WAVELENGTHS
from ..atomic_files import atomic_file, fsync_folder, temp_sibling
from .documents import (
    BandCentres, BandTransforms, Document, Expect, ImageRectangle, JsonObject, NonEmptyStr, PositiveNumber, RelativePath, Timestamp,
    _check_format, _json_value, _readable_json, _utc_now, check_document, choice, integer, located, numbers, refuse,
    shape,
)
from .errors import SessionError, SpherejaxFileError, _reraise_as, _show
from .plain_files import read_small
from .frames import _FRAME_EXPECTED, _require_frame_shape, frame_spec, read_frame, require_image_file, write_frame

SESSION_FORMAT = "spherejax-session"
SESSION_FORMAT_VERSION = 1
MANIFEST_NAME = "manifest.json"
ROLES = ("dark", "white", "sample", "target", "registration")
SETS = ("training", "test")
_SAFE_ID = re.compile(r"[A-Za-z0-9._-]+")

def rectangle_mask(rect: Sequence[int], image_shape: Sequence[int]) -> np.ndarray:
    """Boolean mask (H, W), True on rows r0:r1 and columns c0:c1 of rect = (r0, r1, c0, c1)."""
    r0, r1, c0, c1 = rect
    mask = np.zeros(tuple(image_shape), dtype=bool)
    mask[r0:r1, c0:c1] = True
    return mask


def _readonly(array: np.ndarray) -> np.ndarray:
    # The dataclasses are frozen; their arrays should not change under them either.
    array.setflags(write=False)
    return array


@dataclasses.dataclass(frozen=True, eq=False)
class Region:
    """A rectangle of a frame showing one patch. Compare regions with `to_json()`.

    Fields:
      name: unique within its frame.
      patch: the physical patch shown (the same patch on several backgrounds shares it).
      region: (r0, r1, c0, c1), rows r0:r1 and columns c0:c1.
      reflectance: known reflectance (31,) at 400..700 nm step 10, float64, or None.
    """

    name: str
    patch: str
    region: tuple[int, int, int, int]
    reflectance: np.ndarray | None = None

    def mask(self, image_shape: Sequence[int]) -> np.ndarray:
        """Boolean (H, W), True inside the rectangle."""
        return rectangle_mask(self.region, image_shape)

    def mean(self, array) -> np.ndarray:
        """Average of an (..., H, W, B) array over the rectangle -> (..., B).

        float64 for integer input (raw counts), the input's dtype for float input.
        """
        r0, r1, c0, c1 = self.region
        return np.asarray(array)[..., r0:r1, c0:c1, :].mean(axis=(-3, -2))

    def to_json(self) -> dict:
        """The region as it appears in a manifest."""
        out = {"name": self.name, "patch": self.patch, "region": [int(v) for v in self.region]}
        if self.reflectance is not None:
            out["reflectance"] = np.asarray(self.reflectance, dtype=np.float64).tolist()
        return out


@dataclasses.dataclass(frozen=True, eq=False)
class FrameInfo:
    """One frame of a session, as listed in its manifest (no pixels). Compare with `to_json()`.

    Fields:
      id: unique in the session.
      role: "dark", "white", "sample", "target" or "registration" (a registration target: a
        frame of high-contrast edges across the field that `spherejax calibrate` registers the
        bands on; no regions).
      file: path of the frame file relative to the session folder (`Session.frame_path`).
      exposure_s: exposure times (B,) in seconds, float64.
      timestamp: ISO 8601.
      set: "training" or "test" (always set for samples), or None.
      background: the background a sample lies on (always set for samples), or None.
      regions: the `Region`s of a sample or target frame.
      metadata: free JSON.
    """

    id: str
    role: str
    file: str
    exposure_s: np.ndarray
    timestamp: str
    set: str | None = None
    background: str | None = None
    regions: tuple[Region, ...] = ()
    metadata: dict = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict:
        """The frame as it appears in a manifest."""
        out = {
            "id": self.id,
            "role": self.role,
            "file": self.file,
            "exposure_s": self.exposure_s.tolist(),
            "timestamp": self.timestamp,
        }
        if self.set is not None:
            out["set"] = self.set
        if self.background is not None:
            out["background"] = self.background
        if self.regions:
            out["regions"] = [region.to_json() for region in self.regions]
        if self.metadata:
            out["metadata"] = self.metadata
        return out


@dataclasses.dataclass(frozen=True, eq=False)
class Session:
    """A loaded session: its manifest, checked, with methods to read its frames.

    Fields:
      path: the session folder.
      instrument_id, software_version, created: from the manifest.
      band_centres_nm: (B,) int64, strictly increasing.
      image_shape: (H, W).
      saturation: raw level at or above which a pixel counts as saturated.
      white_patch, holder: (r0, r1, c0, c1) rectangles.
      frames: every `FrameInfo`, in manifest order.
      metadata: free JSON.
      band_transforms: (B, 2, 3) or None: where each band's image lies, when the session records
        it (a simulated one: the truth), as 2 x 3 affine maps from the reference geometry's pixel
        coordinates (x = column, y = row, pixel centres at integers) to the band's.
    """

    path: pathlib.Path
    instrument_id: str
    band_centres_nm: np.ndarray
    image_shape: tuple[int, int]
    saturation: int | float
    white_patch: tuple[int, int, int, int]
    holder: tuple[int, int, int, int]
    frames: tuple[FrameInfo, ...]
    software_version: str
    created: str
    metadata: dict = dataclasses.field(default_factory=dict)
    band_transforms: np.ndarray | None = None

    @property
    def bands(self) -> int:
        return int(self.band_centres_nm.size)

    @property
    def manifest_path(self) -> pathlib.Path:
        return self.path / MANIFEST_NAME

    def frames_with(self, role: str | None = None, set: str | None = None) -> tuple[FrameInfo, ...]:
        """The frames of a role and/or set, in manifest order (None matches any)."""
        if role is not None and role not in ROLES:
            raise ValueError(f"role: expected one of {list(ROLES)}, got {role!r}")
        if set is not None and set not in SETS:
            raise ValueError(f"set: expected one of {list(SETS)}, got {set!r}")
        return tuple(
            frame
            for frame in self.frames
            if (role is None or frame.role == role) and (set is None or frame.set == set)
        )

    def frame(self, id: str) -> FrameInfo:
        """The frame with this id."""
        for frame in self.frames:
            if frame.id == id:
                return frame
        known = [frame.id for frame in self.frames]
        raise SessionError(self.manifest_path, f"has no frame {id!r}", f"one of {known}")

    def frame_path(self, frame: FrameInfo | str) -> pathlib.Path:
        """Where a frame's file lies. The manifest names it in UTF-8 text; the file system is
        given those bytes (`os.fsdecode` of them), so that "frames/rôt.tif" is found under a
        locale that is not UTF-8 too (LC_ALL=C cannot encode "ô" as text)."""
        frame = self.frame(frame) if isinstance(frame, str) else frame
        return self.path / os.fsdecode(frame.file.encode("utf-8", "surrogateescape"))

    def read(self, frame: FrameInfo | str) -> np.ndarray:
        """The pixels of a frame (or frame id): (H, W, B) uint16, checked against the manifest."""
        with _reraise_as(SessionError):
            expected_shape = (*self.image_shape, self.bands)
            return read_frame(self.frame_path(frame), expected_shape=expected_shape)

    def dark(self) -> np.ndarray:
        """The dark frame, (H, W, B) uint16."""
        return self.read(self.frames_with(role="dark")[0])

    def white(self) -> np.ndarray:
        """The white-standard frame, (H, W, B) uint16."""
        return self.read(self.frames_with(role="white")[0])

    def registration_frame(self) -> FrameInfo | None:
        """The frame of role "registration" (at most one; its pixels `read`, (H, W, B) uint16),
        or None when the session holds none."""
        frames = self.frames_with(role="registration")
        return frames[0] if frames else None

    def white_patch_mask(self) -> np.ndarray:
        """Boolean (H, W), True on the reference white patch (Eq. 14-15)."""
        return rectangle_mask(self.white_patch, self.image_shape)

    def holder_mask(self) -> np.ndarray:
        """Boolean (H, W), True on the sample holder."""
        return rectangle_mask(self.holder, self.image_shape)

    def to_manifest(self) -> dict:
        """The manifest this session was loaded from, as written by `write_session`."""
        return {
            "format": SESSION_FORMAT,
            "format_version": SESSION_FORMAT_VERSION,
            "software_version": self.software_version,
            "instrument_id": self.instrument_id,
            "created": self.created,
            "band_centres_nm": self.band_centres_nm.tolist(),
            "image_shape": list(self.image_shape),
            "saturation": self.saturation,
            "white_patch": list(self.white_patch),
            "holder": list(self.holder),
            "frames": [frame.to_json() for frame in self.frames],
            "metadata": self.metadata,
        } | ({} if self.band_transforms is None else {"band_transforms": self.band_transforms.tolist()})


# The manifest as documents (spherejax.io.documents), fields in the order they are checked. The
# validation context gives "bands" (B), "image_shape" (H, W), "height" and "width".

_REFLECTANCE = f"{N_WAVELENGTHS} finite reflectances at 400..700 nm step 10"
_Reflectance = numbers(N_WAVELENGTHS, _REFLECTANCE)
_Exposures = numbers("bands", "{bands} exposure times in seconds > 0, one per band", positive=True)
_ImageShape = shape(2, "[H, W], two integers > 0")


class _Region(Document):
    name: NonEmptyStr
    reflectance: _Reflectance | None = None
    patch: NonEmptyStr | None = None  # None: the region's name
    region: ImageRectangle


class _Frame(Document):
    role: choice(*ROLES)
    exposure_s: _Exposures
    regions: Annotated[list[Annotated[_Region, Expect("one of the regions, an object")]], Expect("a list of regions")] = []
    id: NonEmptyStr
    file: RelativePath
    timestamp: Timestamp
    set: choice(*SETS) | None = None  # required for samples (below)
    background: NonEmptyStr | None = None  # required for samples
    metadata: JsonObject = pydantic.Field(default_factory=dict)

    @pydantic.model_validator(mode="after")
    def _by_role(self):
        if self.regions and self.role in ("dark", "white", "registration"):
            raise refuse(f"lists {len(self.regions)} regions", f"none on a {self.role} frame", ("regions",))
        if self.role == "target":
            for index, region in enumerate(self.regions):
                if region.reflectance is None:
                    raise refuse("is missing", f"{_REFLECTANCE}, required for a target", ("regions", index, "reflectance"))
        names = [region.name for region in self.regions]
        if len(set(names)) != len(names):
            raise refuse(f"repeat names: {names}", "unique region names within a frame", ("regions",))
        if self.role == "sample":
            for key in ("set", "background"):
                if getattr(self, key) is None:
                    raise refuse("is missing", None, (key,))
        return self


class _Geometry(Document):
    """What the rest of the manifest is checked against: the bands and the image's size."""

    band_centres_nm: BandCentres
    image_shape: _ImageShape


class _Manifest(_Geometry):
    format: str
    format_version: integer(1)
    frames: Annotated[list[Annotated[_Frame, Expect("one of the frames, an object")]], Expect("a list of frames")]
    instrument_id: NonEmptyStr
    saturation: PositiveNumber
    white_patch: ImageRectangle
    holder: ImageRectangle
    software_version: NonEmptyStr
    created: Timestamp
    metadata: JsonObject = pydantic.Field(default_factory=dict)
    band_transforms: BandTransforms | None = None


def _frame_info(frame: _Frame) -> FrameInfo:
    regions = tuple(
        Region(name=r.name, patch=r.patch or r.name, region=r.region, reflectance=r.reflectance)
        for r in frame.regions
    )
    return FrameInfo(
        id=frame.id, role=frame.role, file=frame.file, exposure_s=frame.exposure_s, timestamp=frame.timestamp,
        set=frame.set, background=frame.background, regions=regions, metadata=frame.metadata,
    )


def _check_frame_roles(manifest_path, frames: Sequence[FrameInfo]) -> None:
    # Counted once: ids.count per id took 0.2 s on 5,000 frames (benchmarks/bench_manifest.py).
    repeated = sorted(i for i, n in collections.Counter(frame.id for frame in frames).items() if n > 1)
    if repeated:
        raise SessionError(manifest_path, f"frame ids {repeated} repeat", "unique frame ids")
    for role in ("dark", "white"):
        count = sum(frame.role == role for frame in frames)
        if count != 1:
            raise SessionError(
                manifest_path, f"lists {count} {role} frames", f"exactly one with role {role!r}"
            )
    count = sum(frame.role == "registration" for frame in frames)
    if count > 1:
        raise SessionError(manifest_path, f"lists {count} registration frames", "at most one with role 'registration'")


def _parse_manifest(doc, *, manifest_path: pathlib.Path, root: pathlib.Path) -> Session:
    """Check a manifest's content (not its frame files) and build the `Session`."""
    if not isinstance(doc, dict):
        raise SessionError(manifest_path, f"holds {_show(doc)}", "a JSON object, the manifest")
    error = located(SessionError, manifest_path)
    _check_format(doc, SESSION_FORMAT, SESSION_FORMAT_VERSION, error=error)
    geometry = check_document(_Geometry, {k: doc[k] for k in _Geometry.model_fields if k in doc}, error=error)
    height, width = geometry.image_shape
    context = {"bands": len(geometry.band_centres_nm), "image_shape": (height, width), "height": height, "width": width}
    manifest = check_document(_Manifest, doc, error=error, context=context)
    frames = tuple(_frame_info(frame) for frame in manifest.frames)
    _check_frame_roles(manifest_path, frames)
    return Session(
        path=root,
        instrument_id=manifest.instrument_id,
        band_centres_nm=_readonly(np.asarray(manifest.band_centres_nm, dtype=np.int64)),
        image_shape=manifest.image_shape,
        saturation=manifest.saturation,
        white_patch=manifest.white_patch,
        holder=manifest.holder,
        frames=frames,
        software_version=manifest.software_version,
        created=manifest.created,
        metadata=manifest.metadata,
        band_transforms=manifest.band_transforms,
    )


def _read_manifest(manifest_path: pathlib.Path):
    try:
        # Bounded, and a FIFO refused at once: a 3 GB sparse manifest.json was read whole.
        data = read_small(manifest_path)
    except OSError as error:
        raise SessionError(manifest_path, f"cannot be read: {error.strerror}", "the manifest of a spherejax session") from None
    try:
        # Not json.loads: jsontext also turns bad UTF-8, 4300-digit integers, deep nesting and a
        # key given twice (json.loads keeps the last) into the one-line problem. NaN and Infinity
        # are not JSON, and `write_session` never writes them (its metadata is refused first).
        return jsontext.loads(data, allow_nan=False)
    except jsontext.JSONTextError as error:
        raise SessionError(manifest_path, error.problem, "JSON") from None


def _check_frame_file(session: Session, frame: FrameInfo) -> None:
    """A frame's file lies inside the session (links included) and has the right header."""
    file = session.frame_path(frame)
    resolved, root = file.resolve(), session.path.resolve()
    if not resolved.is_relative_to(root):
        raise SessionError(
            file, f"resolves to {resolved}, outside the session folder", "frame files inside it"
        )
    if not file.exists():
        raise SessionError(
            file, f"no such file (frame {frame.id!r} in {MANIFEST_NAME})", _FRAME_EXPECTED
        )
    with _reraise_as(SessionError):
        # A FIFO or device named as a frame: refused by what it is, never opened; a frame far
        # larger than the session's image shape could ever need, before OpenImageIO reads it.
        require_image_file(file, f"{_FRAME_EXPECTED}, frame {frame.id!r} in {MANIFEST_NAME}",
                           (*session.image_shape, session.bands))
        _require_frame_shape(file, frame_spec(file), (*session.image_shape, session.bands))


def load_session(path) -> Session:
    """Load and check a session folder (manifest and every frame header; no pixels are read).

    Raises:
      SessionError: a missing folder or manifest; a manifest that is not JSON, not a session,
        of a newer format version, with a missing or mistyped field (named), exposures that do not
        match the bands, a bad region, not exactly one dark and one white frame or more than one
        registration frame; a frame file that is missing, outside the folder, not a
        16-bit image, or of the wrong size or channel count. The message names the file.
    """
    root = pathlib.Path(path)
    if not root.is_dir():
        problem = "is not a folder" if root.exists() else "no such folder"
        raise SessionError(root, problem, f"a session folder holding {MANIFEST_NAME}")
    manifest_path = root / MANIFEST_NAME
    if not manifest_path.exists():
        raise SessionError(manifest_path, "no such file", "the manifest of a spherejax session")
    session = _parse_manifest(_read_manifest(manifest_path), manifest_path=manifest_path, root=root)
    for frame in session.frames:
        _check_frame_file(session, frame)
    return session


def _frame_entries(manifest_path, frames) -> list[tuple[dict, np.ndarray]]:
    """(manifest entry with "file", array) per (frame dict, array) given to `write_session`."""
    entries = []
    for index, item in enumerate(frames):
        where = f"frames[{index}]"
        if not (isinstance(item, Sequence) and len(item) == 2 and isinstance(item[0], Mapping)):
            problem = f"{where} is a {type(item).__name__}"
            raise SessionError(manifest_path, problem, "a (frame dict, array) pair")
        frame, array = item
        frame_id = frame.get("id")
        if not (isinstance(frame_id, str) and _SAFE_ID.fullmatch(frame_id)):
            raise SessionError(
                manifest_path, f"{where}.id is {_show(frame_id)}", "a name of A-Z a-z 0-9 . _ -"
            )
        if "file" in frame:
            raise SessionError(
                manifest_path, f"{where} names a file", f"none: it goes to frames/{frame_id}.tif"
            )
        entries.append(({**frame, "file": f"frames/{frame_id}.tif"}, np.asarray(array)))
    return entries


def check_new_session_folder(path) -> None:
    """Raise SessionError unless `path` is absent or an empty folder (where a session may go).

    The session is renamed into place at `path` (`write_session`), which replaces an empty folder
    and nothing else: a symbolic link there (to an empty folder or to nothing) is refused, as is a
    name ending in ".." (it names a folder that exists, the one above), so that such a path fails
    here, before the work, and not at the rename after it.
    """
    path = pathlib.Path(path)
    if path.is_symlink():
        raise SessionError(
            path, f"is a symbolic link (to {os.readlink(path)})",
            "a new or empty folder: the session would replace the link, which spherejax did not make",
        )
    if path.name == "..":
        raise SessionError(path, f"names the folder {os.path.realpath(path)} through '..'", "a new or empty folder")
    if path.exists() and not (path.is_dir() and not any(path.iterdir())):
        raise SessionError(
            path, "already exists and is not an empty folder", "a new or empty folder"
        )


def write_session(
    path,
    *,
    instrument_id: str,
    band_centres_nm,
    image_shape: Sequence[int],
    saturation: int | float,
    white_patch: Sequence[int],
    holder: Sequence[int],
    frames: Sequence[tuple[Mapping, np.ndarray]],
    metadata: Mapping | None = None,
    created: str | None = None,
    band_transforms=None,
) -> Session:
    """Write a session folder, all or nothing, and load it back.

    Args:
      path: the session folder; must not exist or be empty. Missing parents are created.
      instrument_id, band_centres_nm (B,), image_shape (H, W), saturation, white_patch, holder,
        metadata: the manifest's fields (the docstring of spherejax.io).
      frames: (frame, array) pairs; frame is a dict with the manifest's frame fields except
        "file" (regions as dicts or `Region`s), its "id" a file name ([A-Za-z0-9._-]+); array is
        (H, W, B) uint16. Files go to frames/<id>.tif with channel names "<nm>nm".
      created: ISO 8601 creation time; default now (UTC). Pass one for reproducible output.
      band_transforms: (B, 2, 3) where each band's image lies (`Session.band_transforms`), or None.

    Returns:
      `load_session(path)`.

    Raises:
      SessionError: invalid fields or arrays, or an existing non-empty target, before anything
        is written; a failed write, after which the partly written temporary folder is removed.
    """
    from .. import __version__

    path = pathlib.Path(path)
    manifest_path = path / MANIFEST_NAME
    entries = _frame_entries(manifest_path, frames)
    manifest = {
        "format": SESSION_FORMAT,
        "format_version": SESSION_FORMAT_VERSION,
        "software_version": __version__,
        "instrument_id": instrument_id,
        "created": created if created is not None else _utc_now(),
        "band_centres_nm": band_centres_nm,
        "image_shape": image_shape,
        "saturation": saturation,
        "white_patch": white_patch,
        "holder": holder,
        "frames": [entry for entry, _ in entries],
        "metadata": {} if metadata is None else metadata,
    }
    if band_transforms is not None:
        manifest["band_transforms"] = np.asarray(band_transforms, np.float64).tolist()
    # Check with the loader's own rules first, so nothing is written for a manifest it would refuse.
    manifest = _json_value(manifest_path, manifest, SessionError, "the manifest")
    session = _parse_manifest(manifest, manifest_path=manifest_path, root=path)
    expected_shape = (*session.image_shape, session.bands)
    for frame, (_, array) in zip(session.frames, entries):
        if array.shape != expected_shape or array.dtype != np.uint16:
            raise SessionError(
                path / frame.file,
                f"frame {frame.id!r} is an array of shape {array.shape} and dtype {array.dtype}",
                f"{expected_shape} uint16, (H, W, B) of the session",
            )
    check_new_session_folder(path)

    staging = temp_sibling(path)
    channel_names = [f"{nm}nm" for nm in session.band_centres_nm.tolist()]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        (staging / "frames").mkdir(parents=True)
        for frame, (_, array) in zip(session.frames, entries):
            attributes = {"spherejax:frame_id": frame.id, "spherejax:role": frame.role}
            try:
                write_frame(
                    staging / frame.file, array, channel_names=channel_names, attributes=attributes
                )
            except SpherejaxFileError as error:
                # Name the file as it would have been, not the temporary folder (removed below).
                raise SessionError(path / frame.file, error.problem, error.expected) from None
        # The manifest last: a folder with a manifest is a complete session.
        text = _readable_json(session.to_manifest()) + "\n"
        with atomic_file(staging / MANIFEST_NAME, "w") as manifest:  # fsynced before the folder's rename
            manifest.write(text)
        # POSIX rename replaces an empty folder atomically, and fails on a non-empty one.
        os.rename(staging, path)
        fsync_folder(path.parent)
    except OSError as error:
        raise SessionError(path, f"could not be written: {error.strerror or error}") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return load_session(path)


def write_simulated_session(path, seed: int = 0, instrument=None, design=None) -> Session:
    """Simulate the paper's experiment (`spherejax.simulate.simulate_experiment`) and write it as a
    session folder (`write_session`); return the loaded `Session`.

    Args:
      path: the session folder to create (refused if it exists and is not empty).
      seed: the simulation's seed.
      instrument, design: `simulate.InstrumentModel` and `simulate.ExperimentDesign`, or None
        for the defaults.
    """
    from .. import simulate  # here: the files layer calls the simulator only when asked to

    experiment = simulate.simulate_experiment(seed, instrument, design)
    return write_session(path, **simulate.session_contents(experiment))
