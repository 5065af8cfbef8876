"""Monte Carlo of the per-pixel path (JCGM 101:2008, GUM Supplement 1), to check the
first-order uncertainties of `spherejax.uncertainty` against.

A `NoiseScene` holds the true mean signals of one capture: the white standard, a sample frame
of colour-chart patches and a white patch, and the dark level. Each trial draws the frames a
camera would give (`draw_frame`: Poisson electrons, Gaussian read noise, averaging, rounding to
counts, clipping at full scale), builds the calibration from that trial's dark and white frames,
and runs `spherejax.correct`. The spread of the trials is what the propagated uncertainties must
match; the path's value on the noise-free frames is the "true" value whose coverage the k = 2
intervals must give.

The scene's patches (`noise_scene`) are the ColorChecker's 24 (N. Ohta's measurements, shipped
with colour-science), so that chromatic, near-neutral and dark colours are all there, plus the
cases where first order is least exact: very dark pixels (the black patch at a fifth of its
reflectance), pixels near full scale (a white at 95 % of the ADC's range) and neutrals (ΔE00
against a grey). The camera is the simulated instrument's (`simulate.InstrumentModel`:
gain, read noise, frames averaged), its 16 bands seen through `simulated_targets.target_system`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import spectra
from .grid import N_BANDS
from .pipeline import Calibration, correct
from .polynomial import PAPER_TABLE_2, stage2
from .simulate import InstrumentModel
from .simulated_targets import target_system
from .uncertainty import NoiseModel
from .estimation import fit_wiener

#: Pixel kinds of `NoiseScene.kind`.
KIND_PATCH, KIND_CHART, KIND_DARK, KIND_NEAR_FULL_SCALE, KIND_NEUTRAL = -1, 0, 1, 2, 3
KIND_NAMES = {KIND_CHART: "chart", KIND_DARK: "dark", KIND_NEAR_FULL_SCALE: "near full scale", KIND_NEUTRAL: "neutral"}


def draw_frame(rng: np.random.Generator, counts, bias: float, gain, read_noise, frames: int, saturation: int) -> np.ndarray:
    """One averaged camera frame, uint16: the mean of `frames` exposures of mean `counts`
    (dark-subtracted, counts) above the dark level `bias`.

    The sum of `frames` Poisson exposures is Poisson, so the mean is Poisson(counts gain frames)
    / (gain frames) counts; read noise adds N(0, read_noise² / frames); then the ADC rounds and
    clips at `saturation`.
    """
    counts = np.asarray(counts, np.float64)
    electrons = rng.poisson(np.maximum(counts, 0.0) * gain * frames) / (gain * frames)
    read = rng.standard_normal(counts.shape) * (read_noise / np.sqrt(frames))
    return np.clip(np.rint(bias + electrons + read), 0, saturation).astype(np.uint16)


@dataclasses.dataclass(frozen=True)
class NoiseScene:
    """True mean signals of one capture, for Monte Carlo.

    Fields:
      white_counts: (H, W, B) dark-subtracted mean counts of the white-standard frame.
      sample_counts: (H, W, B) the same of the sample frame (its white patch included).
      bias: the dark frame's level, counts.
      patch: (H, W) bool, the white patch.
      kind: (H, W) int, `KIND_*` of each pixel.
      coeffs: (B, 4) Stage II coefficients; wiener (31, B), wiener_offset (31,): the estimator.
      gain: electrons per count; read_noise: counts rms; frames: {"dark", "white", "sample"}.
      saturation: full scale in counts.
    """

    white_counts: np.ndarray
    sample_counts: np.ndarray
    bias: float
    patch: np.ndarray
    kind: np.ndarray
    coeffs: np.ndarray
    wiener: np.ndarray
    wiener_offset: np.ndarray
    gain: float
    read_noise: float
    frames: dict
    saturation: int

    def noise_model(self, **systematic) -> NoiseModel:
        """The scene camera's `NoiseModel` (systematic terms as keyword arguments)."""
        return NoiseModel(
            gain=self.gain, read_noise=self.read_noise, dark_frames=self.frames["dark"],
            white_frames=self.frames["white"], sample_frames=self.frames["sample"], **systematic,
        )

    def calibration(self, dark: np.ndarray, white: np.ndarray) -> Calibration:
        """The calibration of one trial's dark and white frames."""
        return Calibration(
            dark=dark.astype(np.float32), white=white.astype(np.float32), patch=self.patch,
            coeffs=self.coeffs.astype(np.float32), wiener=self.wiener.astype(np.float32),
            wiener_offset=self.wiener_offset.astype(np.float32), saturation=float(self.saturation),
        )

    def noise_free(self):
        """(raw, calibration) of the noise-free frames (float32 counts): the true value."""
        dark = np.full(self.white_counts.shape, self.bias, np.float32)
        return (self.sample_counts + self.bias).astype(np.float32), self.calibration(dark, (self.white_counts + self.bias).astype(np.float32))

    def draw(self, rng: np.random.Generator):
        """(raw uint16, calibration) of one trial."""
        shape = self.white_counts.shape
        frame = lambda counts, n: draw_frame(rng, counts, self.bias, self.gain, self.read_noise, n, self.saturation)  # noqa: E731
        dark = frame(np.zeros(shape), self.frames["dark"])
        white = frame(self.white_counts, self.frames["white"])
        raw = frame(self.sample_counts, self.frames["sample"])
        return raw, self.calibration(dark, white)


