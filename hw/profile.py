"""The instrument profile: which device sits on which port, and which band is which wheel slot.

A TOML file (docs/instrument.md, "16 filters do not fit one wheel": the band -> (wheel, slot)
mapping belongs in a profile, never in code):

    [instrument]
    id = "sphere-1"
    [wheels.a]
    port = "/dev/ttyUSB0"     # any pyserial URL
    model = "FW212C"          # FW102C (6 slots) or FW212C (12 slots)
    open_slot = 12            # the empty slot the wheel rests on when another wheel's filter is used
    move_timeout_s = 20.0     # optional: how long a move may take (up to ~7 s in slow mode)
    [wheels.b]
    port = "/dev/ttyUSB1"
    model = "FW212C"
    open_slot = 12
    [shutter]
    port = "/dev/ttyUSB2"
    model = "SC10"
    [camera]
    backend = "sim"           # "sim", "pvcam" or "genicam"; the other keys are the backend's
    seed = 0                  #   options: sim: seed, image_shape = [H, W], name; pvcam:
                              #   camera_name, exposure_s; genicam: device_id, exposure_s, gain,
                              #   pixel_format, roi, binning, timeout_s (hw.camera.PROFILE_OPTIONS)
    [bands]                   # band centre in nm = [wheel, slot]
    400 = ["a", 1]
    ...

Bands selected by a liquid-crystal tunable filter instead of wheels (hw.tunablefilter): a
[tunable_filter] table in place of [wheels] and [bands]:

    [tunable_filter]
    model = "VariSpec-VIS"    # Kurios-VIS (420-730 nm), Kurios-NIR (650-1100) or VariSpec-VIS (400-720)
    port = "/dev/ttyUSB0"
    bands = [420, 440, 460]   # optional: band centres in nm (default the 16 centres 400..700 step 20),
                              #   each inside the model's range, or the profile is refused here
    settle_s = 0.1            # optional: seconds after each tune before the read-back and the frame
    warmup_timeout_s = 600.0  # optional: how long the filter's warm-up may take before the first frame
    bandwidth = "wide"        # Kurios only: "wide", "medium" or "narrow" (its BW= modes)
    warmup_s = 0.0            # VariSpec only: seconds to wait before the first frame (no warm-up query)

Optional sections (defaults in `AcquisitionSettings` and `Layout`):

    [acquisition]
    frames_averaged = 16      # frames averaged per white-standard and sample frame
    dark_frames = 16          # frames averaged per dark frame (docs/instrument.md: 10-25)
    target_level = 0.8        # exposure: this fraction of full scale ...
    target_percentile = 99.5  # ... at this percentile of the white standard, nothing saturated
    warmup_drift_percent = 0.5
    warmup_interval_s = 30.0  # warm-up check: one white-standard image every interval ...
    warmup_checks = 6         # ... drift measured over this many intervals (3 minutes)
    warmup_timeout_s = 3600.0
    [layout]                  # frame pixels, half-open [r0, r1, c0, c1]; required for a real camera
    white_patch = [10, 20, 10, 20]
    holder = [40, 160, 30, 240]
    [lamp]
    state_file = "lamp.json"  # relative to the profile's folder (default "<profile stem>.lamp.json")
    [[samples]]               # what to capture after the white standard, in order
    id = "s001"
    set = "test"              # "training" or "test"
    background = "black velvet"
    [[samples]]               # optional, at most one: the registration target (docs/instrument.md,
    id = "checkerboard"       #   "Registration target"), captured like a sample where it stands in
    role = "registration"     #   the plan, into the session frame of role "registration"; it takes
                              #   no set or background (role is "sample" by default)
    [noise]                   # the camera's noise, recorded in the session for calibrate's
    gain_e_per_count = 1.04   #   noise model: electrons per count (> 0), and one frame's read
    read_noise_counts = 5.8   #   noise in counts rms (>= 0); give both or neither (a camera
                              #   that reports its own, the simulated one, overrides them)
    white_reflectance_u = 0.003  # optional: relative standard uncertainty (>= 0) of the white
                              #   standard's certified reflectance (0.003 = 0.3 %)

Every number is bounded by a documented limit (`LIMITS`: the waits, timeouts and counts a run
acts on), generous for any instrument but finite: `settle_s = 1e300` would otherwise overflow the
wait once the devices had moved, and `dark_frames = 9223372036854775807` would average for ever.

    tunable_filter.settle_s          0 .. 60 s      a liquid crystal settles in tens of ms
    tunable_filter.warmup_s          0 .. 3600 s    a VariSpec warms up in minutes
    tunable_filter.warmup_timeout_s  > 0 .. 86400 s
    wheels.NAME.move_timeout_s       > 0 .. 600 s   a slow-mode move takes up to about 7 s
    acquisition.warmup_interval_s    0 .. 3600 s
    acquisition.warmup_timeout_s     > 0 .. 86400 s a lamp warms up in tens of minutes
    acquisition.frames_averaged,
      dark_frames, warmup_checks     1 .. 1000
    noise.gain_e_per_count           > 0 .. 1e6;  read_noise_counts 0 .. 1e6;
    noise.white_reflectance_u        0 .. 1
    camera options                   hw.camera.PROFILE_OPTIONS (exposures and timeouts <= 3600 s)

Everything is checked when the profile is read, before any device is opened, and a problem is
one `ProfileError` line naming the file and the key: a missing key, an unknown key (a typo must not
pass silently, nor a camera option the backend does not take), two bands on one slot, a slot beyond
the wheel's count or on its open slot, a band on a wheel the profile does not define, a path that
leaves the profile's folder, a [noise] value out of range or one of gain_e_per_count and
read_noise_counts without the other, set or background on the registration target or a second
registration target in [[samples]]. The tables are declared as documents
(spherejax.io.documents): strict types, so a TOML boolean or float is never taken for an integer.
"""

