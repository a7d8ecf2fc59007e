"""The one atomic writer: a file or a folder appears whole or not at all, never half-written."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


@contextlib.contextmanager
def atomic_path(path: str | Path, folder: bool = False) -> Iterator[Path]:
    """Yield a hidden temporary path beside `path` to write into; on success it is renamed to
    `path` (replacing a file of the same kind), on any error (Ctrl-C included) it is removed.

    With `folder`, the temporary path is an empty folder (permissions as the umask allows), and
    `path` must not exist yet (a folder is never merged or replaced).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if folder:
        if path.exists():
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