def noise_scene(block: int = 6, *, instrument: InstrumentModel | None = None, lamp_change: float = 1.18) -> NoiseScene:
    """The test scene: ColorChecker patches and the hard cases, `block` x `block` pixels each.

    Layout, 6 x 5 blocks: the white patch (top left), the 24 ColorChecker patches, a black at a
    fifth of its reflectance and a dark blue at a third (dark), a white at 95 % of full scale in
    the sample frame (near full scale) and two flat greys (neutral). The sample frame's lamp is
    `lamp_change` times the white frame's (p = 1 / lamp_change corrects it); vignetting falls by
    15 % to the corners. Stage II uses the paper's Table 2; the estimator is the training-based
    one fitted to every shipped spectrum's noise-free Stage II response, so that Lab is right.
    """
    instrument = instrument or InstrumentModel()
    system = target_system(instrument, offset_fraction=0.0)
    chart = spectra.reflectance_sets()["ColorChecker: ColorChecker N Ohta"]
    flat = lambda value: np.full(chart.shape[1], value)  # noqa: E731
    white_standard = instrument.white_standard_reflectance
    full_scale = instrument.saturation_dn
    white_level = instrument.exposure_fill * full_scale  # the protocol's 80 % of full scale
    materials = [flat(white_standard)] + list(chart) + [
        0.2 * chart[23], 0.33 * chart[12], flat(0.95 * full_scale / (white_level * lamp_change) * white_standard),
        flat(0.45), flat(0.2),
    ]
    kinds = [KIND_PATCH] + [KIND_NEUTRAL if 18 <= i <= 23 else KIND_CHART for i in range(24)] + [
        KIND_DARK, KIND_DARK, KIND_NEAR_FULL_SCALE, KIND_NEUTRAL, KIND_NEUTRAL,
    ]
    rows, cols = 5, 6
    height, width = rows * block, cols * block
    material = np.arange(rows * cols).reshape(rows, cols).repeat(block, 0).repeat(block, 1)
    y, x = np.mgrid[0:height, 0:width]
    r = np.hypot((y - (height - 1) / 2) / (height / 2), (x - (width - 1) / 2) / (width / 2)) / np.sqrt(2)
    beta = 1.0 - 0.15 * r**2
    # Flat-fielded response of each material: M r, normalised so the white standard gives 1.
    response = np.stack(materials) @ system.sensitivity.T  # (30, B)
    white_counts = white_level * beta[..., None] * np.ones(N_BANDS)
    sample_counts = white_counts * lamp_change * response[material]

    reflectances = spectra.all_reflectances()
    p = np.full_like(reflectances[:, :N_BANDS], 1.0 / lamp_change)
    coeffs = np.asarray(PAPER_TABLE_2, np.float64)
    v_tilde = np.asarray(stage2(lamp_change * reflectances @ system.sensitivity.T, p, coeffs))
    estimator = fit_wiener(v_tilde, reflectances, method="training")
    return NoiseScene(
        white_counts=white_counts, sample_counts=sample_counts, bias=instrument.bias_dn,
        patch=material == 0, kind=np.asarray(kinds)[material], coeffs=coeffs,
        wiener=np.asarray(estimator.matrix, np.float64), wiener_offset=np.asarray(estimator.offset, np.float64),
        gain=instrument.gain_e_per_dn, read_noise=instrument.read_noise_e / instrument.gain_e_per_dn,
        frames={"dark": instrument.frames_averaged_dark, "white": instrument.frames_averaged_white, "sample": instrument.frames_averaged_sample},
        saturation=full_scale,
    )