from __future__ import annotations

import dataclasses
import functools
import pathlib
import re
import tomllib
from collections.abc import Mapping
from typing import Annotated, Any, Literal

import pydantic
from pydantic import AfterValidator
from spherejax.io.plain_files import read_small
from spherejax.io.documents import Document, Expect, NonEmptyStr, Rectangle, check_document, integer, number, refuse

from .camera import PROFILE_OPTIONS, ProfileOption
from .errors import InstrumentError
from .tunablefilter import KURIOS_BANDWIDTHS, MODELS as TUNABLE_FILTER_MODELS

#: Positions of each filter wheel model (Thorlabs: pcount accepts only 6 or 12).
WHEEL_POSITIONS = {"FW102C": 6, "FW212C": 12}
SHUTTER_MODELS = ("SC10",)
CAMERA_BACKENDS = tuple(PROFILE_OPTIONS)
SETS = ("training", "test")
#: The roles of a [[samples]] entry: a sample (the default), or the registration target (at most one).
PLAN_ROLES = ("sample", "registration")

#: The documented limits of the profile's numbers (module docstring): key -> (low, high).
LIMITS = {
    "settle_s": (0.0, 60.0),
    "warmup_s": (0.0, 3600.0),
    "move_timeout_s": (0.0, 600.0),
    "warmup_interval_s": (0.0, 3600.0),
    "warmup_timeout_s": (0.0, 86400.0),
    "frames": (1, 1000),
    "gain_e_per_count": (0.0, 1e6),
    "read_noise_counts": (0.0, 1e6),
    "white_reflectance_u": (0.0, 1.0),
}


def _seconds(key: str, *, above_zero: bool = False, why: str = ""):
    """A number of seconds within LIMITS[key] (> its low end if `above_zero`), worded with them."""
    low, high = LIMITS[key]
    bound = number(gt=low, le=high) if above_zero else number(ge=low, le=high)
    text = f"seconds {'>' if above_zero else '>='} {low:g} and <= {high:g}" + (f" ({why})" if why else "")
    return Annotated[bound, Expect(text)]


def _count():
    low, high = LIMITS["frames"]
    return Annotated[integer(low, high), Expect(f"an integer >= {low} and <= {high}")]

_SAFE_ID = re.compile(r"[A-Za-z0-9._-]+")


class ProfileError(InstrumentError, ValueError):
    """An instrument profile that cannot be used: "FILE: key: problem (expected ...)"."""

    def __init__(self, path, key: str | None, problem: str, expected: str | None = None):
        self.path, self.key, self.problem, self.expected = str(path), key, problem, expected
        message = f"{self.path}: " + (f"{key}: " if key else "") + problem
        if expected:
            message += f" (expected {expected})"
        super().__init__(" ".join(message.split()))


