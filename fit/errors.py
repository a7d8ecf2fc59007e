"""The exception of bad configs and presets (captures have `captures.CaptureError`; both are
`captures.InputError`, which the CLI prints as one line)."""

from captures.errors import InputError


class ConfigError(InputError):
    """A config or preset is wrong; the message names the file, the key and the fix."""


class OutputError(InputError):
    """A run folder could not be written (a full disk, no permission); the message names the
    folder, what was kept and how to go on."""
