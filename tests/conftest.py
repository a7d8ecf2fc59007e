"""Session setup: one Mitsuba variant, the plugins registered, and the shared test data."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def pytest_configure(config):
    from fit.variant import BackendError, select_variant

    try:
        select_variant()
    except BackendError as err:  # one line, never an LLVM crash dump
        pytest.exit(f"layerfit tests cannot run: {err}", returncode=3)
    import materials

    materials.register()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """`<project>/../shared/data` (or `LAYERFIT_SHARED_DATA`); skips when it is absent."""
    path = Path(os.environ.get("LAYERFIT_SHARED_DATA", ROOT.parent / "shared" / "data"))
    if not path.is_dir():
        pytest.skip(f"shared test data not found at {path} (set LAYERFIT_SHARED_DATA)")
    return path