@dataclasses.dataclass(frozen=True)
class WheelConfig:
    name: str
    port: str
    model: str
    open_slot: int
    move_timeout_s: float = 20.0

    @property
    def positions(self) -> int:
        return WHEEL_POSITIONS[self.model]


@dataclasses.dataclass(frozen=True)
class ShutterConfig:
    port: str
    model: str


#: The band centres of a [tunable_filter] profile that lists none: the instrument's 16.
DEFAULT_BANDS_NM = tuple(range(400, 701, 20))


@dataclasses.dataclass(frozen=True)
class TunableFilterConfig:
    """[tunable_filter]: the filter's model and port, the bands it is tuned to (nm, increasing),
    and the family's options (`options`: bandwidth for a Kurios, warmup_s for a VariSpec)."""

    model: str
    port: str
    bands: tuple[int, ...]
    settle_s: float = 0.1
    warmup_timeout_s: float = 600.0
    options: Mapping = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class CameraConfig:
    backend: str
    options: Mapping = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class AcquisitionSettings:
    frames_averaged: int = 16
    dark_frames: int = 16
    target_level: float = 0.8
    target_percentile: float = 99.5
    warmup_drift_percent: float = 0.5
    warmup_interval_s: float = 30.0
    warmup_checks: int = 6
    warmup_timeout_s: float = 3600.0


@dataclasses.dataclass(frozen=True)
class Layout:
    white_patch: tuple[int, int, int, int] | None = None
    holder: tuple[int, int, int, int] | None = None


@dataclasses.dataclass(frozen=True)
class NoiseSettings:
    """[noise]: the camera's gain (e-/count) and read noise (counts rms), both or neither, and
    the white standard's relative certificate uncertainty; None where the profile gives none."""

    gain_e_per_count: float | None = None
    read_noise_counts: float | None = None
    white_reflectance_u: float | None = None


@dataclasses.dataclass(frozen=True)
class SamplePlan:
    """One [[samples]] entry: a sample (its set and background), or with role "registration" the
    registration target (set and background None)."""

    id: str
    set: str | None = "test"
    background: str | None = "unknown"
    role: str = "sample"


@dataclasses.dataclass(frozen=True)
class Profile:
    """A checked instrument profile (module docstring). `bands` maps band centre (nm) to
    (wheel name, slot), in increasing band order; with a tunable filter `wheels` and `bands` are
    empty and `tunable_filter` lists the bands."""

    path: pathlib.Path
    instrument_id: str
    wheels: Mapping[str, WheelConfig]
    shutter: ShutterConfig
    camera: CameraConfig
    bands: Mapping[int, tuple[str, int]]
    acquisition: AcquisitionSettings
    layout: Layout
    lamp_state_file: pathlib.Path
    samples: tuple[SamplePlan, ...]
    noise: NoiseSettings = NoiseSettings()
    tunable_filter: TunableFilterConfig | None = None

    @property
    def band_centres_nm(self) -> list[int]:
        if self.tunable_filter is not None:
            return list(self.tunable_filter.bands)
        return list(self.bands)

    def positions_for(self, band_nm: int) -> dict[str, int]:
        """The slot of every wheel for one band: its filter on one wheel, the open slot on the
        others."""
        wheel, slot = self.bands[band_nm]
        return {name: (slot if name == wheel else config.open_slot) for name, config in self.wheels.items()}

    def band_at(self, positions: Mapping[str, int]) -> int | None:
        """The band whose filter the wheel positions put in the light path; None when no filter
        or more than one is in the path (or a position is unknown)."""
        in_path = [
            (name, slot) for name, slot in positions.items()
            if name in self.wheels and slot != self.wheels[name].open_slot
        ]
        if len(in_path) != 1 or set(positions) != set(self.wheels):
            return None
        for band, place in self.bands.items():
            if place == in_path[0]:
                return band
        return None


# The profile as documents (spherejax.io.documents), tables and keys in the order they are checked.

_Port = Annotated[str, pydantic.Field(min_length=1), Expect("a serial port path or pyserial URL")]
_WheelModel = Annotated[Literal[tuple(WHEEL_POSITIONS)], Expect(f"one of {sorted(WHEEL_POSITIONS)}")]
# Which slots exist depends on the wheel's model: the range is checked with it (_Wheel below).
_Slot = Annotated[int, Expect("a slot 1..12 of the FW212C, 1..6 of the FW102C")]
_MoveTimeout = _seconds("move_timeout_s", above_zero=True, why="a slow-mode move takes up to about 7 s")
_ShutterModel = Annotated[Literal[SHUTTER_MODELS], Expect(f"one of {list(SHUTTER_MODELS)}")]
_Backend = Annotated[Literal[CAMERA_BACKENDS], Expect(f"one of {list(CAMERA_BACKENDS)}")]
_Table = Expect("a table")


