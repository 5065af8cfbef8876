"""How the cost of `spherejax.correct` grows with pixels and cores, beside the numpy reference.

What it measures
    `spherejax.correct` and the numpy + colour-science `reference_correct` (reference.py) on
    1, 4 and 16 megapixel cubes (1024², 2048², 4096² x 16 uint16; --sizes), each on 1 core and on
    2 cores: every (size, cores) pair runs in a fresh process pinned with os.sched_setaffinity
    before JAX starts (XLA sizes its thread pool from the CPUs it may use). Reported: median ms
    per call (after a warm-up call), ms per megapixel, MP/s, and the ratio to the reference.
    Cost should grow linearly with pixels: ms per megapixel roughly constant down a column.

The inputs and the agreement check are reference.py's (make_inputs, compare), the timing
harness.py's, in benchmarks/scaling_child.py, run once per (size, cores): a child that
disagrees with the reference stops the benchmark.

Run:
    python benchmarks/bench_scaling.py [--sizes 1024 2048 4096] [--repeats 3]
        [--allocator reuse|default] [--json PATH]

    --allocator as in bench_correct.py, applied in each child process before JAX starts.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))



def run(size: int, cpus: set[int], repeats: int, reuse: bool) -> dict:
    options = json.dumps({"size": size, "cpus": sorted(cpus), "repeats": repeats, "reuse": reuse})
    child = os.path.join(HERE, "scaling_child.py")  # its folder is first on its sys.path: harness, reference
    done = subprocess.run([sys.executable, child, options], capture_output=True, text=True, timeout=3600)
    if done.returncode != 0:
        last = done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}"
        raise SystemExit(f"size {size}, cpus {sorted(cpus)}: {last}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048, 4096])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", metavar="PATH")
    sys.path.insert(0, HERE)
    from harness import add_allocator_argument, machine_info, write_record
    add_allocator_argument(parser)
    args = parser.parse_args(argv)

    available = sorted(os.sched_getaffinity(0))
    core_sets = {1: set(available[:1]), len(available[:2]): set(available[:2])}
    rows = []
    for size in args.sizes:
        for cores, cpus in core_sets.items():
            result = run(size, cpus, args.repeats, args.allocator == "reuse")
            megapixels = size * size / 1e6
            t = result["timings"]
            rows.append({
                "size": size, "megapixels": megapixels, "cores": cores,
                "spherejax_ms": t["spherejax"]["median_s"] * 1e3, "reference_ms": t["reference"]["median_s"] * 1e3,
                "agreement": result["agreement"],
            })
            r = rows[-1]
            print(f"{size:5d}² ({megapixels:5.1f} MP) {cores} core(s): spherejax {r['spherejax_ms']:8.1f} ms "
                  f"({r['spherejax_ms'] / megapixels:6.1f} ms/MP, {megapixels / r['spherejax_ms'] * 1e3:5.2f} MP/s), "
                  f"reference {r['reference_ms']:8.1f} ms ({r['reference_ms'] / megapixels:6.1f} ms/MP), "
                  f"ratio {r['reference_ms'] / r['spherejax_ms']:4.2f}x", flush=True)
    if args.json:
        record = {"benchmark": "bench_scaling", "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                  "repeats": args.repeats, "rows": rows, "machine": machine_info(), "argv": sys.argv}
        write_record(args.json, record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