def simulated_scene(experiment, frame_id: str, *, coeffs, wiener, wiener_offset) -> NoiseScene:
    """A scene from the physical simulator (`simulate.simulate_experiment` of an instrument with
    `noise=False`): its dark, white-standard and `frame_id` captures as the true means, so that
    Monte Carlo runs on the sphere's own images (glare, vignetting, non-Lambertian samples,
    patterned backgrounds), with the given Stage II coefficients and estimator.

    Pixels below 5 % of the white standard's signal count as dark, the rest as chart.
    """
    instrument = experiment.instrument
    if instrument.noise:
        raise ValueError("experiment: expected one simulated with InstrumentModel(noise=False), whose frames are the means")
    frames = {frame.id: frame for frame in experiment.frames}
    if frame_id not in frames:
        raise ValueError(f"frame_id: {frame_id!r} is not a frame of the experiment")
    bias = float(instrument.bias_dn)
    white_counts = frames["white"].pixels.astype(np.float64) - bias
    sample_counts = frames[frame_id].pixels.astype(np.float64) - bias
    r0, r1, c0, c1 = experiment.white_patch
    patch = np.zeros(experiment.image_shape, bool)
    patch[r0:r1, c0:c1] = True
    dark = np.min(sample_counts / np.maximum(white_counts, 1.0), axis=-1) < 0.05
    kind = np.where(patch, KIND_PATCH, np.where(dark, KIND_DARK, KIND_CHART))
    return NoiseScene(
        white_counts=white_counts, sample_counts=sample_counts, bias=bias, patch=patch, kind=kind,
        coeffs=np.asarray(coeffs, np.float64), wiener=np.asarray(wiener, np.float64),
        wiener_offset=np.asarray(wiener_offset, np.float64), gain=instrument.gain_e_per_dn,
        read_noise=instrument.read_noise_e / instrument.gain_e_per_dn,
        frames={"dark": instrument.frames_averaged_dark, "white": instrument.frames_averaged_white, "sample": instrument.frames_averaged_sample},
        saturation=instrument.saturation_dn,
    )


@dataclasses.dataclass(frozen=True)
class MonteCarloRun:
    """Trials of the path on one scene.

    Fields:
      lab, reflectance: (T, H, W, 3) and (T, H, W, 31), NaN where a trial's pixel is bad.
      lab_u, reflectance_u: the propagated standard uncertainties of each trial, same shapes.
      lab_covariance: (T, H, W, 3, 3).
      true_lab, true_reflectance: (H, W, 3), (H, W, 31): the path on the noise-free frames.
      raws: (T, H, W, B) uint16 and darks, whites: (T, H, W, B) uint16, the frames drawn
        (for `spherejax.measure` on the same trials).
    """

    lab: np.ndarray
    reflectance: np.ndarray
    lab_u: np.ndarray
    reflectance_u: np.ndarray
    lab_covariance: np.ndarray
    true_lab: np.ndarray
    true_reflectance: np.ndarray
    raws: np.ndarray
    darks: np.ndarray
    whites: np.ndarray


def run(scene: NoiseScene, noise: NoiseModel, trials: int, seed: int = 0) -> MonteCarloRun:
    """`trials` draws of the scene through `correct(raw, calibration, noise=noise)`."""
    rng = np.random.default_rng(seed)
    true_raw, true_calibration = scene.noise_free()
    truth = correct(true_raw, true_calibration)
    out = {name: [] for name in ("lab", "reflectance", "lab_u", "reflectance_u", "lab_covariance", "raws", "darks", "whites")}
    for _ in range(trials):
        raw, calibration = scene.draw(rng)
        result = correct(raw, calibration, noise=noise)
        for name in ("lab", "reflectance", "lab_u", "reflectance_u", "lab_covariance"):
            out[name].append(np.asarray(getattr(result, name)))
        out["raws"].append(raw)
        out["darks"].append(np.asarray(calibration.dark).astype(np.uint16))
        out["whites"].append(np.asarray(calibration.white).astype(np.uint16))
    return MonteCarloRun(
        **{name: np.stack(values) for name, values in out.items()},
        true_lab=np.asarray(truth.lab), true_reflectance=np.asarray(truth.reflectance),
    )


__all__ = [
    "KIND_PATCH",
    "KIND_CHART",
    "KIND_DARK",
    "KIND_NEAR_FULL_SCALE",
    "KIND_NEUTRAL",
    "KIND_NAMES",
    "draw_frame",
    "NoiseScene",
    "noise_scene",
    "simulated_scene",
    "MonteCarloRun",
    "run",
]