def _band_place(value: list) -> tuple[str, int]:
    if not (len(value) == 2 and isinstance(value[0], str) and type(value[1]) is int):
        raise ValueError("not [wheel, slot]")
    return value[0], value[1]


_BandPlace = Annotated[list, AfterValidator(_band_place), Expect("[wheel, slot] with a wheel of [wheels] and its slot number")]
_SampleId = Annotated[str, pydantic.Field(pattern=r"^[A-Za-z0-9._-]+$"), Expect("a name of letters, digits, '.', '_' or '-'")]
_ProfileRectangle = Annotated[Rectangle, Expect("[r0, r1, c0, c1], integers with r0 < r1 and c0 < c1")]


class _Instrument(Document):
    id: NonEmptyStr


_FilterModel = Annotated[Literal[tuple(TUNABLE_FILTER_MODELS)], Expect(f"one of {sorted(TUNABLE_FILTER_MODELS)}")]
_Bandwidth = Annotated[Literal[tuple(m for m in KURIOS_BANDWIDTHS if m != "black")], Expect("one of wide, medium, narrow")]


class _TunableFilter(Document):
    model: _FilterModel
    port: _Port
    bands: Annotated[list[integer(1)], pydantic.Field(min_length=1), Expect("a list of band centres in nm")] | None = None
    settle_s: _seconds("settle_s") = TunableFilterConfig.settle_s
    warmup_timeout_s: _seconds("warmup_timeout_s", above_zero=True) = TunableFilterConfig.warmup_timeout_s
    bandwidth: _Bandwidth | None = None
    warmup_s: _seconds("warmup_s") | None = None

    @pydantic.model_validator(mode="after")
    def _bands_the_model_tunes(self):
        family = TUNABLE_FILTER_MODELS[self.model].family
        for key, only in (("bandwidth", "kurios"), ("warmup_s", "varispec")):
            if getattr(self, key) is not None and family != only:
                raise refuse(f"is given for a {self.model}", f"no {key}: it is a {only.capitalize()} option", (key,))
        bands = list(DEFAULT_BANDS_NM if self.bands is None else self.bands)
        if sorted(set(bands)) != bands:
            raise refuse(f"is {bands}", "band centres in increasing order, each once", ("bands",))
        low, high = TUNABLE_FILTER_MODELS[self.model].range_nm
        outside = [band for band in bands if not low <= band <= high]
        if outside:
            where = "bands" if self.bands is not None else "model"
            listed = "lists" if self.bands is not None else "has no bands list, so asks for the 16 centres with"
            raise refuse(
                f"{listed} {outside} nm, outside the {self.model}'s {low:g}-{high:g} nm",
                f"bands = [...] of centres inside {low:g}-{high:g} nm", (where,),
            )
        return self


class _Wheel(Document):
    port: _Port
    model: _WheelModel
    open_slot: _Slot
    move_timeout_s: _MoveTimeout = 20.0

    @pydantic.model_validator(mode="after")
    def _slot_of_the_model(self):
        count = WHEEL_POSITIONS[self.model]
        if not 1 <= self.open_slot <= count:
            raise refuse(f"is {self.open_slot}", f"a slot 1..{count} of the {self.model}", ("open_slot",))
        return self


class _Shutter(Document):
    port: _Port
    model: _ShutterModel


class _CameraBackend(Document):
    backend: _Backend


def _option_type(option: ProfileOption):
    """A [camera] option (hw.camera.PROFILE_OPTIONS) as a field type: its TOML kind, checked."""
    kinds = option.kinds if isinstance(option.kinds, tuple) else (option.kinds,)
    kind = number() if float in kinds else kinds[0]  # (int, float): any finite number

    def check(value):
        if option.check is not None and not option.check(value):
            raise ValueError("refused by the backend's check")
        return value

    return Annotated[kind, AfterValidator(check), Expect(option.expected)]


