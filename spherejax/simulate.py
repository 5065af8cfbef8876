"""A physical integrating-sphere multispectral imager, and the paper's experiment on it.

Nobody here has the instrument of Zou et al. (2019), so the simulator renders the camera frames
such an instrument would record, from first principles, with the phenomena the paper corrects and
the ones it cannot correct exactly:

- the multi-bounce sphere of Eqs. 1-9: the holder's area-weighted mean reflectance sets
  k(λ) = α_ww + α_wsp α_spw ρ̄(λ) (Eq. 9), and the irradiance on the holder is the sum of all wall
  bounces, ρ_w Φ_0 Σ_n (k ρ_w)^(n-1) = ρ_w Φ_0 / (1 - k ρ_w) (Eq. 6-7); port fractions follow
  from the sphere's geometry (Section 5);
- spatial non-uniformity β(x): cos⁴-like vignetting times a per-filter linear gradient;
- a xenon lamp: a 6000 K near-continuum with the xenon line cluster at 450-500 nm, slow drift,
  and frame-to-frame fluctuation of each band image;
- what Stage I cannot remove: veiling glare (a long-tailed point spread carrying a few percent of
  the flux), non-Lambertian samples (the first wall bounce, which reaches the holder from a narrow
  range of directions, couples into the camera differently from the diffuse later bounces, by a
  factor that depends on the material), and optional fluorescence near 440 nm in backgrounds;
- the camera: 16 Gaussian filters (FWHM 10 nm) integrated on a 2 nm grid with a CCD quantum
  efficiency, shot noise, read noise, dark current, frame averaging, a 14-bit ADC and saturation.

All reflectances are measured spectra shipped with colour-science (`spherejax.spectra`).
Rendering is JAX (jitted; one compilation per image shape); layout and bookkeeping are numpy.

The simulator is a module per job; every public name is importable from here:

    simulated_instrument   `InstrumentModel`, the physics of sphere, lamp, filters and camera;
                           FINE_WAVELENGTHS_NM, the 2 nm grid its spectra are on
    simulated_layout       `ExperimentDesign`, `Material`, `Scene`, `experiment_layout`: what lies
                           on the holder in each capture, before rendering
    simulated_rendering    the JAX renderer: rates (16, H, W) e-/s, frames (H, W, 16) uint16
    simulate (this)        the experiment rendered (`simulate_experiment`) and as a session

`simulate_experiment` builds the paper's experiment (Section 4-5): grey patches on uniform
backgrounds at several positions (training), coloured patches on patterned backgrounds (test),
a 144-target chart of known reflectance (Wiener training), the reference white patch beside the
holder in every frame, 0.5 cm patches averaged over their centres. `session_contents` gives it as a
session's contents, which `spherejax.io.write_simulated_session` writes to disk.
"""

from __future__ import annotations

import dataclasses
import datetime

import numpy as np

from .grid import BAND_CENTRES_NM
from .simulated_instrument import FINE_WAVELENGTHS_NM, InstrumentModel
from .simulated_layout import (
    ExperimentDesign,
    ExperimentLayout,
    Material,
    Scene,
    experiment_layout,
    fixed_materials,
    sensor_map,
)
from .simulated_rendering import _Renderer


@dataclasses.dataclass
class SimulatedFrame:
    """One capture: what the session manifest records and the pixels."""

    id: str
    role: str
    pixels: np.ndarray  # (H, W, 16) uint16
    start_s: float
    set: str | None = None
    background: str | None = None
    regions: list[dict] = dataclasses.field(default_factory=list)
    metadata: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class SimulatedExperiment:
    """Everything a simulated session holds (`session_contents`): frames plus the layout and the
    parameters."""

    instrument: InstrumentModel
    design: ExperimentDesign
    seed: int
    image_shape: tuple[int, int]
    holder: tuple[int, int, int, int]
    white_patch: tuple[int, int, int, int]
    exposure_s: np.ndarray
    frames: list[SimulatedFrame]
    materials: dict[str, Material]
    band_transforms: np.ndarray  # (16, 2, 3): where each band's image lies (`band_geometry`)


