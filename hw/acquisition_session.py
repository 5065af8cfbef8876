"""The finished acquisition assembled into a spherejax session (`spherejax.io.write_session`).

`_write_session` reads back every band image the journal holds, unchanged, (H, W, 1) uint16
each, and writes one session frame (H, W, B) per capture, B the profile's bands in order, with
the exposures (s) chosen for them. Each frame's metadata holds its bands' metadata ("bands") and
its frames averaged ("frames_averaged"); the session's metadata holds the acquisition's record
(profile, warm-up, camera) and, when known, the camera's noise (`_camera_noise`, the "camera"
record calibrate's noise model reads). The white patch and holder come from the profile's
[layout] or the camera (`_layout`), which `acquire.acquire` checks before anything moves.
"""

from __future__ import annotations

import pathlib

import numpy as np

from .acquisition_devices import Instrument
from .acquisition_journal import Journal
from .acquisition_protocol import Capture, _full_scale
from .camera import Camera
from .errors import AcquisitionError
from .profile import Profile


def _layout(profile: Profile, camera: Camera) -> tuple[list[int], list[int]]:
    """(white patch, holder), each [r0, r1, c0, c1] in image pixels: the profile's [layout], else
    the camera's own; AcquisitionError when neither gives them."""
    white_patch = profile.layout.white_patch or getattr(camera, "white_patch", None)
    holder = profile.layout.holder or getattr(camera, "holder", None)
    if white_patch is None or holder is None:
        raise AcquisitionError(f"{profile.path}: [layout] white_patch and holder are needed for this camera")
    return [int(v) for v in white_patch], [int(v) for v in holder]


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
    """The session's "camera" record (`acquire`'s module docstring): gain and read noise from the camera
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
