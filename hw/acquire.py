"""`spherejax acquire`: the acquisition protocol of docs/instrument.md, written as a session.

    connect      wheels (*idn?, pcount? against the profile, sensors=0), shutter (id?, closed),
                 camera, lamp state; nothing moves before every check has passed
    warm-up      white standard in place: one band's central-region mean imaged every interval
                 until it drifts less than warmup_drift_percent over warmup_checks intervals
    exposures    per band on the white standard: a high percentile near target_level of full
                 scale, nothing saturated (blue bands get much longer exposures)
    dark         shutter closed, per band at that band's exposure, dark_frames averaged
    white        the white standard, per band, frames_averaged averaged
    samples      each sample of the plan, per band, frames_averaged averaged, the reference
                 patch in view
    session      the frames assembled into a spherejax session (`spherejax.io.write_session`)

Nothing is lost on a fault. Work goes to SESSION.partial/ beside SESSION: every band image is
written (atomically) as captures/<capture>/<nm>nm.tif with its metadata, then recorded as one
fsynced line of journal.jsonl; exposures and the warm-up result are journal lines too. When the
last band image is in, the session is written (all or nothing) and SESSION.partial/ removed. A
device that stops answering, answers garbage or vanishes stops the run with one line; the shutter
is closed if it still answers, and `--resume` re-runs the warm-up check and takes only the band
images the journal does not hold (verified by SHA-256), with the exposures already chosen, so
darks, whites and samples always share exposures. A kill while the session is written leaves its
hidden staging folder beside SESSION; `--resume` removes it.

SIGINT (Ctrl-C) or SIGTERM, when the command line has turned them into stop requests
(`spherejax.interrupt`), stop the run between band images (or warm-up checks, or exposure
choices): the shutter is closed, the journal and SESSION.partial are kept for `--resume`, and
`acquire` raises `interrupt.Interrupted` saying how many band images are kept.

Per band image the metadata holds: band centre, every wheel's slot read back with pos?, the
exposure, frames averaged, time stamp (UTC), sensor temperature, lamp hours and the count of
saturated pixels. Averages are rounded to 16-bit counts for the session's frames. Each session
frame's metadata holds these per band ("bands") and, as a simulated session does, the frames
averaged for the frame ("frames_averaged": dark_frames for the dark, frames_averaged for the
white standard and samples; the fewest of its bands should a resumed run have changed them).
The session's metadata "camera" holds the camera's gain ("gain_e_per_count") and read noise
("read_noise_counts") when known, for calibrate's noise model: the camera's own (the simulated
camera's model), else the profile's [noise]; and the profile's white_reflectance_u if given.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
import os
import pathlib
import shutil
import sys
import time
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from spherejax import interrupt, jsontext
from spherejax.io.plain_files import read_small

from .camera import Camera, CameraError, open_camera
from .errors import HardwareError, InstrumentError
from .filterbank import FilterBank, WheelCountMismatch
from .filterwheel import FilterWheel
from .lamp import Lamp, LampStateError
from .profile import Profile, load_profile
from .shutter import Shutter

JOURNAL_NAME = "journal.jsonl"
PARTIAL_SUFFIX = ".partial"


class AcquisitionError(InstrumentError):
    """The acquisition cannot start: one line saying why; nothing moved, nothing was written."""


class AcquisitionStopped(AcquisitionError):
    """A fault stopped a running acquisition: one line saying why and what was kept."""


@dataclasses.dataclass(frozen=True)
class Capture:
    """One session frame to acquire: dark, white or a sample (with its session fields)."""

    id: str
    role: str  # "dark", "white", "sample" or "target"
    fields: dict = dataclasses.field(default_factory=dict)  # set, background, regions, ...
    scene: str | None = None  # what the simulated camera renders; None for darks


# ------------------------------------------------------------------------------------- operator


class Operator:
    """Operator prompts: on a terminal, wait for Enter; with `yes`, say what is assumed done."""

    def __init__(self, *, yes: bool, stream=None, input_fn: Callable[[str], str] = input):
        self.yes, self.stream, self.input_fn = yes, stream or sys.stderr, input_fn

    def check_can_prompt(self) -> None:
        if not self.yes and not sys.stdin.isatty():
            raise AcquisitionError(
                "acquire needs an operator at a terminal to place the white standard and samples; "
                "pass --yes to answer every prompt as done"
            )

    def ask(self, message: str) -> None:
        if self.yes:
            print(f"spherejax: {message}: assumed done (--yes)", file=self.stream, flush=True)
            return
        # A signal while the prompt waits stops the run at once, not after the next Enter.
        with interrupt.immediately():
            self.input_fn(f"{message}, then press Enter ")


# -------------------------------------------------------------------------------------- journal


def _utc_now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _sha256(path: pathlib.Path) -> str | None:
    """The SHA-256 (hex) of a band image, or None when it cannot be read as a regular file. No
    safe point: it is called while a stop is handled, to count what was kept."""
    from spherejax.io.hashing import sha256_file

    try:
        return sha256_file(path, check=None)
    except OSError:
        return None


class Journal:
    """SESSION.partial/journal.jsonl: one fsynced JSON line per finished step (`spherejax.io.journal`,
    the format of a batch's manifest too); a line cut by a kill is ignored on reading."""

    def __init__(self, folder: pathlib.Path):
        from spherejax.io.journal import Journal as JsonLines

        self.folder = folder
        self.path = folder / JOURNAL_NAME
        # No safe point: read while a stop is handled (`acquire`), to say what was kept.
        self._lines = JsonLines(self.path, key="event")

    def records(self) -> list[dict]:
        return list(self._lines.records())

    def append(self, record: dict) -> None:
        # Opened for each record: a symbolic link in the journal's place must not redirect the
        # append (O_NOFOLLOW), and a FIFO there must not make the acquisition wait for a reader.
        self._lines.append(record)

    def last(self, event: str) -> dict | None:
        found = [r for r in self.records() if r["event"] == event]
        return found[-1] if found else None

    def done_images(self) -> dict[tuple[str, int], dict]:
        """(capture id, band) -> record of every band image whose file is there, unchanged."""
        done = {}
        for record in self.records():
            if record["event"] != "image":
                continue
            file = self.folder / record["file"]
            if _sha256(file) == record.get("sha256"):
                done[(record["capture"], int(record["band_nm"]))] = record
        return done


# ------------------------------------------------------------------------------------- devices


@dataclasses.dataclass
class Instrument:
    """The connected devices of one run."""

    profile: Profile
    bank: FilterBank
    shutter: Shutter
    camera: Camera
    lamp: Lamp
    emulated: object | None = None  # hw.emulators ports when --emulate


def _emulate(profile: Profile, stack: contextlib.ExitStack):
    """Emulated wheels and shutter on pseudo-terminals, in the profile's initial state."""
    from .emulators import EmulatedPort, FilterWheelEmulator, ShutterEmulator

    wheels = {
        name: stack.enter_context(EmulatedPort(FilterWheelEmulator(model=config.model, position=config.open_slot)).start())
        for name, config in profile.wheels.items()
    }
    shutter = stack.enter_context(EmulatedPort(ShutterEmulator(closed=True)).start())
    return {"wheels": wheels, "shutter": shutter}


def connect(profile: Profile, stack: contextlib.ExitStack, *, emulate: bool, lamp_state_file: pathlib.Path) -> Instrument:
    """Open and check every device; nothing moves until all checks pass.

    Raises AcquisitionError naming the device for an *idn?/id? mismatch, a pcount? that
    disagrees with the profile, or a device that does not answer.
    """
    emulated = _emulate(profile, stack) if emulate else None
    wheel_ports = {name: (emulated["wheels"][name].path if emulated else cfg.port) for name, cfg in profile.wheels.items()}
    shutter_port = emulated["shutter"].path if emulated else profile.shutter.port
    wheels = {}
    for name, config in profile.wheels.items():
        with _naming(f"wheel {name!r} ([wheels.{name}])"):
            wheels[name] = stack.enter_context(
                FilterWheel(wheel_ports[name], model=config.model, move_timeout_s=config.move_timeout_s)
            )
    bank = FilterBank(profile, wheels)
    with _naming("filter wheels"):
        bank.check()
    with _naming("shutter ([shutter])"):
        shutter = stack.enter_context(Shutter(shutter_port))

    if profile.camera.backend == "sim":
        from .simcamera import SimulatedCamera

        if emulated:
            wheel_state = emulated["wheels"]
            light_path = lambda: _band_index(profile.band_at({n: p.emulator.position for n, p in wheel_state.items()}))  # noqa: E731
            shutter_open = lambda: not emulated["shutter"].emulator.closed  # noqa: E731
        else:
            light_path = lambda: _band_index(bank.band_in_path())  # noqa: E731
            shutter_open = lambda: not shutter.is_closed()  # noqa: E731
        options = dict(profile.camera.options)
        camera = SimulatedCamera(light_path=light_path, shutter_open=shutter_open, **options)
        missing = sorted(set(profile.band_centres_nm) - set(camera.band_centres_nm))
        if missing:
            raise AcquisitionError(
                f"{profile.path}: bands {missing} nm: the simulated camera renders only "
                f"{camera.band_centres_nm[0]}..{camera.band_centres_nm[-1]} nm step 20"
            )
    else:
        try:
            camera = open_camera(profile.camera.backend, **profile.camera.options)
        except (CameraError, ValueError) as error:
            raise AcquisitionError(f"camera: {error}") from None
    stack.callback(camera.close)
    return Instrument(profile, bank, shutter, camera, Lamp(lamp_state_file), emulated)


@contextlib.contextmanager
def _naming(device: str) -> Iterator[None]:
    """A failed device check as one AcquisitionError naming the device and its profile key."""
    try:
        yield
    except WheelCountMismatch as error:
        raise AcquisitionError(str(error)) from None
    except HardwareError as error:
        raise AcquisitionError(f"{device} failed its check: {error}") from None


def _band_index(band: int | None) -> int | None:
    """The simulated camera's band index of a band in the path (its bands are spherejax's grid;
    `connect` has checked the profile's bands are among them)."""
    from spherejax.grid import BAND_CENTRES_NM

    return None if band is None else BAND_CENTRES_NM.tolist().index(band)


# ------------------------------------------------------------------------------------- protocol


@dataclasses.dataclass
class Settings:
    """How a run behaves beyond the profile: sleep and clock are injectable for tests."""

    sleep: Callable[[float], None] = time.sleep
    log: Callable[[str], None] = lambda line: print(f"spherejax: {line}", file=sys.stderr, flush=True)
    progress: Callable[[int, int], None] | None = None  # (done, total) band images


def _central_mean(frame: np.ndarray) -> float:
    height, width = frame.shape
    return float(frame[height // 3 : 2 * height // 3, width // 3 : 2 * width // 3].mean())


def _full_scale(camera: Camera) -> int:
    return 2 ** int(camera.bit_depth) - 1


def choose_exposure(camera: Camera, settings, *, start_s: float) -> tuple[float, float]:
    """Exposure putting the `target_percentile` of a frame at `target_level` of full scale
    with no saturated pixel (docs/instrument.md, "Acquisition protocol", step 2). Returns (exposure_s, level reached)."""
    low, high = camera.exposure_limits_s
    full = _full_scale(camera)
    exposure = float(np.clip(start_s, low, high))
    level = 0.0
    for _ in range(12):
        camera.exposure_s = exposure
        frame = camera.snap()
        saturated = int(np.count_nonzero(frame >= full))
        level = float(np.percentile(frame, settings.target_percentile)) / full
        if saturated:
            new = exposure / 4.0
        elif abs(level / settings.target_level - 1.0) <= 0.03:
            return exposure, level
        else:
            new = exposure * settings.target_level / max(level, 1e-3)
        new = float(np.clip(new, low, high))
        if new == exposure:  # at a limit: the best this camera can do
            return exposure, level
        exposure = new
    return exposure, level


def _warm_up(instrument: Instrument, exposures: dict[int, float] | None, settings: Settings, config) -> dict:
    """Image the white standard until the lamp is stable (docs/instrument.md, "Acquisition protocol", step 1)."""
    profile, camera = instrument.profile, instrument.camera
    band = profile.band_centres_nm[len(profile.band_centres_nm) // 2]
    instrument.bank.select(band)
    instrument.shutter.open_shutter()
    exposure = exposures[band] if exposures else choose_exposure(camera, config, start_s=0.05)[0]
    camera.exposure_s = exposure
    means, times, start = [], [], time.monotonic()
    needed = config.warmup_checks + 1
    while True:
        interrupt.check()
        means.append(_central_mean(camera.average(4)))
        times.append(time.monotonic())
        if len(means) >= needed:
            window = np.asarray(means[-needed:])
            # The drift is the trend over the window (a straight-line fit), not the frame-to-frame
            # flicker, which averaging cannot remove entirely and which would never settle.
            slope = np.polyfit(np.arange(needed, dtype=np.float64), window, 1)[0]
            drift = abs(slope * (needed - 1)) / float(window.mean()) * 100.0
            if drift < config.warmup_drift_percent:
                minutes = (times[-1] - times[-needed]) / 60.0  # as measured, not as planned
                settings.log(f"lamp stable: {drift:.2f} % drift over {minutes:.2g} min at {band} nm")
                return {"band_nm": band, "drift_percent": drift, "window_min": minutes, "checks": len(means)}
        if time.monotonic() - start > config.warmup_timeout_s:
            raise AcquisitionStopped(
                f"the lamp did not stabilise: the white standard still drifts more than "
                f"{config.warmup_drift_percent} % after {config.warmup_timeout_s:.0f} s"
            )
        settings.sleep(config.warmup_interval_s)


def _captures(profile: Profile, camera: Camera) -> list[Capture]:
    """Dark, white, then the sample plan (the profile's [[samples]], or for the simulated
    camera without one, every capture of the simulated experiment)."""
    captures = [Capture("dark", "dark"), Capture("white", "white", scene="white")]
    if profile.samples:
        # The simulated camera knows where each of its scenes' patches lie: their regions go into
        # the session, so it can be calibrated like a simulated one.
        known = {f["id"]: f for f in camera.scene_frames()} if hasattr(camera, "scene_frames") else None
        for plan in profile.samples:
            if known is not None and plan.id not in known:
                raise AcquisitionError(
                    f"{profile.path}: samples id {plan.id!r} is not a scene of the simulated camera "
                    f"(expected one of {', '.join(list(known)[:4])}, ...)"
                )
            fields = {"set": plan.set, "background": plan.background}
            if known is not None and known[plan.id].get("regions"):
                fields["regions"] = known[plan.id]["regions"]
            captures.append(Capture(plan.id, "sample", fields, scene=plan.id))
    elif hasattr(camera, "scene_frames"):
        for frame_fields in camera.scene_frames():
            fields = {k: v for k, v in frame_fields.items() if k not in ("id", "role")}
            captures.append(Capture(frame_fields["id"], frame_fields["role"], fields, scene=frame_fields["id"]))
    else:
        captures.append(Capture("sample", "sample", {"set": "test", "background": "unknown"}, scene=None))
    return captures


def _layout(profile: Profile, camera: Camera) -> tuple[list[int], list[int]]:
    white_patch = profile.layout.white_patch or getattr(camera, "white_patch", None)
    holder = profile.layout.holder or getattr(camera, "holder", None)
    if white_patch is None or holder is None:
        raise AcquisitionError(f"{profile.path}: [layout] white_patch and holder are needed for this camera")
    return [int(v) for v in white_patch], [int(v) for v in holder]


def _image_metadata(instrument: Instrument, band: int, positions: dict, exposure: float, frames: int, saturated: int) -> dict:
    return {
        "band_nm": band,
        "wheel": instrument.profile.bands[band][0],
        "slot": instrument.profile.bands[band][1],
        "positions": positions,
        "exposure_s": exposure,
        "frames_averaged": frames,
        "timestamp": _utc_now(),
        "temperature_c": float(instrument.camera.temperature_c()),
        "lamp_hours": round(float(instrument.lamp.hours()), 4),
        "saturated_pixels": saturated,
    }


def _take_image(instrument: Instrument, partial: pathlib.Path, journal: Journal, capture: Capture, band: int, exposure: float, frames: int) -> None:
    from spherejax import io

    positions = instrument.bank.select(band)
    camera = instrument.camera
    camera.exposure_s = exposure
    average = camera.average(frames)
    full = _full_scale(camera)
    saturated = int(np.count_nonzero(average >= full))
    image = np.clip(np.rint(average), 0, 65535).astype(np.uint16)
    metadata = _image_metadata(instrument, band, positions, exposure, frames, saturated)
    relative = f"captures/{capture.id}/{band}nm.tif"
    path = partial / relative
    path.parent.mkdir(parents=True, exist_ok=True)
    io.write_frame(path, image[..., None], channel_names=[f"{band}nm"], attributes={"spherejax:acquisition": json.dumps(metadata, sort_keys=True)})
    journal.append({"event": "image", "capture": capture.id, "band_nm": band, "file": relative, "sha256": _sha256(path), "metadata": metadata})


def _write_session(out: pathlib.Path, partial: pathlib.Path, journal: Journal, instrument: Instrument, captures: list[Capture], exposures: dict[int, float]):
    from spherejax import io

    profile, camera = instrument.profile, instrument.camera
    done = journal.done_images()
    bands = profile.band_centres_nm
    white_patch, holder = _layout(profile, camera)
    frames = []
    for capture in captures:
        records = [done[(capture.id, band)] for band in bands]
        planes = [io.read_frame(partial / record["file"]) for record in records]
        frame = {
            "id": capture.id,
            "role": capture.role,
            "exposure_s": [float(exposures[band]) for band in bands],
            "timestamp": records[0]["metadata"]["timestamp"],
            "metadata": {
                "bands": [record["metadata"] for record in records],
                # The frame's own count, the key a simulated session has (the bands' counts agree
                # unless a resumed run changed them: then the fewest, the noisiest).
                "frames_averaged": min(int(record["metadata"]["frames_averaged"]) for record in records),
            },
            **capture.fields,
        }
        frames.append((frame, np.concatenate(planes, axis=-1)))
    warmup = journal.last("warmup")
    metadata = {"acquisition": {"profile": str(profile.path), "warmup": warmup and {k: v for k, v in warmup.items() if k != "event"},
                                "camera": getattr(camera, "name", profile.camera.backend)}}
    noise = _camera_noise(profile, camera)
    if noise:
        metadata["camera"] = noise
    return io.write_session(
        out, instrument_id=profile.instrument_id, band_centres_nm=bands,
        image_shape=list(camera.frame_shape), saturation=_full_scale(camera),
        white_patch=white_patch, holder=holder, frames=frames, metadata=metadata,
    )


def _camera_noise(profile: Profile, camera: Camera) -> dict:
    """The session's "camera" record (module docstring): gain and read noise from the camera
    when it knows them, else from the profile's [noise]; the white standard's certificate
    uncertainty from the profile. Empty when nothing is known."""
    record = {}
    known = getattr(camera, "noise_parameters", None)
    if known is not None:
        record.update(known, source=f"camera {camera.name!r}")
    elif profile.noise.gain_e_per_count is not None:
        record.update(
            gain_e_per_count=profile.noise.gain_e_per_count, read_noise_counts=profile.noise.read_noise_counts,
            source=f"profile {profile.path.name} [noise]",
        )
    if profile.noise.white_reflectance_u is not None:
        record["white_reflectance_u"] = profile.noise.white_reflectance_u
    return record


def _check_resume(partial: pathlib.Path, profile: Profile) -> None:
    saved = partial / "profile.json"
    if not saved.is_file():
        # A run killed between creating the folder and renaming profile.json into place left
        # nothing to keep (at most the temporary, half written): the resumed run starts afresh.
        if _is_work_folder(partial):
            return
        raise AcquisitionError(f"{partial}: holds no profile.json: not an acquisition spherejax can resume")
    try:
        before = jsontext.loads(read_small(saved, 1 << 20))
    except jsontext.JSONTextError as error:
        raise AcquisitionError(f"{saved}: {error.problem}: not an acquisition spherejax can resume") from None
    except OSError as error:
        raise AcquisitionError(f"{saved}: cannot be read: {error.strerror}: not an acquisition spherejax can resume") from None
    now = _profile_identity(profile)
    if before != now:
        changed = sorted(k for k in now if before.get(k) != now[k])
        raise AcquisitionError(
            f"{profile.path}: differs from the interrupted acquisition's profile in {changed} "
            f"(expected the same instrument, bands and samples to resume)"
        )


def _remove_stale_staging(out: pathlib.Path) -> None:
    """Remove the staging folders a run killed while writing the session left beside it.

    io.write_session writes the session into a hidden sibling (`io.temp_sibling`) and renames it
    into place; a kill before the rename leaves that folder, which the run that completes the
    session would otherwise leave there for good. The finished SESSION.partial is moved to such
    a name too before it is deleted (`acquire`).
    Called on --resume only, when the run that made it is over.
    """
    from spherejax import io

    with contextlib.suppress(OSError):
        for entry in out.parent.iterdir():
            if io.is_temp_sibling(entry.name, out.name) and entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)


def _check_ownership(profile: Profile, out: pathlib.Path, partial: pathlib.Path, *, emulate: bool) -> None:
    """Before anything is opened or removed: SESSION and SESSION.partial, the folders `acquire`
    creates and removes whole, are not links (the session is renamed into place, which would
    replace a link; the work folder would be written through one), and neither is, nor holds at
    any depth, the profile or the lamp state file it reads and updates (io.ownership.refuse_holding,
    by resolved path and (st_dev, st_ino)). AcquisitionError, one line naming the folder."""
    from spherejax.io import SpherejaxFileError, ownership

    inputs = {"the profile (--profile)": profile.path}
    if not emulate:  # emulated, the lamp state lives in SESSION.partial, spherejax's own
        inputs["the profile's lamp state file"] = profile.lamp_state_file
    folders = {"-o SESSION": out, "SESSION.partial": partial}
    try:
        for label, folder in folders.items():
            if folder.is_symlink():
                raise SpherejaxFileError(
                    folder, f"{label} is a symbolic link (to {os.readlink(folder)})",
                    f"{label} a folder spherejax makes, not a link",
                )
        ownership.refuse_holding(folders, inputs)
    except SpherejaxFileError as error:
        raise AcquisitionError(str(error)) from None


def _is_work_folder(partial: pathlib.Path) -> bool:
    """True if `partial` is a folder an acquisition made (it holds its profile.json, or only the
    temporary name of one): what `acquire` may remove."""
    from spherejax.io import atomic

    if partial.is_symlink() or not partial.is_dir():
        return False
    if (partial / "profile.json").is_file():
        return True
    return all(atomic.is_temp_sibling(entry.name, "profile.json") for entry in partial.iterdir())


def _profile_identity(profile: Profile) -> dict:
    return {
        "instrument_id": profile.instrument_id,
        "bands": {str(k): list(v) for k, v in profile.bands.items()},
        "samples": [dataclasses.asdict(s) for s in profile.samples],
        "camera": profile.camera.backend,
    }


def acquire(
    profile_path,
    out,
    *,
    emulate: bool = False,
    resume: bool = False,
    operator: Operator,
    settings: Settings | None = None,
    on_instrument: Callable[[Instrument], None] | None = None,
) -> pathlib.Path:
    """Run the acquisition protocol (module docstring) into the session folder `out`.

    Args:
      profile_path: the instrument profile (TOML, `hw.profile`).
      out: the session folder to write; SESSION.partial beside it holds the work in progress.
      emulate: emulated wheels and shutter on pseudo-terminals and the simulated camera
        (whatever the profile's ports and camera), the lamp state kept in SESSION.partial.
      resume: continue an interrupted acquisition of the same profile.
      operator: prompts (`Operator`).
      settings: sleep / log / progress hooks.
      on_instrument: called with the connected `Instrument` before the protocol starts (tests
        use it to inject faults into emulated devices).

    Returns:
      The session folder.

    Raises:
      ProfileError: a profile that is invalid, before anything is opened.
      AcquisitionError: SESSION or SESSION.partial a symbolic link, or holding the profile or
        its lamp state file (before anything is opened); a device check failed (before anything
        moved), or a fault stopped the run (what was captured stays in SESSION.partial for
        --resume).
    """
    from spherejax.io import atomic

    settings = settings or Settings()
    profile = load_profile(profile_path)
    out = pathlib.Path(out)
    partial = out.with_name(out.name + PARTIAL_SUFFIX)
    if emulate and profile.camera.backend != "sim":
        profile = dataclasses.replace(profile, camera=dataclasses.replace(profile.camera, backend="sim", options={}))
    _check_ownership(profile, out, partial, emulate=emulate)
    if resume:
        _remove_stale_staging(out)
        if (out / "manifest.json").is_file():
            if _is_work_folder(partial):
                shutil.rmtree(partial, ignore_errors=True)  # a run killed after writing the session
            elif os.path.lexists(partial):
                settings.log(f"{partial}: not an acquisition's work folder (no profile.json): left as it is")
            settings.log(f"{out}: the session is already complete")
            return out
        if not partial.is_dir():
            raise AcquisitionError(f"{partial}: no interrupted acquisition to resume (expected the folder a stopped run leaves)")
        _check_resume(partial, profile)
    else:
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise AcquisitionError(f"{out}: already exists and is not empty (expected a new session folder)")
        if partial.exists():
            raise AcquisitionError(f"{partial}: an interrupted acquisition is there (expected --resume to continue it, or remove it)")
    operator.check_can_prompt()
    config = profile.acquisition
    lamp_file = partial / "lamp.json" if emulate else profile.lamp_state_file
    # The lamp's record is read and checked before anything opens or moves: a damaged one (a
    # time stamp without its time zone, say) is refused in one line (LampStateError) that names
    # the file, not as a stopped acquisition whose "run again with --resume" would not mend it.
    Lamp(lamp_file).is_on

    with contextlib.ExitStack() as stack:
        instrument = connect(profile, stack, emulate=emulate, lamp_state_file=lamp_file)
        captures = _captures(profile, instrument.camera)  # checked before anything moves
        _layout(profile, instrument.camera)
        partial.mkdir(parents=True, exist_ok=True)
        # Atomic: a kill while writing it must not leave a folder --resume refuses to read.
        atomic.write_atomic(partial / "profile.json", json.dumps(_profile_identity(profile), sort_keys=True))
        journal = Journal(partial)
        if emulate:
            # An emulated lamp is switched on when the run starts and needs no waiting.
            config = dataclasses.replace(config, warmup_interval_s=0.0)
        if on_instrument is not None:
            on_instrument(instrument)
        try:
            _run_protocol(instrument, captures, partial, journal, config, operator, settings)
        except AcquisitionError:  # already says why and what was kept (the warm-up's)
            instrument.shutter.make_safe()
            raise
        except (InstrumentError, OSError) as error:  # a device, the lamp's record or the disk
            instrument.shutter.make_safe()
            # A lamp record damaged during the run is not mended by --resume: say what is first.
            remedy = (f"mend or remove the lamp state file {lamp_file}, then run again with --resume"
                      if isinstance(error, LampStateError) else "run again with --resume to complete it")
            raise AcquisitionStopped(
                f"acquisition stopped: {' '.join(str(error).split())}; {len(journal.done_images())} band "
                f"images kept in {partial} ({remedy})"
            ) from None
        except interrupt.Interrupted as stopped:
            # SIGINT or SIGTERM (spherejax.interrupt), seen between band images: the journal and
            # SESSION.partial stay as they are for --resume.
            instrument.shutter.make_safe()
            stopped.done, stopped.total = len(journal.done_images()), len(captures) * len(profile.band_centres_nm)
            stopped.unit = "band images"
            raise
        except BaseException:
            instrument.shutter.make_safe()
            raise
        instrument.shutter.make_safe()
        exposures = {int(k): v for k, v in journal.last("exposures")["exposure_s"].items()}
        _write_session(out, partial, journal, instrument, captures, exposures)
        # The session is complete: move the work folder aside at once, in one rename, so that a
        # kill from here on (closing the devices takes a while) leaves no SESSION.partial. Its
        # hidden name is a staging name, which --resume removes if a kill leaves it
        # (`_remove_stale_staging`).
        from spherejax import io

        finished = io.temp_sibling(out)
        os.rename(partial, finished)
    shutil.rmtree(finished, ignore_errors=True)
    return out


def _run_protocol(instrument: Instrument, captures: Sequence[Capture], partial: pathlib.Path, journal: Journal, config, operator: Operator, settings: Settings) -> None:
    profile, camera, lamp = instrument.profile, instrument.camera, instrument.lamp
    bands = profile.band_centres_nm
    done = journal.done_images()
    total = len(captures) * len(bands)
    if len(done) == total:
        return
    if not lamp.is_on:
        operator.ask("Switch the lamp on")
        lamp.switch_on()
    exposures_record = journal.last("exposures")
    exposures = {int(k): v for k, v in exposures_record["exposure_s"].items()} if exposures_record else None

    operator.ask("Place the white standard on the sample holder")
    _set_scene(camera, "white")
    warmup = _warm_up(instrument, exposures, settings, config)
    lamp.record_warmup(warmup["drift_percent"], warmup["window_min"])
    journal.append({"event": "warmup", **warmup, "timestamp": _utc_now()})
    if exposures is None:
        exposures, start = {}, 0.05
        for band in bands:
            interrupt.check()
            instrument.bank.select(band)
            exposures[band], level = choose_exposure(camera, config, start_s=start)
            start = exposures[band]
            settings.log(f"exposure {band} nm: {exposures[band]:.4g} s ({level * 100:.0f} % of full scale)")
        journal.append({"event": "exposures", "exposure_s": {str(b): e for b, e in exposures.items()}, "timestamp": _utc_now()})

    count = len(done)
    for capture in captures:
        missing = [band for band in bands if (capture.id, band) not in done]
        if not missing:
            continue
        if capture.role == "dark":
            instrument.shutter.close_shutter()
            frames = config.dark_frames
        else:
            if capture.role != "white":  # the white standard is in place since the warm-up
                operator.ask(f"Place sample {capture.id!r} on the sample holder")
            _set_scene(camera, capture.scene)
            instrument.shutter.open_shutter()
            frames = config.frames_averaged
        for band in missing:
            interrupt.check()  # a safe point: every band image so far is in the journal
            _take_image(instrument, partial, journal, capture, band, exposures[band], frames)
            count += 1
            if settings.progress is not None:
                settings.progress(count, total)
        settings.log(f"captured {capture.id} ({capture.role}), {len(bands)} bands")
        instrument.shutter.close_shutter()


def _set_scene(camera: Camera, scene: str | None) -> None:
    if scene is not None and hasattr(camera, "set_scene"):
        camera.set_scene(scene)


__all__ = ["AcquisitionError", "AcquisitionStopped", "Operator", "Settings", "Instrument", "Journal", "acquire", "choose_exposure", "connect"]
