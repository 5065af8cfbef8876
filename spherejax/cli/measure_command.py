"""`spherejax measure`: its options checked, the regions measured, the files written
(spherejax.measurement_files)."""

from __future__ import annotations

import datetime
import pathlib

from .. import console, interrupt
from ..console import Steps
from . import number_types as numbers
from .shared import argument_text, check_writable


def _measure_regions(values, image_shape=None) -> list[tuple[str, tuple[int, int, int, int], str]]:
    """--region NAME=r0,r1,c0,c1 values -> [(name, rect, as given)]; ValueError naming the option
    and value. With `image_shape`, each rectangle must also lie inside the image."""
    regions, names = [], set()
    for given in values:
        given = argument_text(given, "--region")  # "rôt" under LC_ALL=C: its UTF-8, not escapes
        expected = "NAME=r0,r1,c0,c1: a name, then four integers, rows r0..r1-1 and columns c0..c1-1"
        name, sep, numbers = given.partition("=")
        name = name.strip()
        parts = [part.strip() for part in numbers.split(",")]
        if not sep or not name or len(parts) != 4:
            raise ValueError(f"--region {given!r}: expected {expected}")
        if not name.isprintable():
            raise ValueError(f"--region {given!r}: the name holds a control character (expected a printable name)")
        try:
            rect = tuple(int(part) for part in parts)
        except ValueError:
            raise ValueError(f"--region {given!r}: the bounds are not integers (expected {expected})") from None
        r0, r1, c0, c1 = rect
        if not (r0 < r1 and c0 < c1):
            raise ValueError(f"--region {given!r}: is empty (expected r0 < r1 and c0 < c1)")
        if image_shape is not None:
            height, width = image_shape
            if not (0 <= r0 and r1 <= height and 0 <= c0 and c1 <= width):
                raise ValueError(
                    f"--region {given!r}: lies outside the {height} x {width} image (expected "
                    f"0 <= r0 < r1 <= {height} and 0 <= c0 < c1 <= {width})"
                )
        if name in names:
            raise ValueError(f"--region {given!r}: the name {name!r} is given twice (expected one name per region)")
        names.add(name)
        regions.append((name, rect, given))
    return regions


def _measure_reference(value: str | None, names):
    """--reference: None, ("region", NAME) or ("lab", [L, a, b]); ValueError naming the value."""
    import math

    if value is None:
        return None
    value = argument_text(value, "--reference")  # as the region names are (`_measure_regions`)
    if value in names:
        return "region", value
    parts = value.split(",")
    if len(parts) == 3:
        try:
            lab = [float(part) for part in parts]
        except ValueError:
            lab = None
        if lab is not None and all(math.isfinite(x) for x in lab):
            (l_low, l_high), (ab_low, ab_high) = numbers.REFERENCE_L_RANGE, numbers.REFERENCE_AB_RANGE
            if l_low <= lab[0] <= l_high and all(ab_low <= x <= ab_high for x in lab[1:]):
                return "lab", lab
            raise ValueError(
                f"--reference {value!r}: lies outside CIELAB's range (expected L* {numbers.shown(l_low)}.."
                f"{numbers.shown(l_high)} and a*, b* {numbers.shown(ab_low)}..{numbers.shown(ab_high)})"
            )
    known = ", ".join(repr(name) for name in names)
    raise ValueError(
        f"--reference {value!r}: expected the name of a --region ({known}) or three finite numbers L,a,b"
    )


def _measure_noise(args, from_file):
    """(noise model or None, where it came from, a note for stderr or None); ValueError on bad
    options.

    The calibration's model by default; --gain, --read-noise and --frames override its fields or,
    both of the first two given, make one when the calibration has none. Each is a number in
    range or None: the parser refused anything else (cli.number_types)."""
    import numpy as np

    from ..uncertainty import NoiseModel

    gain, read, frames = args.gain, args.read_noise, args.frames
    options = gain is not None or read is not None or frames is not None
    single = lambda x: np.float32(x)  # noqa: E731  the dtype a calibration file's model reads back in
    if from_file is None:
        if not options:
            return None, None, (
                "spherejax: note: no noise model (the calibration has none): values without "
                "uncertainties; give --gain E_PER_COUNT and --read-noise COUNTS (and --frames N) for them"
            )
        missing = [name for name, value in (("--gain", gain), ("--read-noise", read)) if value is None]
        if missing:
            given = "--gain" if gain is not None else "--read-noise" if read is not None else "--frames"
            raise ValueError(
                f"{missing[0]}: missing; the calibration has no noise model, so {given} needs "
                f"{' and '.join(missing)} too (expected --gain E_PER_COUNT and --read-noise COUNTS)"
            )
        note = ("spherejax: note: noise model from --gain and --read-noise (the calibration has none): "
                "dark and white frames taken as single frames, Stage II and the estimator as exact")
        model = NoiseModel(gain=single(gain), read_noise=single(read), sample_frames=single(1 if frames is None else frames))
        return model, "options", note
    if not options:
        return from_file, "calibration", None
    model = NoiseModel(
        gain=from_file.gain if gain is None else single(gain),
        read_noise=from_file.read_noise if read is None else single(read),
        dark_frames=from_file.dark_frames, white_frames=from_file.white_frames,
        sample_frames=from_file.sample_frames if frames is None else single(frames),
        white_reflectance_u=from_file.white_reflectance_u, coeffs_covariance=from_file.coeffs_covariance,
        estimator_covariance=from_file.estimator_covariance,
    )
    return model, "calibration, options", None


