"""Consistency of a patch measured on different backgrounds: the paper's Tables 1 and 3-6.

How every figure is computed (Zou et al. 2019, Section 5, made exact):

- Responses. Every annotated patch region of a capture is averaged (the paper's 35 x 35 px; bad pixels left
  out) at four stages, all from the same v (Eq. 10) and p (Eq. 15) that `correct` computes:
  original = v; Stage I = p v (Eq. 17); Stage II = Eq. 23 with the calibration's coefficients;
  Markov = R / R_W with R the Markov model's reflectance (`spherejax.markov`, κ fitted on the
  training greys) and R_W the white board's reflectance per band, so that all four are on the
  scale of v (1 = as bright as the white board).
- Response standard deviation (Tables 1 and 3): for each patch and band, the population standard
  deviation (ddof = 0) of its responses across the backgrounds it was measured on; averaged over
  patches, per band; "average" is the mean over the 16 bands.
- Reflectance: the calibration's Wiener matrix applied to each stage's region responses (the
  same matrix for every stage, as in the paper).
- Spectral rms and ΔE00 (Tables 4 and 5): for each patch, every pair of backgrounds (j, j')
  gives the rms over the 31 wavelengths of r_j - r_j', and the CIEDE2000 difference of their
  CIELAB under D65, A and F2 (ASTM E308, 2° observer); averaged over the pairs of a patch, then
  over patches.
- Table 6: the test set's average response standard deviation, spectral rms and ΔE00 for the
  original responses, the Markov model and Stage II.
- Accuracy (not in the paper): mean ΔE00 (D65) of each stage's reflectance against the patch's
  known reflectance, where the session annotates it (the spectrophotometer's value).

The response standard deviation, spectral rms and ΔE00 figures are computed by
`spherejax.consistency`, the same differentiable functions a study of their gradients uses.
"""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np

from .calibrate import RegionMeasurement, measure_frames
from .colorimetry import delta_e_2000, reflectance_to_lab
from .consistency import pairwise_delta_e, pairwise_spectral_rms, response_std
from .markov import fit_markov_kappa, markov_correct
from .number_text import csv_text, json_ready
from .pipeline import Calibration
from .polynomial import stage2

STAGES = ("original", "stage1", "stage2", "markov")
STAGE_LABELS = {"original": "Original", "stage1": "Stage I", "stage2": "Stage II", "markov": "Markov model"}
ILLUMINANTS = ("D65", "A", "F2")

#: White board reflectance assumed when a session does not state it (PTFE, Spectralon-like).
DEFAULT_WHITE_REFLECTANCE = 0.99


@dataclasses.dataclass
class StageData:
    """Per set: patches (P names), backgrounds (J names), responses[stage] (P, J, B) and
    reflectance[stage] (P, J, 31), NaN where a patch was not measured on a background; truth
    (P, 31) known reflectance or NaN."""

    patches: list[str]
    backgrounds: list[str]
    responses: dict[str, np.ndarray]
    reflectance: dict[str, np.ndarray]
    truth: np.ndarray


@dataclasses.dataclass
class Evaluation:
    """All tables. sets: "training" and "test" -> StageData; metrics[set][stage] -> dict."""

    band_centres_nm: list[int]
    kappa: list[float]
    sets: dict[str, StageData]
    metrics: dict[str, dict[str, dict]]


def white_reflectance_per_band(session) -> np.ndarray:
    """R_W at the band centres: from the session's metadata "white_standard_reflectance"
    (31 values, 400..700 nm step 10) or DEFAULT_WHITE_REFLECTANCE."""
    values = (session.metadata or {}).get("white_standard_reflectance")
    bands = np.asarray(session.band_centres_nm, float)
    if values is None:
        return np.full(bands.shape, DEFAULT_WHITE_REFLECTANCE)
    return np.interp(bands, np.arange(400.0, 701.0, 10.0), np.asarray(values, float))


