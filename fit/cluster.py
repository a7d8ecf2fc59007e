"""Ray for batches and multi-start: joining (or starting) a cluster, and preparing a worker
process for fits (the Mitsuba variant, Dr.Jit's threads, its kernel cache on this node).

Ray is imported only here and in the modules that submit tasks, never by a plain fit."""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import warnings
from collections.abc import Iterator
from typing import Any

log = logging.getLogger(__name__)

#: The variant the driver chose: workers select the same one.
VARIANT_ENV = "LAYERFIT_VARIANT"
#: Dr.Jit's kernel cache on each node ({host}: its host name). LLVM kernels are compiled for the
#: node's CPU, so nodes that share a home folder must not share one cache folder.
DEFAULT_KERNEL_CACHE = "~/.drjit/{host}"
_prepared: set[tuple] = set()


class Cancelled(Exception):
    """Ctrl-C cancelled the Ray tasks (a batch's fits, a fit's starts); the message says what."""


#: Seconds to wait for a cluster's address to answer before saying it does not.
CONNECT_TIMEOUT = 5.0


def check_address(address: str | None, where: str = "--address") -> None:
    """Refuse, before Ray starts, an address that is not one (`HOST:PORT`, `ray://HOST:PORT`,
    `auto`) or where nothing answers within `CONNECT_TIMEOUT` seconds (Ray itself waits minutes,
    printing its own log lines)."""
    from captures.errors import InputError

    if address is None or address in ("auto", "local"):
        return
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(
            f"{where} {address!r}: not a cluster address; give HOST:PORT, ray://HOST:PORT or "
            "auto (or leave it out to start Ray on this machine)"
        )
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT).close()
    except OSError as err:
        raise InputError(
            f"{where} {address}: no Ray cluster answers there ({err.strerror or err}); check the "
            "address, or leave it out to start Ray on this machine"
        ) from None


@contextlib.contextmanager
def connect(address: str | None = None, num_cpus: int | None = None) -> Iterator[None]:
    """Ray for the duration of the block: an existing connection (a caller's, a test's) is used
    as it is; else `address` joins a running cluster, or a local instance starts on this
    machine with `num_cpus` CPUs (default: all), no dashboard, and the workers' output left in
    Ray's session logs. Shut down at the end when this block started it."""
    os.environ.setdefault("RAY_DISABLE_USAGE_STATS", "1")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    address = address or os.environ.get("RAY_ADDRESS") or None
    if address is None:  # a local instance: token auth on, said explicitly (else Ray warns);
        os.environ.setdefault("RAY_AUTH_MODE", "token")  # read when Ray is first imported
    import ray

    if ray.is_initialized():
        yield
        return
    where = "--address" if os.environ.get("RAY_ADDRESS") != address else "RAY_ADDRESS"
    check_address(address, where)
    with warnings.catch_warnings():
        # Ray starts its processes by fork + exec; JAX, when loaded, warns at every fork
        warnings.filterwarnings("ignore", r"os\.fork\(\) was called", RuntimeWarning)
        try:
            ray.init(
                address=address,
                num_cpus=None if address else num_cpus,
                include_dashboard=False,
                log_to_driver=False,
                logging_level=logging.WARNING,
                configure_logging=True,
            )
        except ConnectionError as err:  # `auto` with no cluster running, a cluster gone
            from captures.errors import InputError

            first = str(err).strip().splitlines()[0] if str(err).strip() else "no answer"
            raise InputError(
                f"{where} {address}: cannot join a Ray cluster ({first}); start one, or leave "
                "it out to start Ray on this machine"
            ) from None
    try:
        yield
    finally:
        ray.shutdown()


#: The fewest threads a worker gives Dr.Jit: with one (or none), Mitsuba 3.9 never returns from
#: loading an EXR bitmap (the cup's masks, a free texture's start), and a `--starts` fit or a
#: batch task of one CPU hung there (`tests/fit/test_batch.py`).
MIN_THREADS = 2


def prepare_worker(cpus: int, variant: str | None, kernel_cache: str | None = None) -> str:
    """In a worker, before its first fit: Dr.Jit's kernel cache folder on this node (only while
    Dr.Jit is not loaded yet in this process), the Mitsuba variant with our plugins, and Dr.Jit's
    thread count = the task's CPUs, at least `MIN_THREADS`. Returns the variant."""
    from .variant import select_variant

    if (cpus, variant) in _prepared:
        return variant
    if kernel_cache and "DRJIT_CACHE_DIR" not in os.environ:
        folder = os.path.expanduser(kernel_cache.format(host=socket.gethostname()))
        try:
            os.makedirs(folder, exist_ok=True)
        except OSError as err:
            from captures.errors import InputError

            raise InputError(
                f"kernel_cache = {kernel_cache!r}: cannot make {folder} on "
                f"{socket.gethostname()} ({err.strerror or err}); give a folder path there"
            ) from None
        os.environ["DRJIT_CACHE_DIR"] = folder
    chosen = select_variant(variant)
    import drjit as dr

    import materials

    materials.register()
    dr.set_thread_count(max(cpus, MIN_THREADS))
    _prepared.add((cpus, variant))
    return chosen


def driver_variant() -> str | None:
    """The variant the driver process uses (the workers follow it)."""
    try:
        import mitsuba as mi

        return mi.variant()
    except (ImportError, AttributeError):
        return os.environ.get(VARIANT_ENV)


def one_line_error(err: Exception) -> str:
    """A Ray task's error as one line: its type and the first line of its cause."""
    text = str(getattr(err, "cause", None) or err).strip()
    return f"{type(err).__name__}: {text.splitlines()[0] if text else ''}"


def as_finished(pending: list) -> Iterator[tuple[Any, Any, str | None]]:
    """Ray tasks' outcomes in the order they finish: `(ref, result, None)`, or `(ref, None, error)`
    where the task raised or its worker died (`one_line_error`). `pending` (refs) is kept to the
    unfinished ones, for a caller that cancels them on Ctrl-C."""
    import ray

    while pending:
        ready, pending[:] = ray.wait(pending, num_returns=1)
        try:
            result, error = ray.get(ready[0]), None
        except ray.exceptions.RayError as err:
            result, error = None, one_line_error(err)
        yield ready[0], result, error
