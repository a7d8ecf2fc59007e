"""Ctrl-C before a command takes over its handling: recorded, so that the command honours it.

The command line's imports (SciPy, scikit-image, then Mitsuba and JAX) take seconds; a Ctrl-C
there printed a traceback of the import, and one that landed in JAX's garbage-collection
callback was swallowed ("Exception ignored in: _xla_gc_callback") while the fit ran on to its
end. So the first handler (`install`) also records the request (`asked()`), which a command
checks where its own handling begins (`fit.commands.common.start`, the fit's stop handler)."""

from __future__ import annotations

import contextlib
import signal
import sys
from collections.abc import Iterator

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


def install() -> None:
    """Install the recording Ctrl-C handler and the hook that records a swallowed one."""
    with contextlib.suppress(ValueError):  # only the main thread may set handlers
        signal.signal(signal.SIGINT, _interrupt)
    sys.unraisablehook = _unraisable