def _stage_responses(m: RegionMeasurement, calibration: Calibration, kappa, white_r) -> dict[str, np.ndarray]:
    coeffs = np.asarray(calibration.coeffs, np.float64)
    g = m.v * white_r
    markov = np.asarray(markov_correct(g, m.holder_v * white_r, kappa, white_r)) / white_r
    return {
        "original": m.v,
        "stage1": m.p * m.v,
        "stage2": np.asarray(stage2(m.v, m.p, coeffs), np.float64),
        "markov": markov,
    }


def _assemble(measurements, calibration, kappa, white_r) -> StageData:
    patches = sorted({m.patch for m in measurements})
    backgrounds = list(dict.fromkeys(m.background for m in measurements))
    bands = calibration.bands
    sums = {s: np.zeros((len(patches), len(backgrounds), bands)) for s in STAGES}
    counts = np.zeros((len(patches), len(backgrounds), 1))
    truth = np.full((len(patches), 31), np.nan)
    for m in measurements:
        i, j = patches.index(m.patch), backgrounds.index(m.background)
        for stage, value in _stage_responses(m, calibration, kappa, white_r).items():
            sums[stage][i, j] += value
        counts[i, j] += 1
        if m.reflectance is not None:
            truth[i] = m.reflectance
    with np.errstate(invalid="ignore"):
        responses = {s: np.where(counts > 0, sums[s] / np.maximum(counts, 1), np.nan) for s in STAGES}
    # The calibration's estimate of every stage's responses: r = W v + r0 (E1), plus its kernel
    # residual A k(v) (E8) where it has one; unmeasured (NaN) stay NaN.
    W = np.asarray(calibration.wiener, np.float64)
    r0 = np.asarray(calibration.wiener_offset, np.float64)
    reflectance = {s: responses[s] @ W.T + r0 for s in STAGES}
    if calibration.wiener_residual is not None:
        with jax.enable_x64(True):
            kernel = calibration.wiener_residual.astype(jnp.float64)
            reflectance = {s: reflectance[s] + np.asarray(kernel(jnp.asarray(responses[s])), np.float64) for s in STAGES}
    return StageData(patches, backgrounds, responses, reflectance, truth)


def consistency_metrics(data: StageData, stage: str) -> dict:
    """The figures of Tables 1/3 and 4/5 for one stage of one set (see the module docstring).

    Computed by `spherejax.consistency` in float64, whatever JAX's default precision: the tables
    print four decimals of differences between responses near 1.
    """
    responses = np.asarray(data.responses[stage], np.float64)
    reflectance = np.asarray(data.reflectance[stage], np.float64)
    # _assemble leaves NaN where a patch was not measured on a background. Responses are judged
    # per band, so that a band whose Stage II coefficients are not finite is NaN on its own; a
    # reflectance mixes all bands.
    measured_bands = np.isfinite(responses)
    measured = np.all(np.isfinite(reflectance), axis=-1)
    with jax.enable_x64(True):
        std_per_band = np.asarray(response_std(responses, measured_bands), np.float64)
        metrics = {
            "response_std_per_band": [float(x) for x in std_per_band],
            "response_std": float(np.mean(std_per_band)),
            "spectral_rms": float(pairwise_spectral_rms(reflectance, measured)),
        }
        for illuminant in ILLUMINANTS:
            metrics[f"delta_e00_{illuminant}"] = float(pairwise_delta_e(reflectance, measured, illuminant))
    if np.isfinite(data.truth).all():
        lab = np.asarray(reflectance_to_lab(np.nan_to_num(reflectance), "D65"), np.float64)
        lab_truth = np.asarray(reflectance_to_lab(data.truth, "D65"), np.float64)[:, None]
        de = np.asarray(delta_e_2000(lab, lab_truth))
        de = np.where(np.all(np.isfinite(reflectance), axis=-1), de, np.nan)
        metrics["accuracy_delta_e00_D65"] = float(np.nanmean(de))
    return metrics


