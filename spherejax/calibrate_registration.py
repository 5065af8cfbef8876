"""Bands in register for `calibrate`: which frame of a session registers them, the check that it
can, the maps it gives (`band_registration.register_bands`) on the session's base calibration, and
how the report records and shows them.

The frame: the session's registration target (role "registration", `Session.registration_frame`:
a target of the lab's choice, docs/instrument.md) if it holds one, else its first target capture
(the chart: edges in every band across the frame).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .band_geometry import largest_displacement
from .band_registration import BandRegistration, check_structure, flat_fielded, register_bands
from .calibration import Calibration
from .number_text import json_ready


def registration_frame(session):
    """The frame the bands are registered from: the session's registration target (role
    "registration") if it holds one, else its first target capture (a chart: edges in every band
    across the frame), else None."""
    targets = session.frames_with(role="target")
    return session.registration_frame() or (targets[0] if targets else None)


def _frame_to_register(session):
    """`registration_frame`, or ValueError (one line naming the manifest) where there is none."""
    frame = registration_frame(session)
    if frame is None:
        raise ValueError(f"{session.manifest_path}: has no registration target or target capture to register the bands "
                         "by (expected a frame of role \"registration\" or \"target\"; or calibrate with --no-registration)")
    return frame


def _refusal(session, frame, error: ValueError) -> ValueError:
    """The one-line refusal of a frame that cannot register the bands (`band_registration`'s reason)."""
    return ValueError(f"{session.manifest_path}: frame {frame.id!r} cannot register the bands: {error} "
                      "(or calibrate with --no-registration)")


def check_registration_frame(session) -> None:
    """Raise ValueError, one line naming the manifest and the frame, unless the session holds a
    frame to register the bands by (`registration_frame`) with edges in every band
    (`band_registration.check_structure`): before any other work (reads that frame, the dark and
    the white)."""
    frame = _frame_to_register(session)
    try:
        check_structure(flat_fielded(session.read(frame), session.dark(), session.white()))
    except ValueError as error:
        raise _refusal(session, frame, error) from None


def register_session_bands(session, base: Calibration) -> tuple[Calibration, dict]:
    """(base with the session's band maps, the report's summary of them). Raises ValueError, one
    line naming the manifest and the frame, when the session has no frame to register from or the
    frame has too little structure (`band_registration.register_bands`)."""
    frame = _frame_to_register(session)
    try:
        registration = register_bands(session.read(frame), np.asarray(base.dark), np.asarray(base.white))
    except ValueError as error:
        raise _refusal(session, frame, error) from None
    return dataclasses.replace(base, band_transforms=registration.transforms), registration_summary(
        session, frame.id, registration)


def registration_summary(session, frame_id: str, registration: BandRegistration) -> dict:
    """The report's record of a registration: the frame, the reference band (index and nm), each
    band's map (manifest convention), the tiles' residual about it (px), the tiles used, and the
    largest displacement in the frame (px)."""
    return {
        "frame": frame_id,
        "reference_band": int(registration.reference_band),
        "reference_band_nm": int(session.band_centres_nm[registration.reference_band]),
        "band_transforms": json_ready(registration.transforms),
        "residual_px": json_ready(np.round(registration.residual_px, 4)),
        "tiles": [int(n) for n in registration.tiles],
        "largest_displacement_px": round(largest_displacement(registration.transforms, session.image_shape), 4),
    }


def registration_line(report) -> str:
    """One line for the log (`calibrate.CalibrationReport`'s band_registration): how far the bands
    were apart, or that they were taken as in register."""
    summary = report.band_registration
    if summary is None:
        return "bands: not registered (taken as in register)"
    residual = np.asarray(summary["residual_px"], float)
    return (f"bands: registered from frame {summary['frame']!r} to {summary['reference_band_nm']} nm; largest "
            f"displacement {summary['largest_displacement_px']:.2f} px, tile residual at most {np.nanmax(residual):.2f} px")


__all__ = ["registration_frame", "check_registration_frame", "register_session_bands", "registration_summary",
           "registration_line"]
