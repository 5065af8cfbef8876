"""spherejax: lighting deviation correction for integrating-sphere multispectral imaging.

Implements Zou, Shen, Li, Zhu, Xin, "Lighting Deviation Correction for Integrating-Sphere
Multispectral Imaging Systems", Sensors 19(16), 3501 (2019), doi:10.3390/s19163501, in JAX.

Conventions (all modules): channels last with any leading dimensions; raw and corrected cubes
(..., 16) at the band centres 400..700 nm step 20, reflectance (..., 31) at 400..700 nm step 10,
XYZ and Lab (..., 3); float32 by default, float64 when the caller passes float64. Kernels are pure
and can be jitted, vmapped and differentiated; bad pixel values give NaN, never an exception;
bad shapes and names raise ValueError.

Layers. Each module imports only modules of its own layer or of the layers below it
(tests/test_layers.py reads every import, function-level ones included, and fails otherwise):

1. Kernels, pure JAX and numpy, no files: colorimetry, flatfield, polynomial, estimation (a
   module per reflectance estimator, and their cross-validation) and wiener_estimation (its old
   name, kept for existing imports), quality (the quality bits, one IntFlag), calibration (the
   `Calibration` pytree), equations (the per-pixel equations in jax.numpy, the definition every
   kernel is tested against), pipeline (the public functions `correct`, `plan`, `patch_ratio`),
   pixel_constants (the calibration's arrays as the per-pixel step reads them),
   correction_result, uncertainty, noise_document (a NoiseModel's JSON as a document),
   noise_bands (the rule for a noise model's per-band values that both check against),
   consistency, markov, angles, _engine
   (private: the kernel contract and its kernels, the prepared plan and its routes, the jitted
   steps, buffers, allocator; its package docstring says which module does what), grid, spectra, jsontext (a parser of text it is
   given), number_text (numbers in the shortest text of their precision, JSON values and CSV
   tables as text), labelled (the xarray names of the outputs), _checks, atomic_files (the one
   way every writer puts a file in place, the engine's cache and io's writers alike),
   band_resampling (each band's flat-fielded response resampled through its map into the
   reference band's geometry, before Stage I and II).
2. Workflows, arrays and sessions in, results out (a session is an object they are handed, never
   a path they open): calibrate (calibrate_registration: the bands registered for it), evaluate, study, simulate (the physical simulator and the
   paper's experiment on it, a module per job: simulated_instrument, simulated_layout,
   simulated_rendering, band_geometry (each band's map, as the filters and lens make it),
   sphere_radiosity (the sphere as radiosity elements), textile_brdf (textiles off the Lambertian
   ideal, read under the sphere's light), twin (the simulator fitted to a session)),
   band_registration (each band's map estimated from a session's frames), stripwise, measurement, monte_carlo, simulated_targets, kubelka_munk,
   target_families (shade cards, brighteners, gloss and texture beside kubelka_munk's mixing sets), figures.
3. Files and orchestration: io (frames, cubes, sessions, calibration files; io.journal, the
   fsynced JSON-lines journal of a batch's manifest and an acquisition; io.hashing, the one file
   hash), measurement_files, archive (batch correction, a module per job: discovery, inputs,
   outputs, manifest, lock, batch), cluster, interrupt, console (the command line's messages and
   progress), cli and __main__ (`python -m spherejax`), viewer (the napari plugin and `spherejax
   view`: a pixel's and a region's readout, the reader, the dock widget; the viewer extra); and the instrument, hw/ (installed as
   spherejax_hw), which uses spherejax and which spherejax never imports: it adds `spherejax
   acquire` to cli through the "spherejax.commands" entry points.
"""

