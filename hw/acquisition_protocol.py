"""The acquisition protocol of docs/instrument.md on connected devices: what is captured, and how.

    plan         `_captures`: dark, white, then the profile's [[samples]] in order (without them,
                 every scene of the simulated camera, or one sample), each a `Capture`; the entry
                 with role = "registration", if any, is the registration target, taken like a
                 sample into the session's frame of role "registration"
    warm-up      `_warm_up`: the white standard imaged until the lamp drifts less than
                 warmup_drift_percent over warmup_checks intervals (AcquisitionStopped after
                 warmup_timeout_s)
    exposures    `choose_exposure`, per band on the white standard
    captures     `_run_protocol`: every band image of every capture the journal does not hold
                 yet, each written and journalled by `_take_image` before the next is taken

A band image is written atomically as SESSION.partial/captures/<capture>/<nm>nm.tif, (H, W, 1)
uint16 counts (the average of the frames, rounded), with its metadata: band centre, wheel slots
read back, exposure (s), frames averaged, UTC time stamp, sensor temperature (°C), lamp hours
and saturated pixels; then recorded as one journal line (`acquisition_journal.Journal`). Between
band images, warm-up checks and exposure choices, `spherejax.interrupt.check()` is the safe
point a stop request is honoured at. `Operator` asks the operator to place what is imaged.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import sys
import time
from collections.abc import Callable, Sequence

import numpy as np

from spherejax import interrupt

from .acquisition_devices import Instrument
from .acquisition_journal import Journal, _sha256, _utc_now
from .camera import Camera
from .errors import AcquisitionError, AcquisitionStopped
from .profile import Profile


@dataclasses.dataclass(frozen=True)
class Capture:
    """One session frame to acquire: dark, white, a sample (with its session fields) or the
    registration target."""

    id: str
    role: str  # "dark", "white", "sample", "target" or "registration"
    fields: dict = dataclasses.field(default_factory=dict)  # set, background, regions, ...
    scene: str | None = None  # what the simulated camera renders; None for darks


#: What the simulated camera shows for a registration target it has no scene of the same name
#: for: the chart of colour targets, its scene with the most edges (it renders no checkerboard).
SIMULATED_REGISTRATION_SCENE = "targets"


def _captures(profile: Profile, camera: Camera) -> list[Capture]:
    """Dark, white, then the sample plan (the profile's [[samples]], the registration target among
    them where it stands, or for the simulated camera without one, every capture of the simulated
    experiment)."""
    captures = [Capture("dark", "dark"), Capture("white", "white", scene="white")]
    if profile.samples:
        # The simulated camera knows where each of its scenes' patches lie: their regions go into
        # the session, so it can be calibrated like a simulated one.
        known = {f["id"]: f for f in camera.scene_frames()} if hasattr(camera, "scene_frames") else None
        for plan in profile.samples:
            if plan.role == "registration":
                # Its id is the lab's name for its target; the simulated camera shows the scene of
                # that name if it has one, else its chart. No regions: nothing is averaged on it.
                scene = plan.id if known is None or plan.id in known else SIMULATED_REGISTRATION_SCENE
                captures.append(Capture(plan.id, "registration", scene=scene))
                continue
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


# ------------------------------------------------------------------------------------- operator


class Operator:
    """Operator prompts: on a terminal, wait for Enter; with `yes`, say what is assumed done."""

    def __init__(self, *, yes: bool, stream=None, input_fn: Callable[[str], str] = input):
        self.yes, self.stream, self.input_fn = yes, stream or sys.stderr, input_fn

    def check_can_prompt(self) -> None:
        if not self.yes and not _stdin_is_terminal():
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
            try:
                self.input_fn(f"{message}, then press Enter ")
            except EOFError:  # the terminal closed (Ctrl-D, a hang-up) while the prompt waited
                raise AcquisitionError(
                    f"standard input ended while waiting for the operator ({message}); "
                    "expected Enter at the terminal, or --yes"
                ) from None


def _stdin_is_terminal() -> bool:
    """Whether stdin is a terminal an operator can answer at: False for a closed stdin (`<&-`:
    sys.stdin is None outside the command line, which opens /dev/null there) or a pipe."""
    try:
        return sys.stdin is not None and sys.stdin.isatty()
    except (AttributeError, ValueError, OSError):  # replaced by an object without it, or closed
        return False


# ------------------------------------------------------------------------------------- protocol


@dataclasses.dataclass
class Settings:
    """How a run behaves beyond the profile: sleep and clock are injectable for tests."""

    # The lamp's warm-up interval (30 s by default) in slices with a safe point after each.
    sleep: Callable[[float], None] = interrupt.sleep
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


def _run_protocol(instrument: Instrument, captures: Sequence[Capture], partial: pathlib.Path, journal: Journal, config, operator: Operator, settings: Settings) -> None:
    """The protocol from lamp on to the last band image (module docstring): the warm-up always,
    the exposures unless the journal holds them, then every band image it does not hold."""
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
            if capture.role == "registration":
                operator.ask(f"Place the registration target {capture.id!r} on the sample holder, filling it, "
                             "flat and in focus")
            elif capture.role != "white":  # the white standard is in place since the warm-up
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


def _image_metadata(instrument: Instrument, band: int, selection, exposure: float, frames: int, saturated: int) -> dict:
    """A band image's metadata; `selection` is what the band selector's `select` returned (the
    wheels' slots, or the wavelength a tunable filter reads back)."""
    return {
        "band_nm": band,
        **instrument.bank.image_metadata(band, selection),
        "exposure_s": exposure,
        "frames_averaged": frames,
        "timestamp": _utc_now(),
        "temperature_c": instrument.camera.temperature_c(),  # °C, or None (JSON null): hw.camera
        "lamp_hours": round(float(instrument.lamp.hours()), 4),
        "saturated_pixels": saturated,
    }


def _take_image(instrument: Instrument, partial: pathlib.Path, journal: Journal, capture: Capture, band: int, exposure: float, frames: int) -> None:
    from spherejax import io

    selection = instrument.bank.select(band)
    camera = instrument.camera
    camera.exposure_s = exposure
    average = camera.average(frames)
    full = _full_scale(camera)
    saturated = int(np.count_nonzero(average >= full))
    image = np.clip(np.rint(average), 0, 65535).astype(np.uint16)
    metadata = _image_metadata(instrument, band, selection, exposure, frames, saturated)
    relative = f"captures/{capture.id}/{band}nm.tif"
    path = partial / relative
    path.parent.mkdir(parents=True, exist_ok=True)
    io.write_frame(path, image[..., None], channel_names=[f"{band}nm"], attributes={"spherejax:acquisition": json.dumps(metadata, sort_keys=True)})
    journal.append({"event": "image", "capture": capture.id, "band_nm": band, "file": relative, "sha256": _sha256(path), "metadata": metadata})


__all__ = ["Capture", "Operator", "Settings", "choose_exposure"]
