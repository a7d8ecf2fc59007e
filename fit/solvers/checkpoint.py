"""Checkpoints of a running schedule: the solver's state saved atomically every ~30 s of work, so
that a killed fit resumes losing at most one interval.

A checkpoint is one `.npz` file: a JSON `meta` entry (phase, step, history, finished phases'
reports, seeds follow from them) and the arrays (the vector, the optimiser's state leaves, the
averaged iterates). Adam saves within its phase; LM and BFGS (one optimistix call each) at their
ends.
"""

from __future__ import annotations

import io
import json
import logging
import os
import time
import zipfile
from pathlib import Path

import numpy as np

from captures.errors import InputError
from captures.files import atomic_path

log = logging.getLogger(__name__)

#: Seconds of work between checkpoints (`LAYERFIT_CHECKPOINT_SECONDS` overrides, for tests).
INTERVAL = 30.0


class Checkpoint:
    """Where and how often a schedule's state is saved; `offer` each step, `flush` on demand."""

    def __init__(self, path: Path, interval: float | None = None):
        self.path = Path(path)
        env = os.environ.get("LAYERFIT_CHECKPOINT_SECONDS")
        self.interval = interval if interval is not None else float(env or INTERVAL)
        self.latest: dict | None = None
        self.stop = False  # set (by a Ctrl-C handler) to stop at the next step
        #: What fit this is (JSON values: its free keys, views, phases, seed), saved with every
        #: state; a resume compares it (`fit.commands.fit.check_resume`).
        self.identity: dict | None = None
        #: Seconds of work before this process (a resumed run's earlier processes), and when this
        #: one began: each state records their sum (`elapsed_s`), so a resumed run's wall time
        #: is the whole run's.
        self.elapsed_before = 0.0
        self.began = time.monotonic()
        self._last = time.monotonic()
        self._unsaved = False  # the last write failed (warned once until one succeeds)

    def offer(self, state: dict) -> None:
        """Remember `state` (it may hold references the caller keeps changing: it is converted
        only when written) as the latest; write it when an interval has passed. Raises
        `KeyboardInterrupt` here, between steps, once `stop` is set."""
        self.latest = state
        if time.monotonic() - self._last >= self.interval:
            self.flush()
        if self.stop:
            raise KeyboardInterrupt

    def flush(self) -> None:
        """Write the latest state now (a reader never sees half a file)."""
        if self.latest is None:
            return
        meta, arrays = {}, {}
        state = dict(self.latest)
        for key in ("history", "tail", "tail_gradients"):  # live lists, possibly appended to
            if f"n_{key}" in state:
                state[key] = state[key][: state.pop(f"n_{key}")]
        for key, value in state.items():
            if key == "leaves":
                arrays |= {f"leaf_{i}": np.asarray(v) for i, v in enumerate(value)}
                meta["n_leaves"] = len(value)
            elif key in ("tail", "tail_gradients"):  # per averaged step: u (and its gradient)
                size = np.size(state["u"]) * (1 if key == "tail" else 2)
                arrays[key] = np.asarray(value, np.float32).reshape(len(value), size)
            elif hasattr(value, "shape"):  # numpy or JAX arrays
                arrays[key] = np.asarray(value)
            else:
                meta[key] = value
        if self.identity is not None:
            meta["identity"] = self.identity
        meta["elapsed_s"] = self.elapsed()
        buffer = io.BytesIO()
        np.savez(buffer, meta=np.array(json.dumps(meta)), **arrays)
        self._last = time.monotonic()
        try:
            with atomic_path(self.path) as tmp:
                tmp.write_bytes(buffer.getvalue())
        except OSError as err:  # a full disk: the fit goes on (it is only lost work if killed)
            if not self._unsaved:
                log.warning(
                    "%s: could not save the checkpoint (%s); the fit goes on, and a --resume "
                    "would start from the last one saved",
                    self.path,
                    err.strerror or err,
                )
            self._unsaved = True
        else:
            self._unsaved = False

    @property
    def unsaved(self) -> bool:
        """Whether the latest write failed (the file on disk, if any, is an earlier state)."""
        return self._unsaved

    def elapsed(self) -> float:
        """Seconds of work on this run so far, earlier processes included."""
        return self.elapsed_before + time.monotonic() - self.began

    def load(self) -> dict | None:
        """The saved state, or None when there is no checkpoint."""
        if not self.path.exists():
            return None
        try:
            with np.load(self.path) as data:
                state = json.loads(str(data["meta"]))
                n = state.pop("n_leaves", None)
                for key in data.files:
                    if key != "meta" and not key.startswith("leaf_"):
                        state[key] = data[key]
                if n is not None:
                    state["leaves"] = [data[f"leaf_{i}"] for i in range(n)]
        except (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile) as err:
            raise InputError(
                f"{self.path}: unreadable checkpoint ({type(err).__name__}: "
                f"{str(err).splitlines()[0] if str(err) else 'empty or cut short'}); run without "
                "--resume (and with --force) to start again"
            ) from None
        bad = [
            key
            for key in ("u", "u_phase")
            if key in state and not np.all(np.isfinite(np.asarray(state[key], np.float64)))
        ]
        if bad:
            raise InputError(
                f"{self.path}: its {' and '.join(bad)} hold non-finite values (not a state a fit "
                "saves); run without --resume (and with --force) to start again"
            )
        return state

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)
