"""FilterBank: two stacked emulated wheels on pseudo-terminals driven as one band selector.

Each band's filter sits on one wheel; selecting it puts that wheel on the filter's slot and the
other wheel on its open slot. Assertions read the EMULATORS' state (where the wheels really are)
as well as what the bank reports.
"""

from __future__ import annotations

import contextlib

import pytest

from spherejax_hw.emulators import EmulatedPort, FilterWheelEmulator
from spherejax_hw.errors import DeviceError, ProtocolError
from spherejax_hw.filterbank import FilterBank, WheelCountMismatch
from spherejax_hw.filterwheel import FilterWheel
from spherejax_hw.profile import load_profile

BANDS = list(range(400, 701, 20))  # 400..540 on wheel a slots 1..8, 560..700 on wheel b slots 1..8


def profile_text(model_b: str = "FW212C", open_b: int = 12) -> str:
    bands = "".join(f'{nm} = ["{"a" if i < 8 else "b"}", {i % 8 + 1}]\n' for i, nm in enumerate(BANDS))
    return f"""\
[instrument]
id = "sphere-test"
[wheels.a]
port = "/dev/ttyUSB0"
model = "FW212C"
open_slot = 12
[wheels.b]
port = "/dev/ttyUSB1"
model = "{model_b}"
open_slot = {open_b}
[shutter]
port = "/dev/ttyUSB2"
model = "SC10"
[camera]
backend = "sim"
[bands]
{bands}"""


@pytest.fixture
def profile(tmp_path):
    path = tmp_path / "profile.toml"
    path.write_text(profile_text())
    return load_profile(path)


class Rig:
    """Emulated wheels on ptys, FilterWheels connected to them, and the bank over them."""

    def __init__(self, profile, stack: contextlib.ExitStack, positions: dict[str, int], models=None, connect_model=True):
        models = models or {}
        self.ports = {}
        wheels = {}
        for name, config in profile.wheels.items():
            model = models.get(name, config.model)
            emulator = FilterWheelEmulator(model=model, position=positions.get(name, 1), move_time_scale=0)
            self.ports[name] = stack.enter_context(EmulatedPort(emulator).start())
            wheels[name] = stack.enter_context(
                FilterWheel(self.ports[name].path, model=config.model if connect_model else None, timeout_s=0.5)
            )
        self.wheels = wheels
        self.bank = FilterBank(profile, wheels)

    def emulator(self, name) -> FilterWheelEmulator:
        return self.ports[name].emulator

    def where(self) -> dict[str, int]:
        """Where the emulated wheels really are."""
        return {name: port.emulator.position for name, port in self.ports.items()}

    def moves(self) -> dict[str, int]:
        return {name: len(port.emulator.moves) for name, port in self.ports.items()}

    def move_commands(self) -> dict[str, list[str]]:
        return {name: [c for c in port.emulator.commands if c.startswith("pos=")] for name, port in self.ports.items()}

    def press(self, name, forward=True) -> None:
        """A front-panel button press on one wheel, behind the software's back."""
        with self.ports[name].lock:
            self.emulator(name).press_button(forward)


@pytest.fixture
def rig(profile):
    with contextlib.ExitStack() as stack:
        yield Rig(profile, stack, {"a": 12, "b": 12})


def test_check_passes_and_reads_positions(profile):
    with contextlib.ExitStack() as stack:
        rig = Rig(profile, stack, {"a": 3, "b": 12})
        rig.bank.check()
        assert rig.bank.positions == {"a": 3, "b": 12}
        assert rig.bank.band_in_path() == 440
        assert rig.moves() == {"a": 0, "b": 0}
        assert all("pcount?" in rig.emulator(name).commands for name in ("a", "b"))


def test_check_at_rest_no_band_in_path(rig):
    rig.bank.check()
    assert rig.bank.positions == {"a": 12, "b": 12}
    assert rig.bank.band_in_path() is None


@pytest.mark.parametrize(("band", "expected"), [(400, {"a": 1, "b": 12}), (540, {"a": 8, "b": 12}),
                                                (560, {"a": 12, "b": 1}), (700, {"a": 12, "b": 8})])
