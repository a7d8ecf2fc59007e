"""The one atomic writer: a file or a folder appears whole or not at all, never half-written."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from .errors import InputError, listing


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


@contextlib.contextmanager
def atomic_path(path: str | Path, folder: bool = False, replace: bool = False) -> Iterator[Path]:
    """Yield a hidden temporary path beside `path` to write into; on success it is renamed to
    `path` (replacing a file of the same kind), on any error (Ctrl-C included) it is removed.

    With `folder`, the temporary path is an empty folder (permissions as the umask allows), and
    `path` must not exist yet unless `replace` (a folder is never merged; with `replace` an
    existing one is removed only once the new one is complete).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if folder:
        if path.exists() and not replace:
            raise FileExistsError(f"{path} exists; choose a new folder (nothing was overwritten)")
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}-", suffix=".partial", dir=path.parent))
        tmp.chmod(0o777 & ~_umask())  # mkdtemp's 0700 is for secrets
    else:
        fd, name = tempfile.mkstemp(
            prefix=f".{path.stem}-", suffix=f".partial{path.suffix}", dir=path.parent
        )
        os.close(fd)
        tmp = Path(name)
        tmp.chmod(0o666 & ~_umask())  # mkstemp's 0600 is for secrets
    try:
        yield tmp
        if folder and path.exists():
            replace_folder(path, tmp)
        else:
            if not folder:  # its bytes on disk before the name points at them: a power cut
                with open(tmp, "rb") as written:  # after the rename left an empty file on
                    os.fsync(written.fileno())  # filesystems that delay allocation
            os.replace(tmp, path)
    except BaseException:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            tmp.unlink(missing_ok=True)
        raise


def write_text(path: str | Path, text: str) -> Path:
    """Write `text` (UTF-8) to `path` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def not_utf8(path: str | Path) -> str | None:
    """The path with its bytes escaped where its name is not UTF-8 text (a name the file system
    holds that Python keeps escaped: the image, mesh and JSON libraries take text), else None."""
    resolved = Path(path).resolve()
    try:
        str(resolved).encode("utf-8")
    except UnicodeEncodeError:  # shown resolved: a relative name may be UTF-8, its folder not
        return os.fsencode(resolved).decode("utf-8", "backslashreplace")
    return None


def require_utf8(path: str | Path, error=InputError) -> None:
    """Raise `error` naming `path` when its name is not UTF-8 text (`not_utf8`)."""
    shown = not_utf8(path)
    if shown is not None:
        raise error(
            f"{shown}: the path is not UTF-8 text (its bytes shown escaped), which the image "
            "and mesh readers cannot open; rename the file or folder in UTF-8"
        )


def check_output(
    path: str | Path,
    option: str,
    *,
    force: bool = False,
    inputs: Iterable[str | Path] = (),
    suffixes: tuple[str, ...] = (),
    folder: bool = False,
) -> Path:
    """Refuse, before any work, an output that cannot be written or would lose something: a
    file of another kind (a folder for a file, or a file for a folder), one of the command's
    `inputs` (or a folder holding one), an existing output without `force`, a suffix not in
    `suffixes`, or a folder where nothing can be created. Returns `path`."""
    path = Path(path)
    resolved = path.resolve()
    shown = not_utf8(path)  # the image and JSON writers and the report take text: an internal
    if shown is not None:  # error after the work
        raise InputError(
            f"{option} {shown}: the path is not UTF-8 text (its bytes shown escaped); give a "
            "path of UTF-8 text"
        )
    if suffixes and not folder and path.is_dir():  # a file's name wanted
        raise InputError(
            f"{option} {path}: is a folder; give a file's name in it (e.g. "
            f"{path / ('out' + suffixes[0])})"
        )
    if suffixes and path.suffix.lower() not in suffixes:
        raise InputError(
            f"{option} {path}: unsupported file type {path.suffix or '(none)'!r}; "
            f"use {', '.join(suffixes)}"
        )
    for item in inputs:
        source = Path(item).resolve()
        if source == resolved or (folder and source.is_relative_to(resolved)):
            raise InputError(
                f"{option} {path}: is an input of this command ({source}); inputs are never "
                "overwritten: choose another path"
            )
    if folder and Path.cwd().resolve().is_relative_to(resolved):
        raise InputError(
            f"{option} {path}: is the current folder or holds it (it would be replaced whole); "
            "give a new folder's name"
        )
    if path.exists() or path.is_symlink():
        if folder and not path.is_dir():
            raise InputError(f"{option} {path}: is a file; give a folder")
        if not folder and path.is_dir():
            raise InputError(f"{option} {path}: is a folder; give a file name")
        if not force:
            raise InputError(
                f"{option} {path}: exists; choose another path, or give --force to replace it"
            )
    parent = resolved.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"{option} {path}: {parent} is a file, not a folder; choose another path")
    # the effective user's rights (a process acting as another user is refused what it is)
    if not os.access(
        parent, os.W_OK | os.X_OK, effective_ids=os.access in os.supports_effective_ids
    ):
        raise InputError(
            f"{option} {path}: cannot write in {parent} (permission denied); choose another path"
        )
    return path


def replace_folder(path: str | Path, new: str | Path) -> None:
    """Put the finished folder `new` at `path`, moving an existing `path` aside first and
    deleting it only once `new` is in place."""
    path, new = Path(path), Path(new)
    old = None
    if path.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{path.name}-", suffix=".old", dir=path.parent))
        os.replace(path, old / path.name)
    try:
        os.replace(new, path)
    except BaseException:
        if old is not None:
            os.replace(old / path.name, path)
            old.rmdir()
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def foreign_entries(folder: str | Path, main: str | Path, extra: tuple[str, ...] = ()) -> list[str]:
    """The names in `folder` that a tool's output there did not write: anything but its main
    file `main` (a manifest, an exported material), the files that file names (names with an
    extension: a node called `clay` in a material does not make a file `clay` ours) and `extra`.
    `--force` replaces a folder whole, so an output folder holding anything else (a user's scene
    beside an exported material, a note in a capture) is refused rather than deleted."""
    folder, main = Path(folder), Path(main)
    try:
        text = main.read_text(errors="replace")
    except OSError:
        text = ""

    def named(name: str) -> bool:  # as a whole file name, not inside another ("a.exr", "data.exr")
        return re.search(rf"(?<![\w.-]){re.escape(name)}(?![\w.-])", text) is not None

    written = {p.name for p in folder.iterdir() if p.is_file() and "." in p.name and named(p.name)}
    ours = {main.name, *extra} | written
    return sorted(p.name for p in folder.iterdir() if p.name not in ours)


def refuse_foreign(
    folder: str | Path, main: str | Path, tool: str, extra: tuple[str, ...] = ()
) -> None:
    """Raise `InputError` when `folder`, which `--force` would replace whole, holds anything
    `tool`'s earlier output did not write there (`foreign_entries`)."""
    foreign = foreign_entries(folder, main, extra)
    if foreign:
        shown = listing(foreign)
        raise InputError(
            f"--out {folder}: also holds {shown}, which {tool} did not write (its "
            f"{Path(main).name} names no such file); --force replaces the whole folder: move "
            "them out or choose another path"
        )
