"""libLLVM discovery: a usable one is chosen explicitly, an unusable one is a one-line error."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from cli_run import run_cli

from fit import variant
from fit.variant import BackendError, ensure_llvm, find_libllvm, llvm_version

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.mark.parametrize(
    "name, version",
    [
        ("libLLVM-19.so", 19),
        ("libLLVM-19.so.1", 19),
        ("libLLVM.so.19.1", 19),
        ("libLLVM-14.0.6.so.1", 14),
        ("libLLVM-15.so", 15),
        ("libLLVM.so", None),
        ("libfoo.so", None),
    ],
)
def test_llvm_version(name, version):
    assert llvm_version(f"/usr/lib/{name}") == version


def test_find_prefers_newest_usable(tmp_path, monkeypatch):
    for name in ("libLLVM-14.so.1", "libLLVM-15.so", "libLLVM-17.so.1", "libLLVM.so.19.1"):
        (tmp_path / name).touch()
    monkeypatch.setattr(variant, "_candidates", lambda: [str(p) for p in tmp_path.iterdir()])
    assert find_libllvm() == str(tmp_path / "libLLVM.so.19.1")


def test_none_usable_is_a_clear_error(tmp_path, monkeypatch):
    (tmp_path / "libLLVM-15.so").touch()
    monkeypatch.setattr(variant, "_candidates", lambda: [str(tmp_path / "libLLVM-15.so")])
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    with pytest.raises(BackendError, match="apt-get install libllvm19"):
        ensure_llvm()


def test_explicit_old_llvm_is_refused(tmp_path, monkeypatch):
    old = tmp_path / "libLLVM-14.so.1"
    old.touch()
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(old))
    with pytest.raises(BackendError, match=r"libLLVM 14, which crashes Dr\.Jit"):
        ensure_llvm()
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / "missing.so"))
    with pytest.raises(BackendError, match="does not exist"):
        ensure_llvm()


def _old_llvm(tmp_path) -> dict:
    """Environment pointing Dr.Jit at a (fake) libLLVM 15, which crashes it, with the LLVM variant
    asked for (also where the suite runs with ``LAYERFIT_VARIANT=cuda_ad_rgb``)."""
    old = tmp_path / "libLLVM-15.so"
    old.touch()
    return {"DRJIT_LIBLLVM_PATH": str(old), "LAYERFIT_VARIANT": "llvm_ad_rgb"}


def test_cli_stops_with_one_line(tmp_path):
    out = run_cli(
        "render",
        "configs/glazed-sphere.toml",
        "--out",
        tmp_path / "x.png",
        env=_old_llvm(tmp_path),
        timeout=300,
    )
    assert out.returncode == 1
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "install libLLVM >= 16" in lines[0], out.stderr
    assert "LLVM ERROR" not in out.stderr and not list(tmp_path.glob("x*"))


def test_tests_stop_with_one_line(tmp_path):
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            "--rootdir",
            ROOT,
            "-c",
            os.path.join(ROOT, "pyproject.toml"),
            "--confcutdir",
            os.path.join(ROOT, "tests"),
            os.path.join(ROOT, "tests", "fit", "test_variant.py::test_llvm_version"),
        ],
        capture_output=True,
        text=True,
        check=False,
        cwd=ROOT,
        timeout=300,
        env={**os.environ, **_old_llvm(tmp_path)},
    )
    assert out.returncode == 3, out.stdout + out.stderr
    assert "layerfit tests cannot run" in out.stdout + out.stderr
    assert "install libLLVM >= 16" in out.stdout + out.stderr


@pytest.mark.parametrize("asked", [None, "cpu,cuda"])
def test_jax_stays_off_the_gpu_unless_asked(asked):
    """`import fit` makes JAX run on the CPU (on a GPU it would take 75 % of the memory that
    Dr.Jit's renders need), unless the user set ``JAX_PLATFORMS``."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_PLATFORMS"}
    if asked:
        env["JAX_PLATFORMS"] = asked
    code = "import os, fit; print(os.environ['JAX_PLATFORMS'])"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env
    )
    assert out.stdout.strip() == (asked or "cpu")