def evaluate_session(session, calibration: Calibration) -> Evaluation:
    """Measure every training and test capture of `session` and compute all tables."""
    white_r = white_reflectance_per_band(session)
    measured = {
        name: measure_frames(session, session.frames_with(role="sample", set=name), calibration)
        for name in ("training", "test")
    }
    if not measured["training"]:
        raise ValueError(f"{session.path}: no training captures to evaluate")
    greys = [m for m in measured["training"] if m.reflectance is not None]
    if not greys:
        raise ValueError(f"{session.path}: no training region with known reflectance to fit the Markov model")
    band_idx = np.searchsorted(np.arange(400, 701, 10), np.asarray(session.band_centres_nm))
    known = np.stack([m.reflectance[band_idx] for m in greys])
    fitted = np.asarray(fit_markov_kappa(
        np.stack([m.v * white_r for m in greys]),
        np.stack([m.holder_v * white_r for m in greys]),
        known, white_r,
    ))
    kappa = fitted.astype(np.float64)
    sets = {name: _assemble(ms, calibration, kappa, white_r) for name, ms in measured.items() if ms}
    metrics = {name: {stage: consistency_metrics(data, stage) for stage in STAGES} for name, data in sets.items()}
    # κ as the shortest decimals of the precision it was fitted in (float32 unless x64 is on).
    return Evaluation([int(b) for b in session.band_centres_nm], json_ready(fitted), sets, metrics)


# --------------------------------------------------------------------------------------------
# Tables as text, CSV and JSON (strings; the command line writes them)


#: The step in L* between neighbouring pixels that `material_edges` takes for an edge.
EDGE_STEP_LSTAR = 3.0


def material_edges(lab: np.ndarray, step: float = EDGE_STEP_LSTAR) -> np.ndarray:
    """(H, W) bool: pixels within one pixel (4-neighbours) of a step of more than `step` in L*
    between neighbouring pixels of lab (H, W, 3): where misregistered bands put their colour
    fringes (`benchmarks/bench_registration.py`, tests/test_calibrate_registration.py). A NaN
    pixel makes no step."""
    lightness = np.asarray(lab, np.float64)[..., 0]
    with np.errstate(invalid="ignore"):
        across = np.abs(np.diff(lightness, axis=1)) > step
        down = np.abs(np.diff(lightness, axis=0)) > step
    edges = np.zeros(lightness.shape, bool)
    edges[:, 1:] |= across
    edges[:, :-1] |= across
    edges[1:, :] |= down
    edges[:-1, :] |= down
    return edges


def neighbourhood_delta_e(reflectance: np.ndarray, reference: np.ndarray, illuminant: str = "D65") -> np.ndarray:
    """(H, W) ΔE00 between the colours of two reflectance cubes (H, W, 31) over each pixel's 3 x 3
    neighbourhood (means of reflectance, the frame's edge repeated). A colour fringe (bands
    displaced by a pixel or more) gives a neighbourhood the wrong colour; a sub-pixel blur, which
    only moves light between neighbours, changes it far less than it changes single pixels
    (`benchmarks/bench_registration.py` measures both). NaN where either has a NaN there."""
    def box3(cube):
        cube = np.asarray(cube, np.float64)
        padded = np.pad(cube, ((1, 1), (1, 1), (0, 0)), mode="edge")
        height, width = cube.shape[:2]
        return sum(padded[i:i + height, j:j + width] for i in range(3) for j in range(3)) / 9.0

    lab = reflectance_to_lab(box3(reflectance), illuminant=illuminant)
    lab_reference = reflectance_to_lab(box3(reference), illuminant=illuminant)
    return np.asarray(delta_e_2000(lab, lab_reference), np.float64)


def format_table(header: list[str], rows: list[list[str]]) -> str:
    """An aligned text table: first column left-aligned, the others right-aligned."""
    widths = [max(len(str(x)) for x in column) for column in zip(header, *rows)]
    line = lambda cells: "  ".join(str(c).rjust(w) if k else str(c).ljust(w) for k, (c, w) in enumerate(zip(cells, widths)))  # noqa: E731
    return "\n".join([line(header), "  ".join("-" * w for w in widths), *[line(r) for r in rows]])


