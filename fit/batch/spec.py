"""The batch spec (TOML): which fits to run (captures x fit configs x seeds), where and on how
many CPUs each; loaded into a list of `Job`s, one run folder each."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

from pydantic import Field

from captures.errors import listing
from captures.files import check_output
from captures.model import ExistingPath, PositiveInt, StrictModel, expect_kind, parse_model

from ..cluster import DEFAULT_KERNEL_CACHE
from ..errors import ConfigError
from ..limits import MAX_SEED
from ..material import read_toml


class BatchSpec(StrictModel):
    configs: list[ExistingPath] = Field(min_length=1)
    """Fit configs (TOML), relative to the spec; each fit starts from its config's material."""
    captures: list[ExistingPath] = Field(default_factory=list)
    """Captures that replace each config's own (empty: every config fits its own capture)."""
    seeds: list[Annotated[int, Field(ge=0, le=MAX_SEED, strict=True)]] = Field(default_factory=list)
    """Seeds that replace each config's `fit.seed` (empty: the config's seed)."""
    out: Path = Path("out/batch")
    """The batch folder, relative to the spec: one run folder per fit and the index."""
    cpus_per_fit: PositiveInt = 1
    """CPUs (Ray resources and Dr.Jit threads) each fit holds."""
    kernel_cache: str = DEFAULT_KERNEL_CACHE
    """Dr.Jit's kernel cache folder on each node ({host}: the node's host name; LLVM kernels are
    compiled for the node's CPU, so nodes sharing a home folder must not share one)."""


@dataclass(frozen=True)
class Job:
    """One fit of a batch: its name (the run folder's), config, capture (None: the config's own),
    seed (None: the config's) and run folder."""

    name: str
    config: Path
    capture: Path | None
    seed: int | None
    out: Path


@dataclass(frozen=True)
class Batch:
    """A loaded spec: its file, settings and jobs."""

    path: Path
    spec: BatchSpec
    jobs: list[Job]

    @property
    def out(self) -> Path:
        return (self.path.parent / self.spec.out).resolve()


def capture_name(path: Path) -> str:
    """A capture's short name: its folder's where a `capture.toml` or a peer `scene.json` names
    it, a manifest's own stem otherwise (`caps/bowl.toml` and `caps/vase.toml` shared `caps`)."""
    if not path.is_file():
        return path.name
    return path.parent.name if path.name in ("capture.toml", "scene.json") else path.stem


def _job_text(config: Path, capture: Path | None) -> str:
    return str(config) if capture is None else f"{config} on {capture}"


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-") or "x"


def load_batch(path: str | Path) -> Batch:
    """A batch spec from its file; a one-line `InputError` naming the file and key."""
    path = Path(path)
    doc = read_toml(path)
    expect_kind(
        doc,
        path,
        "a batch spec",
        'a spec lists configs = ["fit.toml", ...] (see layerfit batch --help and README, Batches)',
        ConfigError,
    )
    spec = parse_model(BatchSpec, doc, path)
    for key in ("configs", "captures", "seeds"):
        items = [str(x) if key == "seeds" else Path(x).resolve() for x in getattr(spec, key)]
        twice = next((x for i, x in enumerate(items) if x in items[:i]), None)
        if twice is not None:
            raise ConfigError(f"{path}: {key}: {twice} is listed twice; list each once")
    try:
        spec.kernel_cache.format(host="node")
    except (KeyError, IndexError, ValueError, AttributeError, TypeError):
        raise ConfigError(
            f"{path}: kernel_cache = {spec.kernel_cache!r}: only {{host}} may be filled in "
            "(the node's host name); remove the other braces"
        ) from None
    if "\0" in str(spec.out):
        raise ConfigError(f"{path}: out = {str(spec.out)!r} holds a NUL character; give a folder")
    out = (path.parent / spec.out).resolve()
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{path}: out = {str(spec.out)!r} is a file; give a folder")
    # where the index (written first) cannot be made: under a file, or in a read-only folder
    check_output(out / INDEX_FILES[0], f"{path}: out = {str(spec.out)!r}:", force=True)
    jobs, names = [], {}
    for config in spec.configs:
        for capture in spec.captures or [None]:
            for seed in spec.seeds or [None]:
                parts = [config.stem]
                if capture is not None:
                    parts.append(capture_name(capture))
                if seed is not None:
                    parts.append(f"seed{seed}")
                name = _slug("__".join(parts))
                if name in names:
                    raise ConfigError(
                        f"{path}: two fits would share the run folder {name!r} ({names[name]} "
                        f"and {_job_text(config, capture)}); give configs and captures distinct "
                        "names"
                    )
                names[name] = _job_text(config, capture)
                jobs.append(Job(name, config, capture, seed, out / name))
    _check_out(path, spec, out, set(names))
    _check_configs(path, spec)
    _check_captures(path, spec)
    return Batch(path, spec, jobs)


def _check_captures(path: Path, spec: BatchSpec) -> None:
    """Each capture's path, kind and syntax (no image read: each fit reads its own), so a
    capture.toml with a TOML error, or a fit config given as a capture, stops the batch before
    Ray starts, by name (it was that fit's failure after the others had run)."""
    from captures.errors import InputError
    from captures.open import check_capture

    for i, capture in enumerate(spec.captures):
        try:
            check_capture(capture)
        except InputError as err:
            raise ConfigError(f"{path}: captures[{i}]: {err}") from None


def _check_configs(path: Path, spec: BatchSpec) -> None:
    """Each config read as its fits will read it (with the first of the spec's captures), so a
    mistake in one (a phase's spp over the limit, an unknown key) stops the batch before Ray
    starts, by name (it was each fit's failure, seen in the index after the batch)."""
    from captures.errors import InputError

    from ..config import load_fit_config

    for i, config in enumerate(spec.configs):
        try:
            load_fit_config(config, spec.captures[0] if spec.captures else None)
        except InputError as err:
            raise ConfigError(f"{path}: configs[{i}]: {err}") from None


#: What a batch folder holds besides its run folders.
INDEX_FILES = ("index.json", "index.csv", "index.html")


def _check_out(path: Path, spec: BatchSpec, out: Path, runs: set[str]) -> None:
    """Refuse a batch folder that holds a user's files (its index would overwrite theirs) or
    another spec's batch (their indexes would replace each other)."""
    if not out.is_dir():
        return
    index = out / "index.json"
    if index.is_file():
        try:
            other = json.loads(index.read_text(encoding="utf-8")).get("spec")
        except (OSError, ValueError, AttributeError):
            other = None
        if other is None or Path(other).resolve() != path.resolve():
            raise ConfigError(
                f"{path}: out = {str(spec.out)!r} holds another batch's index ("
                f"{other or 'unreadable'}); give this batch its own out folder"
            )
    ours = INDEX_FILES if index.is_file() else ()  # an index of this spec (checked above)
    foreign = sorted(
        p.name
        for p in out.iterdir()
        if not p.name.startswith(".")
        and p.name not in ours
        and not (p.is_dir() and (p.name in runs or _is_run(p)))
    )
    if foreign:
        shown = listing(foreign)
        raise ConfigError(
            f"{path}: out = {str(spec.out)!r} holds files that are not this batch's ({shown}); "
            "give the batch a new or its own out folder"
        )


def _is_run(folder: Path) -> bool:
    """A run folder `layerfit fit` wrote (a batch's earlier fits whose config left the spec)."""
    return any((folder / n).is_file() for n in ("summary.json", "checkpoint.npz"))
