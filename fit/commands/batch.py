"""`layerfit batch`: many fits (captures x fit configs x seeds) as Ray tasks, one run folder each
and an index."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from ..errors import Stopped
from .common import Quiet, start


def batch(
    spec: Path,
    address: str | None = None,
    num_cpus: int | None = None,
    variant: str | None = None,
    progress=None,
    failed: Callable[[dict], None] = lambda entry: None,
) -> tuple[list[dict], Path]:
    """Run the batch `spec` on a local Ray instance of `num_cpus` (default: all) or the cluster
    at `address` (or `RAY_ADDRESS`). Finished fits are skipped; a failed one is reported
    (`failed(entry)`) and the others run on. Returns every fit's index entry and the index's
    HTML page."""
    from ..batch import Cancelled, load_batch, run_batch
    from ..cluster import check_address

    progress = progress or Quiet()
    the_batch = load_batch(spec)
    if address is not None:
        check_address(address)
    elif os.environ.get("RAY_ADDRESS"):
        check_address(os.environ["RAY_ADDRESS"], "RAY_ADDRESS")
    start(variant)
    task = progress.add_task(f"{len(the_batch.jobs)} fits", total=len(the_batch.jobs))

    def advance(entry: dict, done: int, total: int) -> None:
        progress.update(task, completed=done)
        if entry["status"] == "failed":
            failed(entry)

    try:
        entries = run_batch(the_batch, advance, address, num_cpus)
    except Cancelled as err:
        raise Stopped(str(err)) from None
    return entries, the_batch.out / "index.html"