def test_select_puts_filter_in_path_and_other_wheel_on_open_slot(rig, band, expected):
    rig.bank.check()
    read_back = rig.bank.select(band)
    assert rig.where() == expected
    assert read_back == expected
    assert rig.bank.positions == expected
    assert rig.bank.band_in_path() == band


def test_select_every_band_in_turn(rig, profile):
    rig.bank.check()
    for band in BANDS + BANDS[::-1]:
        read_back = rig.bank.select(band)
        assert rig.where() == read_back == profile.positions_for(band)
        assert profile.band_at(rig.where()) == band


def test_select_without_check_still_reaches_the_band(rig):
    assert rig.bank.select(600) == rig.where() == {"a": 12, "b": 3}


def test_select_on_the_same_wheel_moves_only_that_wheel(rig):
    rig.bank.check()
    rig.bank.select(400)
    moves, commands = rig.moves(), rig.move_commands()

    assert rig.bank.select(420) == rig.where() == {"a": 2, "b": 12}
    assert rig.moves() == {"a": moves["a"] + 1, "b": moves["b"]}
    assert rig.move_commands() == {"a": commands["a"] + ["pos=2"], "b": commands["b"]}
    assert rig.emulator("a").moves[-1][:2] == (1, 2)

    rig.bank.select(600)  # over to wheel b: a goes to its open slot
    moves = rig.moves()
    assert rig.bank.select(620) == rig.where() == {"a": 12, "b": 4}
    assert rig.moves() == {"a": moves["a"], "b": moves["b"] + 1}


def test_selecting_the_same_band_again_moves_nothing(rig):
    rig.bank.check()
    rig.bank.select(480)
    moves = rig.moves()
    assert rig.bank.select(480) == {"a": 5, "b": 12}
    assert rig.moves() == moves


def test_switching_wheels_takes_the_old_filter_out_first(rig):
    """Never two filters in the path: the wheel going to its open slot moves first."""
    rig.bank.check()
    rig.bank.select(400)  # a: 1, b: 12
    order = []
    for name, wheel in rig.wheels.items():
        original = wheel.move_to

        def recording(slot, name=name, original=original):
            order.append((name, slot))
            return original(slot)

        wheel.move_to = recording
    assert rig.bank.select(560) == {"a": 12, "b": 1}
    assert order == [("a", 12), ("b", 1)]
    order.clear()
    assert rig.bank.select(420) == {"a": 2, "b": 12}
    assert order == [("b", 12), ("a", 2)]


def test_front_panel_press_on_the_filter_wheel_is_corrected_on_next_select(rig):
    rig.bank.check()
    rig.bank.select(400)
    rig.press("a")  # a: 1 -> 2, i.e. band 420 in the path while the bank last saw 400
    assert rig.where() == {"a": 2, "b": 12}

    read_back = rig.bank.select(400)
    assert read_back == rig.where() == {"a": 1, "b": 12}
    assert rig.bank.band_in_path() == 400
    assert rig.emulator("a").moves[-1][:2] == (2, 1)


def test_front_panel_press_on_the_open_wheel_is_corrected_on_next_select(rig):
    """The wheel resting on its open slot is knocked onto a filter: two filters in the path."""
    rig.bank.check()
    rig.bank.select(400)
    rig.press("b", forward=True)  # b: 12 -> 1 (band 560's filter)
    assert rig.bank.profile.band_at(rig.where()) is None

    read_back = rig.bank.select(420)
    assert read_back == rig.where() == {"a": 2, "b": 12}
    assert rig.bank.band_in_path() == 420


def test_front_panel_press_during_a_move_is_detected(rig):
    rig.bank.check()
    with rig.ports["a"].lock:
        rig.emulator("a").press_button_during_next_move()
    with pytest.raises(DeviceError) as caught:
        rig.bank.select(400)
    assert caught.value.port == rig.ports["a"].path
    assert rig.ports["a"].path in str(caught.value)
    assert "\n" not in str(caught.value)
    # The next select reads where the wheel really is and puts it right.
    assert rig.bank.select(400) == rig.where() == {"a": 1, "b": 12}