def cmd_measure(args) -> int:
    import numpy as np

    from .. import io, measurement_files
    from ..measurement import measure
    from ..uncertainty import NoiseModel

    # Everything the arguments alone decide is refused before any file is read.
    regions = _measure_regions(args.region)
    reference = _measure_reference(args.reference, [name for name, _, _ in regions])
    base = pathlib.Path(args.output) if args.output else measurement_files.default_base(args.input)
    measurement_files.check_output_base(base)
    if args.cgats is not None:
        measurement_files.check_cgats_path(args.cgats, measurement_files.output_paths(base))
    csv_path, json_path = measurement_files.output_paths(base)
    check_writable(csv_path, "-o OUT", folder=False)  # before the cube is read and measured
    if args.cgats is not None:
        check_writable(args.cgats, "--cgats FILE", folder=False)
    outputs = {"OUT.csv": csv_path, "OUT.json": json_path}
    if args.cgats is not None:
        outputs["--cgats FILE"] = args.cgats
    io.refuse_overlaps(outputs, {"the input cube": args.input, "the calibration (-c)": args.calibration})
    # A file at an output's name is replaced only when its own first bytes prove an earlier
    # measure wrote it: a user's user.csv, user.json or notes at the --cgats name, at -o's names
    # or the default ones in the working folder, is refused and left as it is.
    measurement_files.refuse_foreign_files(csv_path, json_path, args.cgats)

    calibration_file = io.open_calibration(args.calibration)
    try:
        header = calibration_file.header
        noise = getattr(calibration_file, "noise_model", None)
        if noise is None and header.get("noise_model") is not None:
            try:
                noise = NoiseModel.from_json(header["noise_model"])
            except ValueError as error:
                raise io.CalibrationFileError(args.calibration, f"has an invalid noise model: {error}") from None
        regions = _measure_regions(args.region, calibration_file.image_shape)
        noise, noise_source, note = _measure_noise(args, noise)
        shape = (*calibration_file.image_shape, calibration_file.bands)
        if noise is not None:
            noise.check_bands(shape[2])
        calibration = calibration_file.calibration()
    finally:
        calibration_file.close()
    raw = io.read_cube(args.input, expected_shape=shape, band_centres_nm=header["band_centres_nm"])

    results = {}
    # A bar on a terminal only: measure's stderr is otherwise empty unless something is wrong.
    with Steps(1, args.quiet, lines=False) as progress:
        progress.start(f"measuring {len(regions)} regions of {args.input}")
        for done, (name, rect, given) in enumerate(regions):
            progress.count(done, len(regions))
            r0, r1, c0, c1 = rect
            mask = np.zeros(shape[:2], bool)
            mask[r0:r1, c0:c1] = True
            try:
                results[name] = measure(raw, calibration, mask, noise, illuminant=args.illuminant)
            except ValueError as error:
                raise ValueError(f"--region {given!r}: {str(error).removeprefix('mask: ')}") from None
        progress.done()
    rows, label, reference_doc = [], None, None
    if reference is not None and reference[0] == "region":
        against = results[reference[1]]
        label = f"region {reference[1]!r} (its uncertainty included)"
        reference_doc = {"region": reference[1], "lab": against.lab.tolist()}
    elif reference is not None:
        against = reference[1]
        label = "L*a*b* = ({:g}, {:g}, {:g}) (exact)".format(*against)
        reference_doc = {"lab": against}
    for name, rect, _ in regions:
        m = results[name]
        delta_e = u = None
        if reference is not None:
            delta_e, u = m.delta_e(against)
        rows.append(measurement_files.RegionResult(name, rect, m, delta_e, u))

    illuminant = rows[0].measurement.illuminant
    document = measurement_files.json_document(
        rows, input_path=args.input, illuminant=illuminant, reference=reference_doc,
        calibration={"path": str(args.calibration), "checksum": header.get("checksum"),
                     "instrument_id": header.get("instrument_id")},
        noise_model=measurement_files.noise_model_summary(noise, noise_source),
    )
    files = {csv_path: measurement_files.csv_text(rows).encode(),
             json_path: measurement_files.json_text(document).encode()}
    if args.cgats is not None:
        created = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        files[pathlib.Path(args.cgats)] = measurement_files.cgats_text(
            rows, input_path=args.input, instrument_id=header.get("instrument_id"), created=created,
        ).encode()
    # A stop request (SIGINT, SIGTERM) while the two files are written waits until both are in place.
    with interrupt.stop_requests():
        measurement_files.write_files(files)
    if note is not None:
        console.say(note)
    if not args.quiet:
        print(measurement_files.format_table(rows, reference=label), end="")
        print("written: " + ", ".join(map(str, files)))
    return 0