#: Per backend, its [camera] table: "backend" and the options its constructor takes.
_CAMERA_TABLES = {
    backend: pydantic.create_model(
        f"_Camera_{backend}", __base__=Document, backend=(_Backend, ...),
        **{name: (_option_type(option) | None, None) for name, option in options.items()},
    )
    for backend, options in PROFILE_OPTIONS.items()
}


class _Acquisition(Document):
    frames_averaged: _count() = AcquisitionSettings.frames_averaged
    dark_frames: _count() = AcquisitionSettings.dark_frames
    target_level: Annotated[number(gt=0, lt=1), Expect("a fraction of full scale in (0, 1)")] = AcquisitionSettings.target_level
    target_percentile: Annotated[number(gt=0, le=100), Expect("a percentile in (0, 100]")] = AcquisitionSettings.target_percentile
    warmup_drift_percent: Annotated[number(gt=0), Expect("a percentage > 0")] = AcquisitionSettings.warmup_drift_percent
    warmup_interval_s: _seconds("warmup_interval_s") = AcquisitionSettings.warmup_interval_s
    warmup_checks: _count() = AcquisitionSettings.warmup_checks
    warmup_timeout_s: _seconds("warmup_timeout_s", above_zero=True) = AcquisitionSettings.warmup_timeout_s


class _Layout(Document):
    white_patch: _ProfileRectangle | None = None
    holder: _ProfileRectangle | None = None


class _Lamp(Document):
    state_file: Annotated[str, Expect("a file name")] | None = None  # None: "<profile stem>.lamp.json"


class _Sample(Document):
    id: _SampleId
    role: Annotated[Literal[PLAN_ROLES], Expect(f"one of {list(PLAN_ROLES)}")] = "sample"
    set: Annotated[Literal[SETS], Expect(f"one of {list(SETS)}")] | None = None  # None: "test" for a sample
    background: NonEmptyStr | None = None  # None: "unknown" for a sample

    @pydantic.model_validator(mode="after")
    def _registration_target_alone(self):
        if self.role == "registration":
            for key in ("set", "background"):
                if getattr(self, key) is not None:
                    raise refuse("is given for the registration target", f"no {key} on the registration target", (key,))
        return self


class _Noise(Document):
    gain_e_per_count: Annotated[number(gt=0, le=LIMITS["gain_e_per_count"][1]),
                                Expect("electrons per count, a number > 0 and <= 1e+06")] | None = None
    read_noise_counts: Annotated[number(ge=0, le=LIMITS["read_noise_counts"][1]),
                                 Expect("one frame's read noise in counts rms, a number >= 0 and <= 1e+06")] | None = None
    white_reflectance_u: Annotated[number(ge=0, le=LIMITS["white_reflectance_u"][1]),
                                   Expect("a relative standard uncertainty >= 0 and <= 1 (0.003 for 0.3 %)")] | None = None

    @pydantic.model_validator(mode="after")
    def _both_or_neither(self):
        if (self.gain_e_per_count is None) != (self.read_noise_counts is None):
            given, missing = (
                ("gain_e_per_count", "read_noise_counts") if self.read_noise_counts is None
                else ("read_noise_counts", "gain_e_per_count")
            )
            raise refuse(f"is missing ({given} is given)", "both gain_e_per_count and read_noise_counts, or neither", (missing,))
        return self


