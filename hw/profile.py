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
    backend = "sim"           # "sim" or "pvcam"; the other keys are the backend's options:
    seed = 0                  #   sim: seed, image_shape = [H, W], name; pvcam: camera_name,
                              #   exposure_s (hw.camera.PROFILE_OPTIONS)
    [bands]                   # band centre in nm = [wheel, slot]
    400 = ["a", 1]
    ...

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
    [noise]                   # the camera's noise, recorded in the session for calibrate's
    gain_e_per_count = 1.04   #   noise model: electrons per count (> 0), and one frame's read
    read_noise_counts = 5.8   #   noise in counts rms (>= 0); give both or neither (a camera
                              #   that reports its own, the simulated one, overrides them)
    white_reflectance_u = 0.003  # optional: relative standard uncertainty (>= 0) of the white
                              #   standard's certified reflectance (0.003 = 0.3 %)

Everything is checked when the profile is read, before any device is opened, and a problem is
one `ProfileError` line naming the file and the key: a missing key, an unknown key (a typo must not
pass silently, nor a camera option the backend does not take), two bands on one slot, a slot beyond
the wheel's count or on its open slot, a band on a wheel the profile does not define, a path that
leaves the profile's folder, a [noise] value out of range or one of gain_e_per_count and
read_noise_counts without the other.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import re
import tomllib
from collections.abc import Mapping

from .camera import PROFILE_OPTIONS
from .errors import InstrumentError

#: Positions of each filter wheel model (Thorlabs: pcount accepts only 6 or 12).
WHEEL_POSITIONS = {"FW102C": 6, "FW212C": 12}
SHUTTER_MODELS = ("SC10",)
CAMERA_BACKENDS = tuple(PROFILE_OPTIONS)
SETS = ("training", "test")
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
    id: str
    set: str = "test"
    background: str = "unknown"


@dataclasses.dataclass(frozen=True)
class Profile:
    """A checked instrument profile (module docstring). `bands` maps band centre (nm) to
    (wheel name, slot), in increasing band order."""

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

    @property
    def band_centres_nm(self) -> list[int]:
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


class _Table:
    """One TOML table being checked: every access names the key in errors."""

    def __init__(self, path, data, where: str):
        self.path, self.where = path, where
        if not isinstance(data, dict):
            raise ProfileError(path, where or None, f"is {_show(data)}", "a table")
        self.data = data

    def key(self, name: str) -> str:
        return f"{self.where}.{name}" if self.where else name

    def only(self, allowed, *, expected: str | None = None) -> None:
        unknown = sorted(set(self.data) - set(allowed))
        if unknown:
            raise ProfileError(self.path, self.key(unknown[0]), "is not a known key", expected or f"one of {sorted(allowed)}")

    def get(self, name: str, kind, expected: str, *, default=dataclasses.MISSING, check=None):
        if name not in self.data:
            if default is dataclasses.MISSING:
                raise ProfileError(self.path, self.key(name), "is missing", expected)
            return default
        value = self.data[name]
        # A TOML boolean is a Python int: refuse it wherever a number is expected (kind may be a
        # tuple such as (int, float), which `kind in (int, float)` would not catch).
        ok = isinstance(value, kind) and not (isinstance(value, bool) and kind is not bool)
        if ok and isinstance(value, (int, float)) and not isinstance(value, bool):
            try:
                ok = math.isfinite(value)
            except OverflowError:  # a TOML integer beyond float range: float() of it would raise
                ok = False
        if not ok or (check is not None and not check(value)):
            raise ProfileError(self.path, self.key(name), f"is {_show(value)}", expected)
        return value

    def table(self, name: str, *, required: bool = True) -> _Table:
        if name not in self.data and not required:
            return _Table(self.path, {}, self.key(name))
        if name not in self.data:
            raise ProfileError(self.path, self.key(name), "is missing", "a table")
        return _Table(self.path, self.data[name], self.key(name))


def _show(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _rect(table: _Table, name: str):
    value = table.get(
        name, list, "[r0, r1, c0, c1], integers with r0 < r1 and c0 < c1", default=None,
        check=lambda v: len(v) == 4 and all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in v)
        and v[0] < v[1] and v[2] < v[3],
    )
    return None if value is None else tuple(value)


def _wheels(root: _Table) -> dict[str, WheelConfig]:
    table = root.table("wheels")
    if not table.data:
        raise ProfileError(table.path, "wheels", "defines no wheel", "[wheels.NAME] tables")
    wheels = {}
    for name in table.data:
        wheel = table.table(name)
        wheel.only({"port", "model", "open_slot", "move_timeout_s"})
        port = wheel.get("port", str, "a serial port path or pyserial URL", check=bool)
        model = wheel.get("model", str, f"one of {sorted(WHEEL_POSITIONS)}", check=lambda m: m in WHEEL_POSITIONS)
        count = WHEEL_POSITIONS[model]
        open_slot = wheel.get("open_slot", int, f"a slot 1..{count} of the {model}", check=lambda s: 1 <= s <= count)
        move_timeout_s = float(wheel.get(
            "move_timeout_s", (int, float), "seconds > 0 (a slow-mode move takes up to about 7 s)",
            default=20.0, check=lambda v: v > 0,
        ))
        wheels[name] = WheelConfig(name, port, model, open_slot, move_timeout_s)
    return wheels


