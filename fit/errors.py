"""The exception of bad configs and presets (captures have `captures.CaptureError`; both are
`captures.InputError`, which the CLI prints as one line)."""

from captures.errors import InputError


class ConfigError(InputError):
    """A config or preset is wrong; the message names the file, the key and the fix."""


class OutputError(InputError):
    """A run folder could not be written (a full disk, no permission); the message names the
    folder, what was kept and how to go on."""


class Stopped(Exception):
    """A command stopped by Ctrl-C or SIGTERM; its text says what it left (the command line
    prints it and exits 130). `unwritten`: what could not be written on the way out (a full
    disk), if anything."""

    def __init__(self, what: str, unwritten: str | None = None):
        super().__init__(what)
        self.unwritten = unwritten
