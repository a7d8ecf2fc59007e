"""The test run's setup: one Mitsuba variant, the plugins registered, and the shared test data."""

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
    """`<project>/../shared/data` (or `LAYERFIT_SHARED_DATA`). Absent, the tests that need it
    skip with the reason on a user's clone, and fail in CI (`CI` set), where it must be."""
    path = Path(os.environ.get("LAYERFIT_SHARED_DATA", ROOT.parent / "shared" / "data"))
    if not path.is_dir():
        missing = f"shared test data not found at {path} (set LAYERFIT_SHARED_DATA)"
        if in_ci():
            pytest.fail(f"{missing}; CI must have it", pytrace=False)
        pytest.skip(missing)
    return path


def in_ci() -> bool:
    """Whether the tests run in CI (`CI` set to anything but empty, 0 or false)."""
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false")