def table_response_std(evaluation: Evaluation, set_name: str) -> tuple[list[str], list[list[str]]]:
    """Tables 1 (training) and 3 (test): rows original, Stage I, Stage II; one column per band."""
    header = ["", *[f"{b} nm" for b in evaluation.band_centres_nm], "Average"]
    rows = []
    for stage in ("original", "stage1", "stage2"):
        m = evaluation.metrics[set_name][stage]
        rows.append([STAGE_LABELS[stage], *[f"{x:.4f}" for x in m["response_std_per_band"]], f"{m['response_std']:.4f}"])
    return header, rows


def table_reflectance(evaluation: Evaluation, set_name: str, stages=("original", "stage1", "stage2")):
    """Tables 4 (training) and 5 (test): spectral rms and ΔE00 under D65, A, F2."""
    header = ["", "Spectral rms", "ΔE00 (D65)", "ΔE00 (A)", "ΔE00 (F2)"]
    rows = []
    for stage in stages:
        m = evaluation.metrics[set_name][stage]
        rows.append([STAGE_LABELS[stage], f"{m['spectral_rms']:.4f}", *[f"{m[f'delta_e00_{i}']:.4f}" for i in ILLUMINANTS]])
    return header, rows


def table_6(evaluation: Evaluation):
    """Table 6: test set, original vs Markov model vs Stage II ("Ours")."""
    header = ["", "Response std. dev.", "Spectral rms", "ΔE00 (D65)", "ΔE00 (A)", "ΔE00 (F2)"]
    rows = []
    for stage, label in (("original", "Original"), ("markov", "Markov model"), ("stage2", "Ours (Stage II)")):
        m = evaluation.metrics["test"][stage]
        rows.append([label, f"{m['response_std']:.4f}", f"{m['spectral_rms']:.4f}", *[f"{m[f'delta_e00_{i}']:.4f}" for i in ILLUMINANTS]])
    return header, rows


def tables(evaluation: Evaluation) -> dict[str, tuple[str, list[str], list[list[str]]]]:
    """name -> (title, header, rows) for every table the evaluation can fill."""
    out = {
        "table1": ("Table 1. Response standard deviation, training data", *table_response_std(evaluation, "training")),
        "table4": ("Table 4. Spectral reflectance consistency, training data", *table_reflectance(evaluation, "training")),
    }
    if "test" in evaluation.sets:
        out["table3"] = ("Table 3. Response standard deviation, test data", *table_response_std(evaluation, "test"))
        out["table5"] = ("Table 5. Spectral reflectance consistency, test data", *table_reflectance(evaluation, "test"))
        out["table6"] = ("Table 6. Comparison with the Markov model, test data", *table_6(evaluation))
    return dict(sorted(out.items()))


def format_tables(evaluation: Evaluation) -> str:
    """All tables as aligned text."""
    return "\n\n".join(f"{title}\n{format_table(header, rows)}" for title, header, rows in tables(evaluation).values())


def tables_csv(evaluation: Evaluation) -> dict[str, str]:
    """name -> CSV text of each table (Python's csv module, `number_text.csv_text`: a label
    with a comma or a quote is quoted, inner quotes doubled), the numbers as the tables print them."""
    return {name: csv_text(header, rows) for name, (_, header, rows) in tables(evaluation).items()}


def to_json(evaluation: Evaluation) -> str:
    """The metrics, κ and band centres as JSON text, every number the shortest decimal of its
    precision (`number_text.json_ready`; the metrics are float64, κ as fitted)."""
    return json.dumps(json_ready(
        {"band_centres_nm": evaluation.band_centres_nm, "markov_kappa": evaluation.kappa, "metrics": evaluation.metrics},
    ), indent=2)


__all__ = [
    "EDGE_STEP_LSTAR",
    "material_edges",
    "neighbourhood_delta_e",
    "STAGES",
    "StageData",
    "Evaluation",
    "evaluate_session",
    "consistency_metrics",
    "white_reflectance_per_band",
    "tables",
    "format_table",
    "format_tables",
    "tables_csv",
    "to_json",
]
