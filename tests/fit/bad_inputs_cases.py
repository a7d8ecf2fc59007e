"""Bad-input cases' parts: a work folder's edits, the commands' arguments, an in-process run."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from captures.images import write_image
from fit.entry import run as main

ROOT = Path(__file__).resolve().parents[2]


MATERIAL = '[material]\ntype = "glaze"\npigment = [0.3, 0.3, 0.3]\nroughness = 0.1\nior = 1.5\n'


FIT = f"""capture = "cap"
{MATERIAL}[fit]
free = ["glaze.roughness"]
uncertainty_spp = 4
[[fit.phases]]
solver = "adam"
steps = 1
spp = 1
"""


OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n"


def edit(path: Path, old: str, new: str) -> None:
    """Replace the first `old` in a text file (which must hold it)."""
    text = path.read_text()
    assert old in text, (path, old)
    path.write_text(text.replace(old, new, 1))


def snapshot(folder: Path) -> dict[str, str]:
    """Every path under `folder` -> the SHA-256 of its bytes (folders: "dir")."""
    out = {}
    for path in sorted(folder.rglob("*")):
        key = str(path.relative_to(folder))
        out[key] = "dir" if path.is_dir() else hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def run(args: list, capsys) -> tuple[int, str, str]:
    """`layerfit ARGS` in this process: (exit status, stdout, stderr)."""
    with pytest.raises(SystemExit) as exit_:
        main([str(a) for a in args])
    out = capsys.readouterr()
    return exit_.value.code, out.out, out.err


# Cases: (id, mutate the work folder and return the arguments, substrings of the one error line)
Case = tuple[str, Callable[[Path], list], tuple[str, ...]]


Setup = Callable[[Path], object]


def out(rel: str) -> Callable[[Path], Path]:
    return lambda d: d / rel


def edited(rel: str, old: str, new: str, before: Setup | None = None) -> Setup:
    """A setup step: `before`, then `old` replaced by `new` in the file `rel` of the work folder."""

    def setup(d: Path) -> None:
        if before:
            before(d)
        edit(d / rel, old, new)

    return setup


def command(*args, setup: Setup | None = None) -> Callable[[Path], list]:
    """`setup`, then the arguments `args` (a callable one is called with the work folder)."""

    def make(d: Path) -> list:
        if setup:
            setup(d)
        return [a(d) if callable(a) else a for a in args]

    return make


def render_args(*extra, setup: Setup | None = None) -> Callable[[Path], list]:
    return command("render", out("render.toml"), *extra, setup=setup)


def render_cfg(old: str, new: str, *extra, setup: Setup | None = None) -> Callable[[Path], list]:
    return render_args("--out", out("o.png"), *extra, setup=edited("render.toml", old, new, setup))


def manifest(old: str, new: str, setup: Setup | None = None) -> Callable[[Path], list]:
    return inspect_args(
        out("cap"),
        "--no-silhouette",
        "--sheet",
        out("s.png"),
        setup=edited("cap/capture.toml", old, new, setup),
    )


def inspect_args(*extra, setup: Setup | None = None) -> Callable[[Path], list]:
    return command("inspect", *extra, setup=setup)


def synth_args(*extra, setup: Setup | None = None) -> Callable[[Path], list]:
    return command("synth", out("render.toml"), *extra, setup=setup)


def fit_args(*extra, setup: Setup | None = None) -> Callable[[Path], list]:
    return command("fit", out("fit.toml"), *extra, setup=setup)


def write(rel: str, data: bytes | str | None = None, folder: bool = False):
    """A setup step: write a file (or make a folder) under the work folder."""

    def setup(d: Path) -> None:
        path = d / rel
        if folder:
            path.mkdir(parents=True)
        elif isinstance(data, bytes):
            path.write_bytes(data)
        else:
            path.write_text(data or "")

    return setup


def image(rel: str, value: float, shape: tuple[int, int] = (4, 8)) -> Setup:
    """A setup step: an image of `shape` pixels, each `value`, written under the work folder."""
    return lambda d: write_image(d / rel, np.full((*shape, 3), value, np.float32))


def truncated_png(d: Path, shape=(4, 8)) -> bytes:
    """The first half of a valid noisy PNG's bytes (its header reads, its pixels do not)."""
    rng = np.random.default_rng(0)
    write_image(d / "whole.png", rng.random((*shape, 3)).astype(np.float32))
    data = (d / "whole.png").read_bytes()
    (d / "whole.png").unlink()
    return data[: len(data) // 2]


GARBAGE = b"\x89not an image at all\xff\xfe"
