"""One measurement of bench_scaling.py, in a fresh process pinned to the CPUs it is given:
`spherejax.correct` and the numpy + colour-science reference on a (size, size, 16) cube, taking
turns, printed as one JSON line.

    python benchmarks/scaling_child.py '{"size": 1024, "cpus": [0], "repeats": 5, "reuse": false}'
"""

import json
import os
import sys
import warnings


def main(argv: list[str]) -> int:
    options = json.loads(argv[1])
    # Pinned before JAX starts, so that XLA sizes its thread pool to these CPUs.
    os.sched_setaffinity(0, set(options["cpus"]))
    warnings.filterwarnings("ignore")
    import spherejax._engine.allocator

    if options["reuse"]:
        spherejax._engine.allocator.keep_freed_memory()  # before any JAX work, as the command line does
    import jax

    import harness
    import reference
    import spherejax

    inputs = reference.make_inputs(options["size"])
    coeffs, wiener = reference.stage2_coeffs(), reference.wiener_matrix()
    calibration = reference.make_calibration(inputs, coeffs, wiener)
    xyz_weights, whitepoint_xy = reference.reference_constants()

    def run_spherejax():
        return jax.block_until_ready(spherejax.correct(inputs["raw"], calibration))

    def run_reference():
        return reference.reference_correct(
            inputs["raw"], inputs["dark"], inputs["white"], inputs["patch"], coeffs, wiener, xyz_weights, whitepoint_xy
        )

    agreement = reference.compare(run_spherejax(), run_reference())
    timings = harness.time_interleaved({"spherejax": run_spherejax, "reference": run_reference}, options["repeats"])
    print(json.dumps({
        "agreement": agreement,
        "timings": {name: {"median_s": t["median_s"], "min_s": t["min_s"]} for name, t in timings.items()},
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