class _Profile(Document):
    instrument: Annotated[_Instrument, _Table]
    # Wheels and their [bands], or a [tunable_filter]: one band selector (_one_band_selector).
    wheels: Annotated[dict[str, Annotated[_Wheel, _Table]], pydantic.Field(min_length=1), Expect("a table of [wheels.NAME] tables")] | None = None
    tunable_filter: Annotated[_TunableFilter, _Table] | None = None
    shutter: Annotated[_Shutter, _Table]
    camera: Annotated[dict[str, Any], _Table]  # its keys depend on the backend: _CAMERA_TABLES
    bands: Annotated[dict[str, _BandPlace], pydantic.Field(min_length=1), Expect('a table of lines "NM = [WHEEL, SLOT]"')] | None = None
    layout: Annotated[_Layout, _Table] = _Layout()
    lamp: Annotated[_Lamp, _Table] = _Lamp()
    samples: Annotated[list[Annotated[_Sample, _Table]], Expect("[[samples]] tables")] = []
    acquisition: Annotated[_Acquisition, _Table] = _Acquisition()
    noise: Annotated[_Noise, _Table] = _Noise()

    @pydantic.model_validator(mode="after")
    def _one_band_selector(self):
        if self.tunable_filter is not None:
            for key in ("wheels", "bands"):
                if getattr(self, key) is not None:
                    raise refuse(
                        "is given beside [tunable_filter]",
                        "either [wheels] with [bands], or [tunable_filter] with its bands = [...]", (key,),
                    )
        elif self.wheels is None:
            raise refuse("is missing", "a table of [wheels.NAME] tables with [bands], or a [tunable_filter] table", ("wheels",))
        elif self.bands is None:
            raise refuse("is missing", 'a table of lines "NM = [WHEEL, SLOT]"', ("bands",))
        return self

    @pydantic.model_validator(mode="after")
    def _bands_on_slots(self):
        owner = {}
        for key, (wheel, slot) in (self.bands or {}).items():
            at = ("bands", key)
            if not re.fullmatch(r"[1-9]\d{2,3}", key):
                raise refuse("is not a band centre", "an integer wavelength in nm", at)
            if wheel not in self.wheels:
                raise refuse(f"names wheel {wheel!r}", f"one of the profile's wheels {sorted(self.wheels)}", at)
            config = self.wheels[wheel]
            count = WHEEL_POSITIONS[config.model]
            if not 1 <= slot <= count:
                raise refuse(f"names slot {slot} of wheel {wheel!r}", f"a slot 1..{count} of its {config.model}", at)
            if slot == config.open_slot:
                raise refuse(f"names slot {slot}, wheel {wheel!r}'s open slot", "a slot holding a filter", at)
            if (wheel, slot) in owner:
                raise refuse(f"names wheel {wheel!r} slot {slot}, already band {owner[(wheel, slot)]}", "one band per slot", at)
            owner[(wheel, slot)] = int(key)
        return self

    @pydantic.model_validator(mode="after")
    def _unique_samples(self):
        seen, registration = set(), None
        for index, sample in enumerate(self.samples):
            if sample.id in seen or sample.id in ("dark", "white"):
                raise refuse(f"is {sample.id!r}, already taken", "a unique sample id", ("samples", index, "id"))
            seen.add(sample.id)
            if sample.role == "registration":
                if registration is not None:
                    raise refuse(f'is "registration" again (samples[{registration}] is the registration target)',
                                 "at most one [[samples]] entry with role = \"registration\"", ("samples", index, "role"))
                registration = index
        return self


def _profile_error(path, location: str, problem: str, expected: str | None) -> ProfileError:
    return ProfileError(path, location or None, problem, expected)


def _camera(path, table: Mapping) -> CameraConfig:
    """[camera]: the backend and the options passed to its constructor, each checked against
    what that backend declares (hw.camera.PROFILE_OPTIONS), so that a typo or an option of
    another backend is refused here, before any device is opened, not as a TypeError later."""
    error = functools.partial(_profile_error, path)
    present = {"backend": table["backend"]} if "backend" in table else {}
    backend = check_document(_CameraBackend, present, error=error, where="camera").backend
    declared = PROFILE_OPTIONS[backend]
    checked = check_document(
        _CAMERA_TABLES[backend], table, error=error, where="camera", unknown="key",
        unknown_expected=f"an option of the {backend!r} backend: one of {sorted(declared)}" if declared
        else f"no option: the {backend!r} backend takes none",
    )
    return CameraConfig(backend, {name: getattr(checked, name) for name in declared if name in table})


def _inside(path: pathlib.Path, key: str, value: str) -> pathlib.Path:
    """A path from the profile, relative to its folder and confined to it."""
    folder = path.resolve().parent
    relative = pathlib.PurePosixPath(value)
    # A NUL byte cannot be in a file name: resolving one raises ValueError.
    if relative.is_absolute() or ".." in relative.parts or not value or "\0" in value:
        raise ProfileError(path, key, f"is {value!r}", "a file name inside the profile's folder")
    target = (folder / relative).resolve()
    if not target.is_relative_to(folder):
        raise ProfileError(path, key, f"is {value!r}, which resolves outside the profile's folder", "a file inside it")
    return target


