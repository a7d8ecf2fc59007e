"""The `layerfit` console entry, light enough to catch a Ctrl-C from the first instant.

The command line's imports (SciPy, scikit-image, then Mitsuba and JAX) take seconds; a Ctrl-C
there printed a traceback of the import, and one that landed in JAX's garbage-collection
callback was swallowed ("Exception ignored in: _xla_gc_callback") while the fit ran on to its
end. So the first handler also records the request (`asked()`), which the command checks where
its own handling begins (`fit.cli._start`, the fit's stop handler)."""

from __future__ import annotations

import atexit
import contextlib
import os
import signal
import sys
from collections.abc import Iterator
from typing import NoReturn

#: Whether a Ctrl-C arrived before a command took over its handling (kept even where a
#: library's callback swallowed the KeyboardInterrupt it raised): `asked()`.
_state = {"asked": False}


def asked() -> bool:
    """Whether a Ctrl-C has been recorded (see the module's text)."""
    return _state["asked"]


def _interrupt(signum, frame) -> None:
    _state["asked"] = True
    raise KeyboardInterrupt


def _record(signum, frame) -> None:
    _state["asked"] = True


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Inside, a Ctrl-C is only recorded (`asked()`), for the caller to honour after: Dr.Jit's
    import interrupted half-way aborted the interpreter at its exit ("Fatal Python error:
    PyThreadState_Get: the function must be called with the GIL held", 1 of 14 Ctrl-Cs in a
    fit's first 5 s)."""
    try:
        previous = signal.signal(signal.SIGINT, _record)
    except ValueError:  # not the main thread: nothing to defer
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _unraisable(report, default=sys.unraisablehook) -> None:
    """A KeyboardInterrupt a callback could not raise is recorded (`asked()`), not printed as
    "Exception ignored in: <function _xla_gc_callback ...>" with its traceback."""
    if not isinstance(report.exc_value, KeyboardInterrupt):
        default(report)


def main() -> None:
    """Install the recording Ctrl-C handler, then run `fit.cli.main`."""
    with contextlib.suppress(ValueError):  # only the main thread may set handlers
        signal.signal(signal.SIGINT, _interrupt)
    sys.unraisablehook = _unraisable
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
