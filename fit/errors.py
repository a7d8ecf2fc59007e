"""The exception of bad configs and presets (captures have `captures.CaptureError`; both are
`captures.InputError`, which the CLI prints as one line)."""

from captures.errors import InputError


class ConfigError(InputError):
    """A config or preset is wrong; the message names the file, the key and the fix."""
