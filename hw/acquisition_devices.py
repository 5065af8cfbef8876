"""The devices of one acquisition, opened and checked before anything moves (`connect`).

`connect` opens the profile's band selector, its filter wheels (`hw.filterbank`) or its
liquid-crystal tunable filter (`hw.tunablefilter`), and the shutter (or, with --emulate, emulated
ones on pseudo-terminals, `hw.emulators`, `hw.tunablefilter_emulators`) and checks them (*idn?,
pcount? against the profile; the filter's identity, tuning range and warm-up; id?), then the
camera: the profile's backend, or the simulated camera (`hw.simcamera`) wired to the band in the
light path and to the shutter, so that its frames follow what the devices do. A device that
fails its check is one AcquisitionError line naming it and its profile key.

The band selector (`Instrument.bank`) is either kind; the acquisition asks the same of both:
`select(band)`, `band_in_path()` and `image_metadata(band, selection)`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import pathlib
from collections.abc import Iterator

from .camera import Camera, CameraError, open_camera
from .errors import AcquisitionError, HardwareError
from .filterbank import FilterBank, WheelCountMismatch
from .filterwheel import FilterWheel
from .lamp import Lamp
from .profile import Profile
from .shutter import Shutter
from .tunablefilter import TunableFilter, open_filter


@dataclasses.dataclass
class Instrument:
    """The connected devices of one run."""

    profile: Profile
    bank: FilterBank | TunableFilter  # the band selector
    shutter: Shutter
    camera: Camera
    lamp: Lamp
    emulated: object | None = None  # hw.emulators ports when --emulate


def _emulate(profile: Profile, stack: contextlib.ExitStack):
    """Emulated wheels or tunable filter, and shutter, on pseudo-terminals, in the profile's
    initial state (an emulated filter warmed up and tuning its model's nominal range)."""
    from .emulators import EmulatedPort, FilterWheelEmulator, ShutterEmulator
    from .tunablefilter import MODELS
    from .tunablefilter_emulators import KuriosEmulator, VariSpecEmulator

    wheels = {
        name: stack.enter_context(EmulatedPort(FilterWheelEmulator(model=config.model, position=config.open_slot)).start())
        for name, config in profile.wheels.items()
    }
    tunable_filter = None
    if profile.tunable_filter is not None:
        model = MODELS[profile.tunable_filter.model]
        emulator = (KuriosEmulator if model.family == "kurios" else VariSpecEmulator)(range_nm=model.range_nm)
        tunable_filter = stack.enter_context(EmulatedPort(emulator).start())
    shutter = stack.enter_context(EmulatedPort(ShutterEmulator(closed=True)).start())
    return {"wheels": wheels, "tunable_filter": tunable_filter, "shutter": shutter}


def _band_selector(profile: Profile, stack: contextlib.ExitStack, emulated) -> FilterBank | TunableFilter:
    """The profile's wheels as one FilterBank, or its tunable filter, connected and checked; the
    filter's warm-up waited for."""
    if profile.tunable_filter is not None:
        config = profile.tunable_filter
        port = emulated["tunable_filter"].path if emulated else config.port
        with _naming(f"tunable filter {config.model} ([tunable_filter])"):
            selector = stack.enter_context(open_filter(
                port, model=config.model, bands_nm=profile.band_centres_nm, settle_s=config.settle_s,
                **config.options,  # its waits are spherejax.interrupt.sleep: a stop cuts them short
            ))
            selector.check()
            selector.wait_until_ready(config.warmup_timeout_s)
        return selector
    wheel_ports = {name: (emulated["wheels"][name].path if emulated else cfg.port) for name, cfg in profile.wheels.items()}
    wheels = {}
    for name, config in profile.wheels.items():
        with _naming(f"wheel {name!r} ([wheels.{name}])"):
            wheels[name] = stack.enter_context(
                FilterWheel(wheel_ports[name], model=config.model, move_timeout_s=config.move_timeout_s)
            )
    bank = FilterBank(profile, wheels)
    with _naming("filter wheels"):
        bank.check()
    return bank


def _emulated_band(profile: Profile, emulated) -> int | None:
    """The band the emulated selector puts in the light path (read from the emulators' state)."""
    if profile.tunable_filter is not None:
        wavelength = emulated["tunable_filter"].emulator.wavelength_nm
        return next((band for band in profile.band_centres_nm if abs(band - wavelength) <= 0.5), None)
    return profile.band_at({name: port.emulator.position for name, port in emulated["wheels"].items()})


def connect(profile: Profile, stack: contextlib.ExitStack, *, emulate: bool, lamp_state_file: pathlib.Path,
            through_gige: bool = False) -> Instrument:
    """Open and check every device; nothing moves until all checks pass. `through_gige`: the
    simulated camera's frames through Aravis's fake GigE Vision camera and the GenICam backend
    (`hw.simulated_gige`).

    Raises AcquisitionError naming the device for an *idn?/id? mismatch, a pcount? that
    disagrees with the profile, a tunable filter whose range misses a band or whose warm-up does
    not end, or a device that does not answer.
    """
    emulated = _emulate(profile, stack) if emulate else None
    shutter_port = emulated["shutter"].path if emulated else profile.shutter.port
    bank = _band_selector(profile, stack, emulated)
    with _naming("shutter ([shutter])"):
        shutter = stack.enter_context(Shutter(shutter_port))

    if profile.camera.backend == "sim":
        from .simcamera import SimulatedCamera

        if emulated:
            light_path = lambda: _band_index(_emulated_band(profile, emulated))  # noqa: E731
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
        if through_gige:
            from .simulated_gige import SimulatorThroughGigE

            try:
                camera = SimulatorThroughGigE(camera)
            except (CameraError, ValueError) as error:
                raise AcquisitionError(f"camera: {error}") from None
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


__all__ = ["Instrument", "connect"]