def _tunable_filter(table: _TunableFilter | None) -> TunableFilterConfig | None:
    if table is None:
        return None
    options = {key: getattr(table, key) for key in ("bandwidth", "warmup_s") if getattr(table, key) is not None}
    return TunableFilterConfig(
        model=table.model, port=table.port,
        bands=tuple(DEFAULT_BANDS_NM if table.bands is None else table.bands),
        settle_s=float(table.settle_s), warmup_timeout_s=float(table.warmup_timeout_s),
        options={key: float(value) if key == "warmup_s" else value for key, value in options.items()},
    )


def load_profile(path) -> Profile:
    """Read and check an instrument profile (module docstring).

    Raises:
      ProfileError: unreadable or not TOML, or any key missing, unknown or invalid; before any
        device is opened.
    """
    path = pathlib.Path(path)
    try:
        # Bounded, and a FIFO refused at once: a profile is a few kilobytes.
        data = tomllib.loads(read_small(path, 1 << 20).decode("utf-8"))
    except FileNotFoundError:
        raise ProfileError(path, None, "no such file", "an instrument profile (TOML)") from None
    except OSError as error:
        raise ProfileError(path, None, f"cannot be read: {error.strerror or error}", "an instrument profile (TOML)") from None
    except UnicodeDecodeError as error:
        # Python's codec words ("'utf-8' codec can't decode byte 0x80 in position 0") in plain ones.
        problem = f"is not UTF-8 text: byte {error.start} (0x{error.object[error.start]:02x}) cannot be decoded"
        raise ProfileError(path, None, problem, "an instrument profile (TOML, UTF-8 text)") from None
    except (ValueError, RecursionError) as error:
        # TOMLDecodeError is a ValueError; so is int() refusing an integer of more than 4300
        # digits, and arrays nested thousands deep raise RecursionError.
        raise ProfileError(path, None, f"is not valid TOML: {error}", "an instrument profile (TOML)") from None
    doc = check_document(_Profile, data, error=functools.partial(_profile_error, path), unknown="key")
    camera = _camera(path, doc.camera)
    layout = Layout(doc.layout.white_patch, doc.layout.holder)
    if camera.backend != "sim" and (layout.white_patch is None or layout.holder is None):
        raise ProfileError(
            path, "layout", "does not give white_patch and holder",
            "[layout] white_patch and holder rectangles for a real camera",
        )
    state_file = doc.lamp.state_file if doc.lamp.state_file is not None else f"{path.stem}.lamp.json"
    acquisition = doc.acquisition
    return Profile(
        path=path,
        instrument_id=doc.instrument.id,
        wheels={
            name: WheelConfig(name, wheel.port, wheel.model, wheel.open_slot, float(wheel.move_timeout_s))
            for name, wheel in (doc.wheels or {}).items()
        },
        shutter=ShutterConfig(doc.shutter.port, doc.shutter.model),
        camera=camera,
        bands={int(key): place for key, place in sorted((doc.bands or {}).items(), key=lambda item: int(item[0]))},
        tunable_filter=_tunable_filter(doc.tunable_filter),
        acquisition=AcquisitionSettings(
            frames_averaged=acquisition.frames_averaged,
            dark_frames=acquisition.dark_frames,
            target_level=float(acquisition.target_level),
            target_percentile=float(acquisition.target_percentile),
            warmup_drift_percent=float(acquisition.warmup_drift_percent),
            warmup_interval_s=float(acquisition.warmup_interval_s),
            warmup_checks=acquisition.warmup_checks,
            warmup_timeout_s=float(acquisition.warmup_timeout_s),
        ),
        layout=layout,
        lamp_state_file=_inside(path, "lamp.state_file", state_file),
        samples=tuple(
            SamplePlan(sample.id, None, None, "registration") if sample.role == "registration"
            else SamplePlan(sample.id, sample.set or "test", sample.background or "unknown")
            for sample in doc.samples
        ),
        noise=NoiseSettings(
            *(None if value is None else float(value) for value in (
                doc.noise.gain_e_per_count, doc.noise.read_noise_counts, doc.noise.white_reflectance_u
            ))
        ),
    )


__all__ = [
    "LIMITS",
    "WHEEL_POSITIONS",
    "ProfileError",
    "WheelConfig",
    "ShutterConfig",
    "TunableFilterConfig",
    "DEFAULT_BANDS_NM",
    "CameraConfig",
    "AcquisitionSettings",
    "Layout",
    "NoiseSettings",
    "PLAN_ROLES",
    "SamplePlan",
    "Profile",
    "load_profile",
]
