"""`spherejax correct`: the batch with its progress (spherejax.archive does the work)."""

from __future__ import annotations

import contextlib
import logging

from .. import console, interrupt
from .shared import _one_line


class _BatchProgress:
    """Progress of `correct`: a tqdm bar (files, MP/s) on a terminal, else one log line per input."""

    def __init__(self, quiet: bool):
        self.quiet, self.bar, self.total, self.index = quiet, None, 0, 0
        self.megapixels, self.seconds = 0.0, 0.0

    def start(self, specs) -> None:
        self.total = len(specs)
        if not self.quiet and console.on_terminal():
            self.bar = console.bar(total=self.total, unit="file")

    def result(self, spec, result) -> None:
        self.index += 1
        if result is not None:
            self.megapixels += result.megapixels
            self.seconds += result.seconds
        rate = self.megapixels / self.seconds if self.seconds else 0.0
        if self.bar is not None:
            self.bar.set_postfix_str(f"{rate:.1f} MP/s", refresh=False)
            self.bar.update(1)
            if result is not None and result.status == "failed":
                console.say(f"spherejax: failed {_one_line(spec.source)}: {_one_line(result.reason)}", logging.WARNING)
            return
        if self.quiet:
            return
        if result is None:
            what = "skipped (already done)"
        elif result.status == "done":
            what = f"done ({result.megapixels:.2f} MP, {result.seconds:.2f} s)"
        else:
            what = f"failed: {result.reason}"
        console.say(f"spherejax: [{self.index}/{self.total}] {_one_line(spec.source)}: {_one_line(what)}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def cmd_correct(args) -> int:
    from .. import archive

    executor = contextlib.nullcontext()
    if args.workers is not None or args.scheduler is not None:
        from .. import cluster

        executor = cluster.DaskExecutor(workers=args.workers, scheduler=args.scheduler)
    progress = _BatchProgress(args.quiet)

    try:
        # SIGINT / SIGTERM stop the batch at its next safe point (spherejax.interrupt); `main`
        # reports it. Outermost, so that the cluster's start and stop are covered too.
        with interrupt.stop_requests(), executor as running:
            summary = archive.run_batch(
                args.inputs, args.output, args.calibration, resume=args.resume,
                illuminant=args.illuminant, exr_compression=args.exr_compression, output_format=args.output_format,
                reflectance_type=args.reflectance_type,
                on_start=progress.start, on_result=progress.result, on_warning=console.warn, executor=running,
            )
    finally:
        progress.close()
    if summary.taken_over:
        console.say(f"spherejax: took over the lock left by {summary.taken_over} (that run ended without releasing it)",
                    logging.WARNING)
    for failure in summary.failed:
        console.say(f"spherejax: failed {_one_line(failure.source)}: {_one_line(failure.reason)}", logging.ERROR)
    print(summary.line())
    return 1 if summary.failed else 0