def _camera(root: _Table) -> CameraConfig:
    """[camera]: the backend and the options passed to its constructor, each checked against
    what that backend declares (hw.camera.PROFILE_OPTIONS), so that a typo or an option of
    another backend is refused here, before any device is opened, not as a TypeError later."""
    table = root.table("camera")
    backend = table.get("backend", str, f"one of {list(CAMERA_BACKENDS)}", check=lambda b: b in CAMERA_BACKENDS)
    declared = PROFILE_OPTIONS[backend]
    table.only(
        {"backend", *declared},
        expected=f"an option of the {backend!r} backend: one of {sorted(declared)}" if declared
        else f"no option: the {backend!r} backend takes none",
    )
    options = {
        name: table.get(name, option.kinds, option.expected, check=option.check)
        for name, option in declared.items() if name in table.data
    }
    return CameraConfig(backend, options)


def _bands(root: _Table, wheels: Mapping[str, WheelConfig]) -> dict[int, tuple[str, int]]:
    table = root.table("bands")
    if not table.data:
        raise ProfileError(table.path, "bands", "lists no band", 'lines "NM = [WHEEL, SLOT]"')
    bands, owner = {}, {}
    for key in table.data:
        if not re.fullmatch(r"[1-9]\d{2,3}", key):
            raise ProfileError(table.path, f"bands.{key}", "is not a band centre", "an integer wavelength in nm")
        value = table.get(
            key, list, f"[wheel, slot] with a wheel of [wheels] ({', '.join(wheels)})",
            check=lambda v: len(v) == 2 and isinstance(v[0], str) and isinstance(v[1], int) and not isinstance(v[1], bool),
        )
        wheel, slot = value
        if wheel not in wheels:
            raise ProfileError(table.path, f"bands.{key}", f"names wheel {wheel!r}", f"one of the profile's wheels {sorted(wheels)}")
        config = wheels[wheel]
        if not 1 <= slot <= config.positions:
            raise ProfileError(
                table.path, f"bands.{key}", f"names slot {slot} of wheel {wheel!r}",
                f"a slot 1..{config.positions} of its {config.model}",
            )
        if slot == config.open_slot:
            raise ProfileError(
                table.path, f"bands.{key}", f"names slot {slot}, wheel {wheel!r}'s open slot",
                "a slot holding a filter",
            )
        if (wheel, slot) in owner:
            raise ProfileError(
                table.path, f"bands.{key}", f"names wheel {wheel!r} slot {slot}, already band {owner[(wheel, slot)]}",
                "one band per slot",
            )
        owner[(wheel, slot)] = int(key)
        bands[int(key)] = (wheel, slot)
    return dict(sorted(bands.items()))


def _acquisition(root: _Table) -> AcquisitionSettings:
    table = root.table("acquisition", required=False)
    defaults = AcquisitionSettings()
    table.only({f.name for f in dataclasses.fields(AcquisitionSettings)})
    positive_int = lambda v: v >= 1  # noqa: E731
    return AcquisitionSettings(
        frames_averaged=table.get("frames_averaged", int, "an integer >= 1", default=defaults.frames_averaged, check=positive_int),
        dark_frames=table.get("dark_frames", int, "an integer >= 1", default=defaults.dark_frames, check=positive_int),
        target_level=float(table.get("target_level", (int, float), "a fraction of full scale in (0, 1)", default=defaults.target_level, check=lambda v: 0 < v < 1)),
        target_percentile=float(table.get("target_percentile", (int, float), "a percentile in (0, 100]", default=defaults.target_percentile, check=lambda v: 0 < v <= 100)),
        warmup_drift_percent=float(table.get("warmup_drift_percent", (int, float), "a percentage > 0", default=defaults.warmup_drift_percent, check=lambda v: v > 0)),
        warmup_interval_s=float(table.get("warmup_interval_s", (int, float), "seconds >= 0", default=defaults.warmup_interval_s, check=lambda v: v >= 0)),
        warmup_checks=table.get("warmup_checks", int, "an integer >= 1", default=defaults.warmup_checks, check=positive_int),
        warmup_timeout_s=float(table.get("warmup_timeout_s", (int, float), "seconds > 0", default=defaults.warmup_timeout_s, check=lambda v: v > 0)),
    )


