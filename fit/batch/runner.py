"""Running a batch: each fit a Ray task in a worker process, into its run folder, and the batch
index (JSON, CSV and an HTML page linking every report) rewritten as each fit ends.

A fit whose run folder holds the `summary.json` of a finished run (and no checkpoint) of what its
config still asks for is skipped, so a killed or interrupted batch continues where it stopped; a
fit killed mid-way resumes from its checkpoint.
A fit that fails is reported with its one-line error; the others run on."""

from __future__ import annotations

import contextlib
import csv
import datetime
import html
import io
import json
import logging
import math
import os
import resource
import socket
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from captures.errors import InputError
from captures.files import write_text

from ..cluster import Cancelled, as_finished, connect, driver_variant, prepare_worker
from .spec import Batch, Job

log = logging.getLogger(__name__)

#: The index's columns (CSV order; the JSON has them and the scalar fitted values).
COLUMNS = (
    "name",
    "status",
    "config",
    "capture",
    "seed",
    "loss",
    "max_abs_error",
    "warnings",
    "wall_time_s",
    "max_rss_mb",
    "host",
    "error",
    "run_folder",
)
#: Seconds cancelled fits get to save their checkpoint after Ctrl-C before Ray shuts down.
CANCEL_GRACE_S = 20.0


def finished(out: Path, job: Job | None = None) -> dict | None:
    """The summary of a finished fit in run folder `out`, else None. A fit writes its summary
    after its other files and removes its checkpoint last: a summary beside a checkpoint, or
    of an interrupted run, is not finished; nor is one that is not a summary, or (given the
    `job`) one of another config, capture or seed (the fit runs again and replaces it)."""
    if (out / "checkpoint.npz").exists():
        return None
    try:
        summary = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(summary, dict) or summary.get("interrupted", True) is not False:
        return None
    shapes = (summary.get("values"), summary.get("error", {}))
    if not all(isinstance(part, dict) for part in shapes):
        return None
    if job is not None and not _same_fit(summary, job):
        return None
    return summary


def _same_fit(summary: dict, job: Job) -> bool:
    """Whether a finished summary is the fit `job` asks for: its config file and capture, and
    what the config asks for now (`config_identity`: settings, seed, starting material)."""
    from ..config import config_identity, load_fit_config

    try:
        config = Path(str(summary.get("config"))).resolve()
        if config != Path(job.config).resolve():
            return False
        if (
            job.capture is not None
            and Path(str(summary.get("capture"))).resolve() != Path(job.capture).resolve()
        ):
            return False
        # with the job's capture: a template config's own capture need not exist
        cfg = load_fit_config(job.config, job.capture, job.seed)
        if "config_identity" in summary:  # the config edited since: the fit runs again
            return summary["config_identity"] == config_identity(cfg)
        return summary.get("seed") == cfg.seed  # a summary written before 2026-12-02
    except (OSError, ValueError, TypeError, InputError):
        return False


