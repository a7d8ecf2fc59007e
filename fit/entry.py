"""The `layerfit` console entry, light enough to catch a Ctrl-C from the first instant
(`fit.interrupts`)."""

from __future__ import annotations

import atexit
import contextlib
import os
import sys
from typing import NoReturn

from . import interrupts


def main() -> None:
    """Install the recording Ctrl-C handler, then run `fit.cli.main`."""
    interrupts.install()
    try:
        from .cli import main as run
    except KeyboardInterrupt:
        sys.stderr.write("interrupted: stopped while starting; nothing written\n")
        sys.stderr.flush()
        # at once: half-imported modules (NumPy's, SciPy's) have nothing to finish, and the
        # interpreter's finalisation after the cut import ended once by SIGINT, not 130
        os._exit(130)
    try:
        run()
    except KeyboardInterrupt:  # between the command's own handlers (logging set up, exiting)
        sys.stderr.write("interrupted: stopped by Ctrl-C or SIGTERM\n")
        _exit_interrupted()
    except SystemExit as done:
        if done.code == 130:
            _exit_interrupted()
        raise


def _exit_interrupted() -> NoReturn:
    """Exit 130 after the exit handlers (Ray's shutdown among them), not through the
    interpreter's own end, which restores SIGINT's default action: the process once ended by
    SIGINT (-2) after it had said "interrupted" and chosen 130 (once in about 40 Ctrl-Cs early
    in a fit, under load; not traced: a native library delivering the signal again is the
    suspect)."""
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(130)
