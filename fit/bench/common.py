"""What the benchmarks share: the table they return, the machine line under it, the progress
ticker, and resumable results files keyed by the fitting code's constants."""

from __future__ import annotations

import json
import platform
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from captures.errors import InputError

#: The scene the speed tables render (relative to the working directory: the repository's root).
DEFAULT_SCENE = Path("configs/glazed-sphere.toml")
CUP_SCENE = Path("configs/cup.toml")


@dataclass
class Table:
    title: str
    columns: list[str]
    rows: list[list[str]]
    notes: list[str]

    def markdown(self) -> str:
        lines = [f"### {self.title}", "", "| " + " | ".join(self.columns) + " |"]
        lines.append("|" + "---|" * len(self.columns))
        lines += ["| " + " | ".join(row) + " |" for row in self.rows]
        return "\n".join(lines + [""] + [f"- {n}" for n in self.notes]) + "\n"

    def rich(self):
        from rich.table import Table as RichTable

        table = RichTable(title=self.title, caption="\n".join(self.notes))
        for column in self.columns:
            table.add_column(column)
        for row in self.rows:
            table.add_row(*row)
        return table


def machine(cpuinfo: str | None = None) -> str:
    """The machine a table was measured on: the CPU's model name, and where /proc/cpuinfo
    says, its family, model and widest vector unit (two VMs both named "AMD EPYC" ran this
    bench's fits 4x apart: CPU family 26 with AVX-512 and an older one), the core count, the
    Mitsuba variant and version."""
    import os

    import mitsuba as mi

    cpu, details = platform.processor() or platform.machine(), {}
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    for line in cpuinfo.splitlines():  # the first processor's lines
        key, _, value = (part.strip() for part in line.partition(":"))
        if not key:  # a blank line ends a processor's block
            if details:
                break
            continue
        details.setdefault(key, value)
    cpu = details.get("model name", cpu)
    flags = set(details.get("flags", "").split())
    extra = [f"{name} {details[key]}" for key, name in CPU_FIELDS if key in details]
    extra += [name for flag, name in SIMD if flag in flags][:1]
    cpu = f"{cpu} ({', '.join(extra)})" if extra else cpu
    return f"{cpu}, {os.cpu_count()} cores, {mi.variant()}, mitsuba {mi.__version__}"


#: The /proc/cpuinfo fields a machine line names, and how.
CPU_FIELDS = (("cpu family", "family"), ("model", "model"))
#: The vector units Dr.Jit's LLVM backend can use, widest first (/proc/cpuinfo flag, name).
SIMD = (("avx512f", "AVX-512"), ("avx2", "AVX2"), ("avx", "AVX"), ("sse4_2", "SSE4.2"))


def ticker(progress, label: str, total: int) -> Callable[[], None]:
    """A task of `total` steps on `progress` (a rich `Progress`, or None: no display), and the
    call that advances it by one."""
    task = progress.add_task(label, total=total) if progress else None
    return (lambda: progress.advance(task)) if progress else (lambda: None)


def short(schedule, steps: int = 1) -> tuple:
    """`schedule` with `steps` steps a phase: a warm-up that compiles every kernel it needs."""
    return tuple(p.model_copy(update={"steps": steps}) for p in schedule)


def legend_once(ax) -> None:
    """A legend with one entry per label (each run's lines repeat the method's label)."""
    handles, labels = ax.get_legend_handles_labels()
    unique = dict(zip(labels, handles, strict=True))
    ax.legend(unique.values(), unique.keys())


# The fitting code's constants in a results file's setting -----------------------------------------

#: The modules whose constants decide a default fit's answer besides its schedule (`gn`'s
#: curvature caution, the uncertainty's thresholds, the BSDFs' sampling and bounds).
FIT_MODULES = (
    "fit.solvers.adam",
    "fit.solvers.gn",
    "fit.solvers.problem",
    "fit.solvers.schedule",
    "fit.solvers.uncertainty",
    "materials.glaze",
    "materials.layered",
    "materials.microfacet",
    "materials.oren_nayar",
    "materials.params",
)


