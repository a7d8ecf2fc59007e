"""The exceptions of bad input: each message names the file, the field and the fix."""


class InputError(ValueError):
    """Bad user input (a config, a capture, a preset); the message names the file, the key and
    the fix, in one line."""


class CaptureError(InputError):
    """Bad capture input; the message names the file, the field and the fix."""
