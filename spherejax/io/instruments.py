"""Simulated-instrument files (format "spherejax-instrument", version 1): what `spherejax twin`
fitted to a session, and what `spherejax simulate --instrument` renders.

    {
      "format": "spherejax-instrument", "format_version": 1,
      "instrument": {"wall_reflectance_400nm": 0.95, ..., "noise": true},
      "fitted": ["full_well_e", ...],          # which of them the twin fitted (optional)
      "report": {...},                          # how well each statistic fits (optional, free)
      "session": "path/of/the/session",         # optional
      "software_version": "...", "created": "2026-11-28T16:00:00+00:00"   # optional
    }

"instrument" holds fields of `spherejax.simulate.InstrumentModel` by name, each checked (a
finite number in the range its physics allows, an integer where the model counts); a field
left out takes the model's default, so a lab may write the few it knows by hand. Anything else
is refused in one line naming the file, the field, the value and what was expected.
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Annotated

import pydantic

from .. import atomic_files, jsontext
from .documents import (
    Document, Expect, JsonObject, NonEmptyStr, Timestamp, _readable_json, _utc_now, check_document, integer, located, number,
    refuse,
)
from .errors import SpherejaxFileError

INSTRUMENT_FORMAT = "spherejax-instrument"
INSTRUMENT_FORMAT_VERSION = 1


class InstrumentFileError(SpherejaxFileError):
    """An instrument file is missing, not JSON, of another format or with a field out of range."""


def _fraction(text: str, *, open_low: bool = False, open_high: bool = True):
    bounds = {"gt" if open_low else "ge": 0.0, "lt" if open_high else "le": 1.0}
    return Annotated[number(**bounds), Expect(text)]


def _positive(text: str):
    return Annotated[number(gt=0.0), Expect(f"{text}, a number > 0")]


_Reflectance = _fraction("a reflectance, a number > 0 and < 1", open_low=True)


class _Instrument(Document):
    """`InstrumentModel`'s fields (simulated_instrument.py says what each is and why its default)."""

    sphere_diameter_m: _positive("metres") = None
    entrance_port_diameter_m: _positive("metres") = None
    detector_port_diameter_m: _positive("metres") = None
    holder_height_m: _positive("metres") = None
    holder_width_m: _positive("metres") = None
    wall_reflectance_400nm: _Reflectance = None
    wall_reflectance_700nm: _Reflectance = None
    lamp_colour_temperature_k: Annotated[number(ge=1000.0, le=20000.0), Expect("kelvin, 1000..20000")] = None
    lamp_line_strength: Annotated[number(ge=0.0, le=10.0), Expect("a relative strength, 0..10")] = None
    lamp_drift_per_hour: Annotated[number(gt=-1.0, lt=1.0), Expect("a fraction an hour, > -1 and < 1")] = None
    lamp_fluctuation: _fraction("a fraction, 0 <= value < 1") = None
    stray_light_fraction: _fraction("a fraction, 0 <= value < 1") = None
    stray_light_core_px: _positive("pixels") = None
    non_lambertian_spread: _fraction("a fraction, 0 <= value < 1") = None
    vignetting: _fraction("the corners' loss, 0 <= value < 1") = None
    filter_gradient: _fraction("a fraction, 0 <= value < 1") = None
    filter_fwhm_nm: Annotated[number(gt=0.0, le=100.0), Expect("nanometres, > 0 and <= 100")] = None
    filter_peak_transmission: _fraction("a transmission, > 0 and <= 1", open_low=True, open_high=False) = None
    qe_peak: _fraction("a quantum efficiency, > 0 and <= 1", open_low=True, open_high=False) = None
    qe_peak_nm: Annotated[number(ge=300.0, le=1100.0), Expect("nanometres, 300..1100")] = None
    qe_width_nm: _positive("nanometres") = None
    full_well_e: _positive("electrons") = None
    read_noise_e: Annotated[number(ge=0.0), Expect("electrons, a number >= 0")] = None
    dark_current_e_per_s: Annotated[number(ge=0.0), Expect("electrons a second, a number >= 0")] = None
    bias_dn: Annotated[number(ge=0.0), Expect("counts, a number >= 0")] = None
    adc_bits: integer(8, 16) = None
    exposure_fill: _fraction("a fraction of full scale, > 0 and <= 1", open_low=True, open_high=False) = None
    peak_rate_e_per_s: _positive("electrons a second") = None
    white_standard_reflectance: _Reflectance = None
    white_patch_reflectance: _Reflectance = None
    mount_reflectance: _Reflectance = None
    fluorescence_peak_nm: Annotated[number(ge=300.0, le=800.0), Expect("nanometres, 300..800")] = None
    fluorescence_width_nm: _positive("nanometres") = None
    fluorescence_strength: _fraction("a strength, 0..1", open_high=False) = None
    frames_averaged_dark: integer(1, 10000) = None
    frames_averaged_white: integer(1, 10000) = None
    frames_averaged_sample: integer(1, 10000) = None
    band_interval_s: _positive("seconds") = None
    filter_thickness_mm: _positive("millimetres") = None
    filter_thickness_tolerance_mm: Annotated[number(ge=0.0), Expect("millimetres, a number >= 0")] = None
    filter_refractive_index: Annotated[number(gt=1.0, le=3.0), Expect("a refractive index, > 1 and <= 3")] = None
    filter_tilt_deg: Annotated[number(ge=0.0, le=10.0), Expect("degrees, 0..10")] = None
    filter_wedge_arcsec: Annotated[number(ge=0.0, le=3600.0), Expect("arc seconds, 0..3600")] = None
    filter_to_sensor_mm: _positive("millimetres") = None
    image_distance_mm: _positive("millimetres") = None
    magnification: Annotated[number(gt=0.0, le=10.0), Expect("a magnification, > 0 and <= 10")] = None
    lens_lateral_colour_per_nm: Annotated[number(gt=-1.0, lt=1.0), Expect("a relative change per nm, > -1 and < 1")] = None
    band_misregistration_px: Annotated[number(ge=0.0, le=50.0), Expect("pixels, 0..50")] = None
    sample_layer_scattering_power: Annotated[number(ge=0.0, le=1000.0), Expect("a scattering power S X, 0 (opaque) or > 0, at most 1000")] = None
    noise: Annotated[bool, Expect("true or false")] = None

    @pydantic.model_validator(mode="after")
    def _ports_fit_the_sphere(self):
        from ..simulated_instrument import InstrumentModel

        model = InstrumentModel(**{k: v for k, v in self.model_dump().items() if v is not None})
        if not 0.0 < model.port_fractions()[0] < 1.0:
            raise refuse("has ports and a holder that cover the sphere", "ports and a holder smaller than the sphere's surface")
        return self