def fit_job(job: Job, cpus: int, variant: str | None, kernel_cache: str) -> dict:
    """In a worker: run one fit into its run folder (resuming from its checkpoint when one is
    there); its index entry, with the one-line error when it failed."""
    began = time.perf_counter()
    entry = {"host": socket.gethostname(), "pid": os.getpid()}
    try:
        prepare_worker(cpus, variant, kernel_cache)
        from ..commands.fit import run_fit
        from ..commands.prepare import check_output, check_resume, prepare
        from ..commands.run_folder import owned
        from ..config import load_fit_config

        cfg = load_fit_config(job.config, job.capture, job.seed)
        with owned(job.out):  # a fit of its own into the folder is refused, and waits for none
            resume = _check_run_folder(job.out)
            prepared = prepare(cfg)
            if resume and cfg.starts > 1:  # the config became a multi-start: no checkpoint
                log.warning("fit %s starts again: a multi-start keeps no checkpoint", job.name)
                resume = False
            elif resume:
                try:
                    check_resume(prepared, cfg, job.out)
                except InputError as err:  # the config changed since: its checkpoint is stale
                    log.warning("fit %s starts again: %s", job.name, err)
                    resume = False
            check_output(job.out, cfg, resume, force=True)  # a failed run's leftovers go
            summary = run_fit(cfg, job.out, resume=resume, prepared=prepared)
        entry |= summary_entry(summary) | {"status": "done"}
    except Exception as err:
        message = str(err).strip().splitlines()[0] if str(err).strip() else ""
        entry |= {"status": "failed", "error": f"{type(err).__name__}: {message}"}
        log.exception("fit %s failed", job.name)
        if job.out.is_dir() and not any(job.out.iterdir()):  # no empty folder left behind
            job.out.rmdir()
    entry["wall_time_s"] = entry.get("wall_time_s") or time.perf_counter() - began
    entry["max_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return entry


def _check_run_folder(out: Path) -> bool:
    """Whether a batch fit resumes from `out`'s checkpoint; a folder holding other files, or an
    unreadable checkpoint, is an error saying what to do in a batch (which has no --force)."""
    from ..solvers import Checkpoint

    path = out / "checkpoint.npz"
    if path.exists():
        try:
            Checkpoint(path).load()
        except InputError:
            raise InputError(
                f"{path}: unreadable, or not a fit's checkpoint; delete it to run this fit again"
            ) from None
        return True
    from ..commands.run_folder import LOCK

    runs = ("summary.json", "checkpoint.npz")
    names = sorted(p.name for p in out.iterdir() if p.name != LOCK)[:3] if out.is_dir() else []
    if names and not any((out / n).is_file() for n in runs):  # the lock: this fit's own
        raise InputError(
            f"run folder {out} holds files that are not a run's ({', '.join(names)}); move them "
            "away, or give the batch another out folder"
        )
    return False


def summary_entry(summary: dict) -> dict:
    """What the index keeps of a fit's summary: loss, largest error vs the truth, the fit's
    warnings (parameters poorly determined or ended at a bound: a fit to look at before its
    numbers), wall time and the fitted values of at most 3 components (with the best start's
    spread when multi-start)."""
    errors = [abs(e) for v in summary.get("error", {}).values() for e in np.ravel(v)]
    warnings = [f"poorly determined: {key}" for key in summary.get("poorly_determined") or ()]
    warnings += [
        f"at its {b['bound']} bound: {b['parameter']}" for b in summary.get("at_bounds") or ()
    ]
    entry = {
        "loss": summary.get("loss"),
        "max_abs_error": max(errors) if errors else None,
        "warnings": "; ".join(warnings),
        "wall_time_s": summary.get("wall_time_s"),
        "values": {k: v for k, v in summary.get("values", {}).items() if np.size(v) <= 3},
    }
    if summary.get("seed") is not None:  # the config's own seed, where the spec gave none
        entry["seed"] = summary["seed"]
    if "starts" in summary:
        entry["starts"] = [{"loss": s["loss"], "best": s["best"]} for s in summary["starts"]]
    return entry


def run_batch(
    batch: Batch,
    progress: Callable[[dict, int, int], None] | None = None,
    address: str | None = None,
    num_cpus: int | None = None,
) -> list[dict]:
    """Run `batch`'s fits not finished yet on Ray (joining `address`, else a local instance of
    `num_cpus` CPUs); returns the index entries (also written to the batch folder).
    `progress(entry, done, total)` as each fit ends (skipped ones first). Ctrl-C cancels the
    running fits (each saves its checkpoint when it can), writes the index and raises
    `Cancelled`."""
    entries = {job.name: _base(batch, job) for job in batch.jobs}
    todo = []
    for job in batch.jobs:
        summary = finished(job.out, job)
        if summary is None:
            todo.append(job)
        else:
            entries[job.name] |= summary_entry(summary) | {"status": "skipped"}
    total, done = len(batch.jobs), len(batch.jobs) - len(todo)
    write_index(batch, list(entries.values()))
    if progress:
        for job in batch.jobs:
            if entries[job.name]["status"] == "skipped":
                progress(entries[job.name], done, total)
    if not todo:
        return list(entries.values())
    cpus = batch.spec.cpus_per_fit
    with connect(address, num_cpus):  # before Ray's import: its settings are read then
        import ray

        largest = max((n["Resources"].get("CPU", 0) for n in ray.nodes() if n["Alive"]), default=0)
        if cpus > largest:  # Ray would wait for such a node forever
            raise InputError(
                f"{batch.path}: cpus_per_fit = {cpus}: no node of this Ray cluster has that many "
                f"CPUs (the largest: {largest:g}); lower it or give --num-cpus"
            )
        task = ray.remote(max_retries=0)(fit_job).options(num_cpus=cpus)
        variant = driver_variant()
        refs = {task.remote(job, cpus, variant, batch.spec.kernel_cache): job.name for job in todo}
        for name in refs.values():
            entries[name]["status"] = "submitted"
        write_index(batch, list(entries.values()))
        pending = list(refs)
        try:
            for ref, entry, error in as_finished(pending):
                name = refs[ref]
                if error is None:
                    entries[name] |= entry
                else:  # the worker died (crash, memory)
                    entries[name] |= {"status": "failed", "error": error}
                done += 1
                write_index(batch, list(entries.values()))
                if progress:
                    progress(entries[name], done, total)
        except KeyboardInterrupt:
            for ref in pending:
                ray.cancel(ref)  # a KeyboardInterrupt in the fit: it saves its checkpoint
            ended, _ = ray.wait(pending, num_returns=len(pending), timeout=CANCEL_GRACE_S)
            for ref in pending:
                entries[refs[ref]]["status"] = "cancelled"
                if ref in ended:  # a fit may have finished meanwhile
                    with contextlib.suppress(ray.exceptions.RayError):
                        entry = ray.get(ref)
                        if entry["status"] == "done":
                            entries[refs[ref]] |= entry
            write_index(batch, list(entries.values()))
            raise Cancelled(
                f"cancelled {len(pending)} unfinished fit(s); the index is in {batch.out}; run the "
                "same command again to continue"
            ) from None
    return list(entries.values())


def _base(batch: Batch, job: Job) -> dict:
    return {
        "name": job.name,
        "status": "pending",
        "config": str(job.config),
        "capture": str(job.capture) if job.capture else "",
        "seed": job.seed,
        "run_folder": os.path.relpath(job.out, batch.out),
    }


def write_index(batch: Batch, entries: list[dict]) -> list[Path]:
    """`index.json`, `index.csv` and `index.html` in the batch folder, each written atomically."""
    out = batch.out
    stamp = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    counts = {s: sum(e["status"] == s for e in entries) for s in _STATUSES}
    # the spec's absolute path: a later run from another folder recognises its own index
    doc = {"spec": str(batch.path.resolve()), "updated": stamp, "counts": counts, "fits": entries}
    paths = [
        write_text(out / "index.json", json.dumps(_finite(doc), indent=2, allow_nan=False)),
        write_text(out / "index.csv", _csv(entries)),
        write_text(out / "index.html", _html(batch, entries, counts, stamp)),
    ]
    return paths


_STATUSES = ("done", "skipped", "failed", "cancelled", "submitted", "pending")


def _csv(entries: list[dict]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, COLUMNS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for entry in entries:
        writer.writerow({k: _cell(entry.get(k)) for k in COLUMNS})
    return buffer.getvalue()


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}" if math.isfinite(value) else ""
    return str(value)


def _html(batch: Batch, entries: list[dict], counts: dict, stamp: str) -> str:
    head = "".join(f"<th>{c}</th>" for c in COLUMNS if c != "run_folder") + "<th>report</th>"
    rows = []
    for entry in entries:
        cells = "".join(
            f"<td>{html.escape(_cell(entry.get(c)))}</td>" for c in COLUMNS if c != "run_folder"
        )
        report = Path(entry["run_folder"]) / "report.html"
        link = (
            f'<a href="{html.escape(report.as_posix())}">report</a>'
            if (batch.out / report).exists()
            else "-"
        )
        rows.append(f'<tr class="{entry["status"]}">{cells}<td>{link}</td></tr>')
    summary = ", ".join(f"{n} {s}" for s, n in counts.items() if n)
    return (
        "<!doctype html><html><head><meta charset='utf-8'>"
        f"<title>batch {html.escape(batch.path.name)}</title><style>"
        "body{font:14px sans-serif;margin:2em}table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:3px 8px;text-align:left}"
        ".failed{background:#fdd}.cancelled,.submitted,.pending{color:#888}</style></head><body>"
        f"<h1>batch {html.escape(str(batch.path))}</h1><p>{summary} (updated {stamp})</p>"
        f"<table><tr>{head}</tr>{''.join(rows)}</table></body></html>\n"
    )


def _finite(value):
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, np.generic):
        return value.item()
    return value
