"""Reading a session manifest of many frames: the JSON parse and the check of every field.

A session may list thousands of frames; `load_session` parses its manifest.json and checks every
field of every frame before it looks at a frame file. This times that step alone (the frame files'
headers are not read) on a synthetic manifest: one dark, one white, and N - 2 sample and target
frames of 16 bands with two regions each (targets with 31 reflectances per region).

    python benchmarks/bench_manifest.py                 # 5000 frames, 7 repeats
    python benchmarks/bench_manifest.py --frames 20000 --repeats 3

Prints the median and minimum of the repeats in ms and per frame in microseconds.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import statistics
import tempfile
import time

from spherejax.io import sessions

BANDS = list(range(400, 701, 20))
H, W = 1024, 1360
CREATED = "2026-01-05T09:00:00+00:00"


def manifest(frames: int) -> dict:
    """A valid manifest (format version 1) of `frames` frames, frames >= 2."""

    def frame(index: int) -> dict:
        entry = {
            "id": f"f{index:06d}",
            "file": f"frames/f{index:06d}.tif",
            "exposure_s": [0.01 + 0.001 * b for b in range(len(BANDS))],
            "timestamp": CREATED,
        }
        if index == 0:
            return {**entry, "role": "dark"}
        if index == 1:
            return {**entry, "role": "white", "metadata": {"lamp_hours": 12.5}}
        target = index % 10 == 0  # one frame in ten shows a chart of known reflectances
        regions = [
            {"name": f"p{k}", "patch": f"patch{k}", "region": [10 + 100 * k, 60 + 100 * k, 10, 60]}
            | ({"reflectance": [0.2 + 0.01 * w for w in range(31)]} if target else {})
            for k in range(2)
        ]
        if target:
            return {**entry, "role": "target", "regions": regions}
        return {**entry, "role": "sample", "set": ("training", "test")[index % 2], "background": "bg03", "regions": regions}

    return {
        "format": sessions.SESSION_FORMAT,
        "format_version": sessions.SESSION_FORMAT_VERSION,
        "software_version": "0.1.0",
        "instrument_id": "sphere-1",
        "created": CREATED,
        "band_centres_nm": BANDS,
        "image_shape": [H, W],
        "saturation": 16383,
        "white_patch": [0, 35, 0, 35],
        "holder": [100, 900, 100, 1200],
        "frames": [frame(i) for i in range(frames)],
        "metadata": {},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=5000)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        root = pathlib.Path(folder)
        path = root / sessions.MANIFEST_NAME
        path.write_text(json.dumps(manifest(args.frames)))
        size = path.stat().st_size
        times = []
        for _ in range(args.repeats + 1):  # the first is a warm-up
            start = time.perf_counter()
            session = sessions._parse_manifest(sessions._read_manifest(path), manifest_path=path, root=root)
            times.append(time.perf_counter() - start)
        assert len(session.frames) == args.frames
    times = times[1:]
    median, best = statistics.median(times), min(times)
    print(
        f"{args.frames} frames, {size} bytes: "
        f"median {median * 1e3:.1f} ms ({median / args.frames * 1e6:.1f} us/frame), "
        f"min {best * 1e3:.1f} ms, {args.repeats} repeats"
    )


if __name__ == "__main__":
    main()
