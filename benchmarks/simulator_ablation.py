"""What each of the simulator's mechanisms contributes to the paper's tables: an ablation.

Not a timing: like bench_wiener's accuracy tables, a results script. For each configuration of
`spherejax.simulate.InstrumentModel` it simulates the paper's experiment (`simulate_experiment`,
seed given), calibrates it as `spherejax calibrate` does by default (`calibrate_session`) and
evaluates it (`evaluate_session`), then prints the averages of Tables 1, 3, 4, 5 and 6 beside
the paper's (Zou et al. 2019), original / Stage I / Stage II:

    lambertian      glare, non-Lambertian first-bounce coupling and fluorescence all off
                    (`InstrumentModel.lambertian()`): the world Stage I was derived for, with
                    the camera's noise and the lamp's flicker
    + glare         that, with the default veiling glare (stray_light_fraction, core)
    + coupling      that, with the default non-Lambertian first-bounce spread
    + fluorescence  that, with the default whitening-agent fluorescence
    default         everything (`InstrumentModel()`), what `spherejax demo` simulates
    + translucency  the default with the small patches and targets as single translucent
                    layers (sample_layer_scattering_power 3, still 3x a single woven layer's)
                    over what lies beneath them: why the default keeps them opaque

Run: python benchmarks/simulator_ablation.py [--seed N] [--json FILE]. About a minute per row on
2 cores. docs/results.md records its output.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import tempfile
import time

import numpy as np

from spherejax import calibrate, evaluate, io
from spherejax.simulate import InstrumentModel

#: The paper's averages: Table 1 / 3 response std., Table 4 / 5 ΔE00 (D65), original / Stage I /
#: Stage II; Table 6 (test, Markov model): response std. and ΔE00 (D65).
PAPER = {
    "training_response_std": (0.0157, 0.0067, 0.0023),
    "test_response_std": (0.0100, 0.0051, 0.0028),
    "training_delta_e00_D65": (5.16, 3.01, 0.37),
    "test_delta_e00_D65": (4.13, 1.79, 0.58),
    "markov": (0.0044, 1.74),
}


def configurations() -> dict[str, InstrumentModel]:
    default = InstrumentModel()
    world = default.lambertian()
    return {
        "lambertian": world,
        "+ glare": dataclasses.replace(world, stray_light_fraction=default.stray_light_fraction),
        "+ coupling": dataclasses.replace(world, non_lambertian_spread=default.non_lambertian_spread),
        "+ fluorescence": dataclasses.replace(world, fluorescence_strength=default.fluorescence_strength),
        "default": default,
        "+ translucency": dataclasses.replace(default, sample_layer_scattering_power=3.0),
    }


def row(instrument: InstrumentModel, seed: int, folder: pathlib.Path) -> dict:
    session = io.write_simulated_session(folder, seed=seed, instrument=instrument)
    calibration, _ = calibrate.calibrate_session(session)
    metrics = evaluate.evaluate_session(session, calibration).metrics
    out = {}
    for name in ("training", "test"):
        out[f"{name}_response_std"] = tuple(metrics[name][s]["response_std"] for s in ("original", "stage1", "stage2"))
        out[f"{name}_delta_e00_D65"] = tuple(metrics[name][s]["delta_e00_D65"] for s in ("original", "stage1", "stage2"))
    out["markov"] = (metrics["test"]["markov"]["response_std"], metrics["test"]["markov"]["delta_e00_D65"])
    return out


def _cells(values, digits):
    return " / ".join(f"{v:.{digits}f}" for v in values)


def table(rows: dict[str, dict]) -> str:
    header = ("| | Table 1 std. | Table 3 std. | Table 4 ΔE00 | Table 5 ΔE00 | Table 6 std. / ΔE00 |\n"
              "|---|---|---|---|---|---|")
    lines = [header]
    for name, values in {"paper": PAPER, **rows}.items():
        lines.append(f"| {name} | {_cells(values['training_response_std'], 4)} | {_cells(values['test_response_std'], 4)} | "
                     f"{_cells(values['training_delta_e00_D65'], 2)} | {_cells(values['test_delta_e00_D65'], 2)} | "
                     f"{values['markov'][0]:.4f} / {values['markov'][1]:.2f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", metavar="FILE", default=None, help="also write the rows as JSON (a new file)")
    args = parser.parse_args(argv)
    rows = {}
    with tempfile.TemporaryDirectory() as scratch:
        for name, instrument in configurations().items():
            started = time.perf_counter()
            rows[name] = row(instrument, args.seed, pathlib.Path(scratch) / name.replace(" ", "").replace("+", "with-"))
            print(f"{name}: {time.perf_counter() - started:.0f} s", file=sys.stderr)
    print(table(rows))
    if args.json:
        with open(args.json, "x", encoding="utf-8") as handle:
            json.dump({"seed": args.seed, "paper": PAPER, "rows": rows}, handle, indent=2)
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    sys.exit(main())