def simulate_experiment(seed: int = 0, instrument: InstrumentModel | None = None, design: ExperimentDesign | None = None) -> SimulatedExperiment:
    """Render the paper's experiment (`experiment_layout`): dark, white standard, training, test
    and target captures.

    Deterministic for a given seed, instrument and design.
    """
    # The defaults are made here, through this module's names, not by `experiment_layout`:
    # tests make a small experiment the default by replacing `simulate.ExperimentDesign`.
    instrument = instrument or InstrumentModel()
    design = design or ExperimentDesign()
    layout = experiment_layout(seed, instrument, design)
    instrument, design = layout.instrument, layout.design
    renderer = _Renderer(instrument, layout.image_shape, layout.holder_shape, seed)

    # White standard, then exposures, then the dark frame at those exposures.
    white_rates = renderer.rates(*layout.sensor_map(layout.white))
    exposure = renderer.calibrate_exposures(white_rates)
    frames: list[SimulatedFrame] = []
    dark_pixels, t = renderer.capture(None, instrument.frames_averaged_dark)
    frames.append(SimulatedFrame("dark", "dark", dark_pixels, t))
    white_pixels, t = renderer.capture(white_rates, instrument.frames_averaged_white)
    frames.append(SimulatedFrame("white", "white", white_pixels, t))
    for scene in layout.scenes.values():
        pixels, start = renderer.capture(renderer.rates(*layout.sensor_map(scene)), instrument.frames_averaged_sample)
        frames.append(SimulatedFrame(scene.name, scene.role, pixels, start, scene.set, scene.background, list(scene.regions)))

    return SimulatedExperiment(
        instrument=instrument, design=design, seed=seed, image_shape=layout.image_shape,
        holder=(0, layout.holder_shape[0], 0, layout.holder_shape[1]), white_patch=layout.white_patch,
        exposure_s=exposure, frames=frames, materials=layout.materials, band_transforms=renderer.band_transforms,
    )


def session_contents(experiment: SimulatedExperiment) -> dict:
    """What a session folder of `experiment` holds, as the keyword arguments of
    `spherejax.io.write_session` (instrument id, bands, shape, saturation, white patch, holder,
    frames (manifest entry, (H, W, B) uint16 pixels), metadata). Writing them is the files
    layer's (`spherejax.io.write_simulated_session`, `spherejax simulate`): this module computes.
    """
    start = datetime.datetime(2026, 1, 1, 9, 0, 0, tzinfo=datetime.timezone.utc)
    frames = []
    for frame in experiment.frames:
        info = {
            "id": frame.id,
            "role": frame.role,
            "exposure_s": [float(e) for e in experiment.exposure_s],
            "timestamp": (start + datetime.timedelta(seconds=frame.start_s)).isoformat(),
            "metadata": dict(frame.metadata, frames_averaged={
                "dark": experiment.instrument.frames_averaged_dark,
                "white": experiment.instrument.frames_averaged_white,
            }.get(frame.role, experiment.instrument.frames_averaged_sample)),
        }
        if frame.role == "sample":
            info["set"] = frame.set
            info["background"] = frame.background
        if frame.regions:
            info["regions"] = frame.regions
        frames.append((info, frame.pixels))
    metadata = {
        # The white board's certificate: what a lab would copy into its session (the Markov
        # baseline needs R_W).
        "white_standard_reflectance": experiment.materials["white standard"].at_31().tolist(),
        "simulator": {
            "seed": experiment.seed,
            "instrument": dataclasses.asdict(experiment.instrument),
            "design": dataclasses.asdict(experiment.design),
            "materials": {
                m.name: {"source": m.source, "coupling": m.coupling, "fluorescence": m.fluorescence}
                for m in experiment.materials.values()
            },
        }
    }
    if experiment.instrument.noise:
        # The camera's true noise, for calibrate's noise model (`spherejax.uncertainty`); with
        # the model's noise switched off the frames have none, and no camera record claims any.
        gain = float(experiment.instrument.gain_e_per_dn)
        metadata["camera"] = {"gain_e_per_count": gain, "read_noise_counts": float(experiment.instrument.read_noise_e) / gain}
    return dict(
        instrument_id="sim-sphere-1",
        band_centres_nm=[int(b) for b in BAND_CENTRES_NM],
        image_shape=list(experiment.image_shape),
        saturation=experiment.instrument.saturation_dn,
        white_patch=list(experiment.white_patch),
        holder=list(experiment.holder),
        frames=frames,
        metadata=metadata,
        band_transforms=experiment.band_transforms,
    )


__all__ = [
    "FINE_WAVELENGTHS_NM",
    "InstrumentModel",
    "ExperimentDesign",
    "Material",
    "SimulatedFrame",
    "SimulatedExperiment",
    "Scene",
    "ExperimentLayout",
    "experiment_layout",
    "fixed_materials",
    "sensor_map",
    "simulate_experiment",
    "session_contents",
]
