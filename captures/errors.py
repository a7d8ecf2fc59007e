"""The one exception of bad capture or config input."""


class CaptureError(ValueError):
    """Bad capture input; the message names the file, the field and the fix."""
