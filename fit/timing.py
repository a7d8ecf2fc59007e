"""Where a command's time goes: named parts timed into the current recording (`recording`), which
`layerfit fit` writes into its summary (`timings_s`) and `layerfit bench --only command` tables.
Outside a recording (a Ray worker, a call from Python) timing a part costs one clock read."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from contextvars import ContextVar

_current: ContextVar[dict[str, float] | None] = ContextVar("layerfit_timings", default=None)


@contextlib.contextmanager
def recording() -> Iterator[dict[str, float]]:
    """Inside, `timed` parts add their seconds to the dict yielded (in the order first met)."""
    parts: dict[str, float] = {}
    token = _current.set(parts)
    try:
        yield parts
    finally:
        _current.reset(token)


def add(part: str, seconds: float) -> None:
    """Add `seconds` to `part` of the current recording (none: nothing)."""
    parts = _current.get()
    if parts is not None:
        parts[part] = parts.get(part, 0.0) + seconds


@contextlib.contextmanager
def timed(part: str) -> Iterator[None]:
    """The wall time inside, added to `part` of the current recording (also when it raises)."""
    began = time.perf_counter()
    try:
        yield
    finally:
        add(part, time.perf_counter() - began)


def recorded() -> dict[str, float]:
    """A copy of the current recording's parts so far (none: empty)."""
    return dict(_current.get() or {})
