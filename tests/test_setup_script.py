"""scripts/setup.sh's options (the README's two commands share it): an unknown option stops it
before it installs anything, naming the options it knows."""

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_setup_refuses_an_unknown_option_before_installing_anything():
    done = subprocess.run(
        ["bash", str(ROOT / "scripts" / "setup.sh"), "--with-test"],
        capture_output=True,
        check=False,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert "unknown option --with-test" in done.stderr
    assert "--with-tests" in done.stderr and "--with-chromium" in done.stderr
    assert "installing" not in done.stdout + done.stderr