class _InstrumentFile(Document):
    format: Annotated[str, Expect(f'"{INSTRUMENT_FORMAT}"')]
    format_version: integer(1)
    instrument: Annotated[_Instrument, Expect("an object of InstrumentModel's fields")]
    fitted: Annotated[list[NonEmptyStr], Expect("a list of field names")] = []
    report: JsonObject = pydantic.Field(default_factory=dict)
    session: NonEmptyStr | None = None
    software_version: NonEmptyStr | None = None
    created: Timestamp | None = None


def instrument_document(instrument, *, fitted=(), report=None, session=None) -> dict:
    """The JSON document (a dict) of an `InstrumentModel`, with what the twin fitted."""
    from .. import __version__

    return {
        "format": INSTRUMENT_FORMAT, "format_version": INSTRUMENT_FORMAT_VERSION,
        # A field left at None (the default's own rule, e.g. band_misregistration_px) is left out.
        "instrument": {k: v for k, v in dataclasses.asdict(instrument).items() if v is not None},
        "fitted": list(fitted), "report": report or {},
        **({"session": str(session)} if session is not None else {}),
        "software_version": __version__, "created": _utc_now(),
    }


def save_instrument(path, instrument, *, fitted=(), report=None, session=None) -> None:
    """Write an instrument file at `path`, new (never over a file already there: refused),
    whole or not at all."""
    path = pathlib.Path(path)
    text = _readable_json(instrument_document(instrument, fitted=fitted, report=report, session=session)) + "\n"
    try:
        created = atomic_files.create_whole(path, text.encode("utf-8"))
    except OSError as error:
        raise InstrumentFileError(path, f"cannot be written: {error.strerror or error}") from None
    if not created:
        raise InstrumentFileError(path, "exists", "a new file name: spherejax does not replace a file")


def load_instrument(path):
    """The `InstrumentModel` an instrument file describes (fields it leaves out: the defaults)."""
    from ..simulated_instrument import InstrumentModel

    path = pathlib.Path(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise InstrumentFileError(path, f"cannot be read: {error.strerror or error}", "an instrument file (spherejax twin -o)") from None
    try:
        doc = jsontext.loads(data, allow_nan=False)
    except jsontext.JSONTextError as error:
        raise InstrumentFileError(path, f"is not JSON: {error}", "an instrument file (spherejax twin -o)") from None
    if not isinstance(doc, dict) or doc.get("format") != INSTRUMENT_FORMAT:
        found = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise InstrumentFileError(path, f"format is {found!r}", f'"{INSTRUMENT_FORMAT}" (spherejax twin -o)')
    if doc.get("format_version") != INSTRUMENT_FORMAT_VERSION:
        raise InstrumentFileError(path, f"format_version is {doc.get('format_version')!r}",
                                  f"{INSTRUMENT_FORMAT_VERSION}, the version this spherejax reads")
    checked = check_document(_InstrumentFile, doc, error=located(InstrumentFileError, path), unknown="key")
    return InstrumentModel(**{k: v for k, v in checked.instrument.model_dump().items() if v is not None})


__all__ = ["INSTRUMENT_FORMAT", "INSTRUMENT_FORMAT_VERSION", "InstrumentFileError", "instrument_document",
           "load_instrument", "save_instrument"]
