"""Run the `layerfit` CLI (`python -m fit`) in a subprocess, as a user would."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def run_cli(*args, env: dict | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """`layerfit ARGS` from the project root, wide terminal (no wrapped lines), captured text."""
    return subprocess.run(
        [sys.executable, "-m", "fit", *map(str, args)],
        capture_output=True,
        text=True,
        check=False,
        cwd=ROOT,
        timeout=timeout,
        env={**os.environ, "COLUMNS": "200", **(env or {})},
    )