def _canonical(value):
    """`value` as JSON-able data that does not depend on the process (sets sorted: their order
    follows the string hash's per-process seed); objects without such a form as their repr,
    None where that holds an address."""
    import dataclasses

    from pydantic import BaseModel

    if isinstance(value, BaseModel):
        value = value.model_dump()
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, set | frozenset):
        return sorted((_canonical(v) for v in value), key=repr)
    if isinstance(value, list | tuple):
        return [_canonical(v) for v in value]
    if value is None or isinstance(value, bool | int | float | str):
        return value
    text = repr(value)
    return None if " at 0x" in text else text


def constants_digest(modules=FIT_MODULES) -> str:
    """A short hash of the upper-case module constants of `modules`: a changed constant
    (`gn.CAUTION`) changes it, and it is the same in every process."""
    import hashlib
    import importlib
    import inspect

    table = {}
    for name in modules:
        module = importlib.import_module(name)
        for key, value in vars(module).items():
            if key.lstrip("_").isupper() and not (inspect.ismodule(value) or callable(value)):
                table[f"{name}.{key}"] = _canonical(value)
    text = json.dumps(table, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def schedule_key(schedule) -> list[str]:
    """A schedule as a resumable results file's setting records it: each phase's solver, spp,
    resolution, steps and options, and the digest of the fitting code's constants
    (`constants_digest`): a changed option or constant makes earlier results another setting
    (until 2026-12-01 a changed `gn.CAUTION` silently kept the old default runs)."""
    return [f"{p.describe()} x {p.steps} {p.options!r}" for p in schedule] + [
        f"constants {constants_digest()}"
    ]


# Resumable results files --------------------------------------------------------------------------


def resumed(
    results: Path,
    setting: dict,
    entries: str,
    other: str,
    replace: bool,
    required: tuple[str, ...] = ("seconds",),
) -> dict:
    """The finished entries of a resumable results file (JSON: its `setting` and `entries`,
    each entry a table with the `required` keys); none when it does not exist or with
    `replace`. A file that is not such JSON, or holds `other` (another setting), is refused:
    nothing a user has is overwritten."""
    if not results.exists() or replace:
        return {}
    try:
        saved = json.loads(results.read_text())
        same = saved.get("setting") == json.loads(json.dumps(setting))
    except (OSError, ValueError, AttributeError):
        raise InputError(f"{results}: not a bench results file; give another --results") from None
    if not same:
        raise InputError(
            f"{results}: holds {other}; give another --results, or delete it to start again"
        )
    done = saved.get(entries, {})
    if not isinstance(done, dict):
        raise InputError(
            f"{results}: {entries}: not a table of finished entries; delete the file or give "
            "another --results"
        )
    for name, entry in done.items():
        missing = [k for k in required if not isinstance(entry, dict) or k not in entry]
        if missing:
            raise InputError(
                f"{results}: {entries}[{name!r}]: no {missing[0]}; delete the file or give "
                "another --results"
            )
    return done


def save(results: Path, setting: dict, entries: str, done: dict) -> None:
    """Rewrite a resumable results file (atomically) with the `done` entries so far."""
    from captures.files import write_text

    write_text(results, json.dumps({"setting": setting, entries: done}, indent=1))


def complete(
    results: Path,
    setting: dict,
    entries: str,
    done: dict,
    jobs: dict,
    progress,
    label: str,
    stale=None,
) -> dict:
    """Run each of `jobs` (name: a call that returns its entry) that `done` lacks, or holds
    stale (`stale(name, entry)` true), rewriting `results` after each (a stopped run resumes
    there); `done`, completed."""
    advance = ticker(progress, label, len(jobs))
    for name, job in jobs.items():
        if name not in done or (stale is not None and stale(name, done[name])):
            done[name] = job()
            save(results, setting, entries, done)
        advance()
    return done
