"""Ctrl-C, SIGTERM, a read-only folder, a name too long, no CUDA: one line each, nothing left."""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from bad_inputs_cases import (
    ROOT,
    fit_args,
    inspect_args,
    out,
    render_args,
    run,
    snapshot,
    synth_args,
)


@pytest.mark.parametrize("how", ["ctrl-c", "sigterm"])
def test_ctrl_c_in_synth_is_one_line_and_leaves_nothing(base, tmp_path, capsys, monkeypatch, how):
    """Ctrl-C, or SIGTERM (a kill), while the views render: nothing is left behind."""
    import os
    import signal

    import fit.render

    def interrupted(*args, **kwargs):
        if how == "sigterm":
            os.kill(os.getpid(), signal.SIGTERM)  # the CLI's handler raises KeyboardInterrupt
            raise AssertionError("SIGTERM did not stop the render")
        raise KeyboardInterrupt

    monkeypatch.setattr(fit.render, "render", interrupted)
    work = tmp_path / "w"
    shutil.copytree(base, work)
    before = snapshot(work)
    code, _, stderr = run(["synth", work / "render.toml", "--out", work / "c"], capsys)
    lines = [line for line in stderr.splitlines() if line.strip().startswith(("error", "Trace"))]
    assert code == 130 and not lines and "interrupted: nothing written" in stderr, stderr
    assert snapshot(work) == before  # no capture, no hidden temporary folder


def test_ctrl_c_in_fit_is_one_line_exit_130(base, tmp_path, capsys, monkeypatch):
    import fit.commands.fit as fit_command

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(fit_command, "run_schedule", interrupted)
    work = tmp_path / "w"
    shutil.copytree(base, work)
    code, _, stderr = run(["fit", work / "fit.toml", "--out", work / "run"], capsys)
    assert code == 130 and "Traceback" not in stderr, stderr
    assert [line for line in stderr.splitlines() if "interrupted" in line] == [
        "interrupted: nothing to resume (stopped before the first checkpoint)"
    ]
    assert not [p for p in work.rglob("*") if ".partial" in p.name]


def test_a_ctrl_c_while_the_command_line_is_built_is_one_line(capsys, monkeypatch):
    """A Ctrl-C inside typer's building of the command (before click's own handling): it left a
    traceback and a death by SIGINT (seen in CI, 1 s into a fit); now one line, exit 130."""
    import fit.entry as entry

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(entry, "_command", interrupted)
    code, _, stderr = run(["fit", "x.toml"], capsys)
    assert code == 130 and stderr.strip() == "interrupted: stopped by Ctrl-C or SIGTERM"


@contextlib.contextmanager
def without_root() -> Iterator[None]:
    """Inside, this process acts as the user `nobody` where it runs as root (root writes into a
    read-only folder: CI runs as root); elsewhere nothing changes."""
    if os.geteuid() != 0:
        yield
        return
    import pwd

    nobody = pwd.getpwnam("nobody")
    os.setegid(nobody.pw_gid)
    os.seteuid(nobody.pw_uid)
    try:
        yield
    finally:
        os.seteuid(0)
        os.setegid(0)


@pytest.mark.parametrize(
    "make",
    [
        render_args("--out", out("ro/o.png")),
        synth_args("--out", out("ro/c")),
        inspect_args(out("cap"), "--no-silhouette", "--sheet", out("ro/s.png")),
        fit_args("--out", out("ro/run")),
    ],
    ids=["render", "synth", "inspect", "fit"],
)
def test_read_only_output_folder(base, capsys, make):
    import tempfile

    import fit.commands.fit  # every module the commands import on the way (read as root)
    import fit.commands.inspect
    import fit.commands.render
    import fit.commands.synth  # noqa: F401

    # a folder `nobody` may read (pytest's own are its owner's alone), its `ro` read-only
    with tempfile.TemporaryDirectory() as folder:
        work = Path(folder) / "w"
        shutil.copytree(base, work)
        for path in [Path(folder), work, *work.rglob("*")]:
            path.chmod(0o755 if path.is_dir() else 0o644)
        (work / "ro").mkdir()
        (work / "ro").chmod(0o555)
        try:
            with without_root():
                assert not os.access(work / "ro", os.W_OK, effective_ids=True)  # as it tests
                code, _, stderr = run(make(work), capsys)
        finally:
            (work / "ro").chmod(0o755)
        assert code == 2 and len(stderr.strip().splitlines()) == 1 and "ro" in stderr, stderr
        assert "cannot write" in stderr or "Permission denied" in stderr, stderr
        assert not any((work / "ro").iterdir())


def test_a_name_too_long_for_the_file_system_is_one_line(tmp_path, capsys):
    """An output path with a name over 255 bytes: one line naming the path and the fix, exit 2
    (it was "internal error (OSError: [Errno 36] File name too long)"), nothing written."""
    long = tmp_path / ("x" * 300)
    code, _, stderr = run(
        ["synth", str(ROOT / "configs" / "glazed-sphere.toml"), "--out", str(long)], capsys
    )
    assert code == 2 and "longer than the file system allows" in stderr and "x" * 300 in stderr
    assert list(tmp_path.iterdir()) == []


def test_cuda_without_a_device_is_one_line(base, tmp_path, capsys):
    """`--variant cuda_ad_rgb` where there is no CUDA device: one line saying so, exit 2,
    nothing made (was an internal error from Dr.Jit at the first render)."""
    import drjit as dr

    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("this machine has a CUDA device")
    work = tmp_path / "w"
    shutil.copytree(base, work)
    before = snapshot(work)
    args = ["fit", work / "fit.toml", "--out", work / "a" / "run", "--variant", "cuda_ad_rgb"]
    code, stdout, stderr = run(args, capsys)
    assert code == 2 and not stdout and "no usable CUDA device" in stderr, stderr
    assert stderr.count("\n") == 1
    assert snapshot(work) == before
