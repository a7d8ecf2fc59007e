"""The `layerfit` console entry, light enough to catch a Ctrl-C from the first instant
(`fit.interrupts`), and the command line run in a process (`run`): every failure one line and
an exit status."""

from __future__ import annotations

import atexit
import contextlib
import errno
import functools
import logging
import os
import signal
import sys
from typing import NoReturn

from . import interrupts


def main() -> None:
    """The `layerfit` console script: install the recording Ctrl-C handler, then `run`."""
    interrupts.install()
    try:
        import typer  # noqa: F401  (the command line's first imports, where a Ctrl-C may land)

        from . import cli  # noqa: F401
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
        _exit(done.code)
    _exit(0)


def _exit(code) -> NoReturn:
    """Exit with `code` (SystemExit's: None, a number or a message) once the exit handlers have
    run and the streams are flushed, without the interpreter's finalisation: every file is
    written and closed by then, and the interpreter's teardown (Dr.Jit's and JAX's modules among
    what it frees) took 0.25 s of the sphere's 8 s draft (Xeon-21, 2026-12-07)."""
    if code is None:
        code = 0
    elif not isinstance(code, int):
        sys.stderr.write(f"{code}\n")
        code = 1
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


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


#: Where a path's file or folder may not be read or written by this user.
NO_PERMISSION = "permission denied; check its permissions (or choose another path)"


#: Where a path holds a name longer than the file system allows (it was an internal error).
NAME_TOO_LONG = (
    "a name in this path is longer than the file system allows (255 bytes on most); choose a "
    "shorter one"
)


def _terminate(signum, frame) -> None:
    """SIGTERM stops like Ctrl-C: partial outputs are removed (a fit keeps its checkpoint)."""
    raise KeyboardInterrupt


def run(argv: list[str] | None = None) -> None:
    """Run the command line in this process (`argv`: its arguments; exits through SystemExit):
    every failure is one line on stderr and an exit status (2 for
    bad input or usage, 130 when interrupted, 1 otherwise); `LAYERFIT_DEBUG=1` shows
    tracebacks of unexpected errors."""
    from . import console as ui

    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    logging.getLogger().handlers[0].setFormatter(ui.Plain())
    previous = None
    with contextlib.suppress(ValueError):  # only the main thread may set handlers
        previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        code = _run(argv)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    sys.exit(code)


@functools.cache
def _command():
    """The app's click command, built once (typer rebuilds it on every call otherwise)."""
    import typer

    from .cli import app

    return typer.main.get_command(app)


def _run(argv: list[str] | None) -> int:
    """Run the app; the exit status, every failure printed as one line."""
    from . import console as ui

    ui.said["interrupted"] = False
    code = _run_app(argv)
    if code == 130 and not ui.said["interrupted"]:  # typer returns 130 for a KeyboardInterrupt
        ui.say("interrupted:", "yellow", "stopped by Ctrl-C or SIGTERM")  # that left a command
    return code


def _run_app(argv: list[str] | None) -> int:
    """`_run`'s work: the app's exit status, a failure printed as one line."""
    import typer

    from . import console as ui

    try:
        code = _command().main(args=argv, prog_name="layerfit", standalone_mode=False)
    except typer.TyperException as err:  # usage: an unknown option, a value out of range
        if type(err).__name__ == "NoArgsIsHelpError":  # `layerfit` alone: the help
            err.show()
        else:
            ctx = getattr(err, "ctx", None)
            where = f"; see '{ctx.command_path} --help'" if ctx is not None else ""
            ui.say("error:", "red", f"{err.format_message().rstrip('.')}{where}")
        code = err.exit_code
    except typer.Abort:  # Ctrl-C before a command's own handling (click's)
        ui.say("interrupted:", "yellow", "stopped by Ctrl-C or SIGTERM")
        code = 130
    except KeyboardInterrupt:  # outside click's own handling (typer building the command)
        code = 130  # `_run` says so
    except Exception as err:
        if interrupts.asked():  # a Ctrl-C inside a library's import or callback, surfaced as
            return 130  # another error (drjit's import: a NameError)
        if isinstance(err, OSError) and err.errno == errno.ENAMETOOLONG:  # a path's long name
            ui.say("error:", "red", f"{err.filename}: {NAME_TOO_LONG}")
            return 2
        if isinstance(err, PermissionError) and err.filename:  # a file this user may not use
            ui.say("error:", "red", f"{err.filename}: {NO_PERMISSION}")
            return 2
        if os.environ.get("LAYERFIT_DEBUG"):
            raise
        first = (str(err).strip().splitlines() or [""])[0][:300]
        ui.say(
            "error:",
            "red",
            f"internal error ({type(err).__name__}: {first}); please report it with the "
            "command (LAYERFIT_DEBUG=1 shows the traceback)",
        )
        code = 1
    return code if isinstance(code, int) else 0
