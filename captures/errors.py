"""The exceptions of bad input: each message names the file, the field and the fix."""


class InputError(ValueError):
    """Bad user input (a config, a capture, a preset); the message names the file, the key and
    the fix, in one line."""


class CaptureError(InputError):
    """Bad capture input; the message names the file, the field and the fix."""


def listing(names, limit: int = 3) -> str:
    """The first `limit` of `names` for a message, and how many more there are."""
    names = [str(n) for n in names]
    more = len(names) - limit
    return ", ".join(names[:limit]) + (f" and {more} more" if more > 0 else "")