def _noise(root: _Table) -> NoiseSettings:
    table = root.table("noise", required=False)
    table.only({f.name for f in dataclasses.fields(NoiseSettings)})

    def number(name: str, expected: str, check):
        value = table.get(name, (int, float), expected, default=None, check=check)
        return None if value is None else float(value)

    gain = number("gain_e_per_count", "electrons per count, a number > 0", lambda v: v > 0)
    read_noise = number("read_noise_counts", "one frame's read noise in counts rms, a number >= 0", lambda v: v >= 0)
    if (gain is None) != (read_noise is None):
        given, missing = ("gain_e_per_count", "read_noise_counts") if read_noise is None else ("read_noise_counts", "gain_e_per_count")
        raise ProfileError(
            table.path, table.key(missing), f"is missing ({given} is given)",
            "both gain_e_per_count and read_noise_counts, or neither",
        )
    return NoiseSettings(
        gain_e_per_count=gain, read_noise_counts=read_noise,
        white_reflectance_u=number(
            "white_reflectance_u", "a relative standard uncertainty >= 0 (0.003 for 0.3 %)", lambda v: v >= 0
        ),
    )


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


def load_profile(path) -> Profile:
    """Read and check an instrument profile (module docstring).

    Raises:
      ProfileError: unreadable or not TOML, or any key missing, unknown or invalid; before any
        device is opened.
    """
    path = pathlib.Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ProfileError(path, None, "no such file", "an instrument profile (TOML)") from None
    except (OSError, UnicodeDecodeError) as error:
        raise ProfileError(path, None, f"cannot be read: {error}", "an instrument profile (TOML)") from None
    except (ValueError, RecursionError) as error:
        # TOMLDecodeError is a ValueError; so is int() refusing an integer of more than 4300
        # digits, and arrays nested thousands deep raise RecursionError.
        raise ProfileError(path, None, f"is not valid TOML: {error}", "an instrument profile (TOML)") from None
    root = _Table(path, data, "")
    root.only({"instrument", "wheels", "shutter", "camera", "bands", "acquisition", "layout", "lamp", "samples", "noise"})

    instrument = root.table("instrument")
    instrument.only({"id"})
    instrument_id = instrument.get("id", str, "a non-empty string", check=bool)

    wheels = _wheels(root)
    shutter_table = root.table("shutter")
    shutter_table.only({"port", "model"})
    shutter = ShutterConfig(
        port=shutter_table.get("port", str, "a serial port path or pyserial URL", check=bool),
        model=shutter_table.get("model", str, f"one of {list(SHUTTER_MODELS)}", check=lambda m: m in SHUTTER_MODELS),
    )
    camera = _camera(root)
    backend = camera.backend
    bands = _bands(root, wheels)

    layout_table = root.table("layout", required=False)
    layout_table.only({"white_patch", "holder"})
    layout = Layout(_rect(layout_table, "white_patch"), _rect(layout_table, "holder"))
    if backend != "sim" and (layout.white_patch is None or layout.holder is None):
        raise ProfileError(
            path, "layout", "does not give white_patch and holder",
            "[layout] white_patch and holder rectangles for a real camera",
        )

    lamp_table = root.table("lamp", required=False)
    lamp_table.only({"state_file"})
    state_file = lamp_table.get("state_file", str, "a file name", default=f"{path.stem}.lamp.json")
    lamp_state_file = _inside(path, "lamp.state_file", state_file)

    samples, seen = [], set()
    plans = data.get("samples", [])
    if not isinstance(plans, list):
        raise ProfileError(path, "samples", f"is {_show(plans)}", "[[samples]] tables")
    for index, plan in enumerate(plans):
        table = _Table(path, plan, f"samples[{index}]")
        table.only({"id", "set", "background"})
        sample_id = table.get("id", str, "a name of letters, digits, '.', '_' or '-'", check=lambda v: _SAFE_ID.fullmatch(v) is not None)
        if sample_id in seen or sample_id in ("dark", "white"):
            raise ProfileError(path, f"samples[{index}].id", f"is {sample_id!r}, already taken", "a unique sample id")
        seen.add(sample_id)
        samples.append(SamplePlan(
            sample_id,
            table.get("set", str, f"one of {list(SETS)}", default="test", check=lambda v: v in SETS),
            table.get("background", str, "a non-empty string", default="unknown", check=bool),
        ))
    return Profile(
        path=path, instrument_id=instrument_id, wheels=wheels, shutter=shutter, camera=camera,
        bands=bands, acquisition=_acquisition(root), layout=layout, lamp_state_file=lamp_state_file,
        samples=tuple(samples), noise=_noise(root),
    )


__all__ = [
    "WHEEL_POSITIONS",
    "ProfileError",
    "WheelConfig",
    "ShutterConfig",
    "CameraConfig",
    "AcquisitionSettings",
    "Layout",
    "NoiseSettings",
    "SamplePlan",
    "Profile",
    "load_profile",
]