from ._engine.allocator import keep_freed_memory as keep_freed_memory
from .colorimetry import (
    delta_e_2000 as delta_e_2000,
    reflectance_to_lab as reflectance_to_lab,
    reflectance_to_xyz as reflectance_to_xyz,
    tristimulus_weights as tristimulus_weights,
    white_point_xyz as white_point_xyz,
    xyz_to_lab as xyz_to_lab,
)
from .consistency import (
    pairwise_delta_e as pairwise_delta_e,
    pairwise_spectral_rms as pairwise_spectral_rms,
    response_std as response_std,
)
from .flatfield import flat_field as flat_field, stage1 as stage1, white_patch_ratio as white_patch_ratio
from .grid import BAND_CENTRES_NM as BAND_CENTRES_NM, WAVELENGTHS_NM as WAVELENGTHS_NM
from .pipeline import (
    QUALITY_NONFINITE as QUALITY_NONFINITE,
    QUALITY_PATCH_UNUSABLE as QUALITY_PATCH_UNUSABLE,
    QUALITY_BELOW_DARK as QUALITY_BELOW_DARK,
    QUALITY_NOT_COVERED as QUALITY_NOT_COVERED,
    BELOW_DARK_LIMIT as BELOW_DARK_LIMIT,
    QUALITY_SATURATED as QUALITY_SATURATED,
    QUALITY_WHITE_NOT_ABOVE_DARK as QUALITY_WHITE_NOT_ABOVE_DARK,
    Quality as Quality,
    Calibration as Calibration,
    CorrectionResult as CorrectionResult,
    correct as correct,
    plan as plan,
    delta_e_map as delta_e_map,
    patch_ratio as patch_ratio,
    patch_ratio_u as patch_ratio_u,
)
from .measurement import Measurement as Measurement, measure as measure
from .uncertainty import NoiseModel as NoiseModel
from .polynomial import fit_stage2 as fit_stage2, identity_coeffs as identity_coeffs, stage2 as stage2
from .estimation import (
    CrossValidation as CrossValidation,
    WienerEstimator as WienerEstimator,
    ResidualKernelEstimator as ResidualKernelEstimator,
    estimate_system as estimate_system,
    fit_estimator as fit_estimator,
    fit_wiener as fit_wiener,
    model_estimator as model_estimator,
    training_estimator as training_estimator,
    wiener_from_system as wiener_from_system,
    wiener as wiener,
    EstimatorCovariance as EstimatorCovariance,
    estimator_covariance as estimator_covariance,
)

__version__ = "0.1.0"


def open_corrected(path):
    """An output of `spherejax correct` as an `xarray.Dataset`, read lazily in row chunks:
    reflectance (y, x, wavelength) with wavelength in nm, lab and quality beside it, the file's
    header as attributes (`spherejax.io.corrected.open_corrected`; names in `spherejax.labelled`).

    `path`: N.reflectance.exr (spectral layout or older names), N.reflectance.hdr (ENVI), a
    sibling output of N, or N. Imported on call: the file readers stay out of `import spherejax`.
    """
    from .io.corrected import open_corrected as _open_corrected

    return _open_corrected(path)

__all__ = [
    "open_corrected",
    "keep_freed_memory",
    "BAND_CENTRES_NM",
    "WAVELENGTHS_NM",
    "QUALITY_NONFINITE",
    "QUALITY_PATCH_UNUSABLE",
    "QUALITY_BELOW_DARK",
    "QUALITY_NOT_COVERED",
    "BELOW_DARK_LIMIT",
    "QUALITY_SATURATED",
    "QUALITY_WHITE_NOT_ABOVE_DARK",
    "Calibration",
    "CorrectionResult",
    "Measurement",
    "NoiseModel",
    "CrossValidation",
    "ResidualKernelEstimator",
    "WienerEstimator",
    "correct",
    "plan",
    "delta_e_2000",
    "delta_e_map",
    "estimate_system",
    "fit_stage2",
    "fit_estimator",
    "fit_wiener",
    "flat_field",
    "identity_coeffs",
    "measure",
    "model_estimator",
    "pairwise_delta_e",
    "pairwise_spectral_rms",
    "patch_ratio",
    "patch_ratio_u",
    "reflectance_to_lab",
    "reflectance_to_xyz",
    "response_std",
    "stage1",
    "stage2",
    "training_estimator",
    "tristimulus_weights",
    "white_patch_ratio",
    "white_point_xyz",
    "wiener",
    "wiener_from_system",
    "xyz_to_lab",
    "EstimatorCovariance",
    "estimator_covariance",
]