def test_a_wheel_that_does_not_stay_put_is_refused_by_the_read_back(rig):
    """A wheel that is not where the bank put it after all the moves: DeviceError naming it."""
    rig.bank.check()
    wheel_b = rig.wheels["b"]
    original = wheel_b.move_to

    def move_then_knocked(slot):
        reached = original(slot)
        rig.press("b")  # knocked right after its move was confirmed
        return reached

    wheel_b.move_to = move_then_knocked
    with pytest.raises(DeviceError) as caught:
        rig.bank.select(600)
    message = str(caught.value)
    assert caught.value.port == rig.ports["b"].path
    assert "'b'" in message and "600 nm" in message and "\n" not in message


def test_unknown_band_moves_nothing(rig):
    rig.bank.check()
    with pytest.raises((KeyError, ValueError)):
        rig.bank.select(410)
    assert rig.moves() == {"a": 0, "b": 0}


def test_wheels_must_match_the_profile(profile):
    with contextlib.ExitStack() as stack:
        rig = Rig(profile, stack, {"a": 12, "b": 12})
        with pytest.raises(ValueError, match="wheels"):
            FilterBank(profile, {"a": rig.wheels["a"]})
        with pytest.raises(ValueError, match="wheels"):
            FilterBank(profile, {**rig.wheels, "c": rig.wheels["a"]})


def test_mixed_models(tmp_path):
    path = tmp_path / "profile.toml"
    # Wheel b is an FW102C: slots 1..6, open slot 6, so only bands 560..640 (slots 1..5) fit on it.
    text = profile_text(model_b="FW102C", open_b=6)
    text = "\n".join(line for line in text.splitlines() if not line.startswith(("660 ", "680 ", "700 "))) + "\n"
    path.write_text(text)
    profile = load_profile(path)
    with contextlib.ExitStack() as stack:
        rig = Rig(profile, stack, {"a": 12, "b": 6})
        rig.bank.check()
        assert rig.bank.select(640) == rig.where() == {"a": 12, "b": 5}
        assert rig.bank.select(400) == rig.where() == {"a": 1, "b": 6}


def test_pcount_mismatch_is_refused_by_the_bank_before_anything_moves(profile):
    """Wheel b is an FW102C (pcount? 6) where the profile says FW212C; connected without model=,
    so the driver accepts it and the bank's check must refuse it."""
    with contextlib.ExitStack() as stack:
        rig = Rig(profile, stack, {"a": 12, "b": 6}, models={"b": "FW102C"}, connect_model=False)
        with pytest.raises(WheelCountMismatch) as caught:
            rig.bank.check()
        message = str(caught.value)
        assert "'b'" in message and rig.ports["b"].path in message
        assert "6" in message and "12" in message and "FW212C" in message and "pcount?" in message
        assert "\n" not in message
        assert isinstance(caught.value, ValueError)
        assert rig.moves() == {"a": 0, "b": 0}
        assert rig.move_commands() == {"a": [], "b": []}


def test_pcount_mismatch_is_refused_by_the_driver_at_connect(tmp_path):
    emulator = FilterWheelEmulator(model="FW102C", move_time_scale=0)
    with EmulatedPort(emulator) as port:
        wheel = FilterWheel(port.path, model="FW212C", timeout_s=0.5)
        with pytest.raises(ProtocolError) as caught:
            wheel.connect()
        assert caught.value.port == port.path
        assert port.path in str(caught.value) and "pcount?" in str(caught.value)
        assert not wheel.is_connected
        assert emulator.moves == []


@pytest.mark.parametrize("identity", ["THORLABS SC10 VERSION 1.07", "ACME Widget 3000", " "], ids=["sc10", "other", "blank"])
def test_wrong_identity_is_refused_at_connect(identity):
    emulator = FilterWheelEmulator(model="FW212C", move_time_scale=0, identity=identity)
    with EmulatedPort(emulator) as port:
        wheel = FilterWheel(port.path, model="FW212C", timeout_s=0.5)
        with pytest.raises(ProtocolError) as caught:
            with wheel:
                pass
        assert caught.value.port == port.path
        assert caught.value.command == "*idn?"
        assert port.path in str(caught.value) and "\n" not in str(caught.value)
        assert not wheel.is_connected
        assert emulator.moves == []
        assert not any(c.startswith(("pos=", "pcount=")) for c in emulator.commands)
