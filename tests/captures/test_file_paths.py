"""Input and output paths: names not in UTF-8, a folder for a file, own files, atomic writes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scene_tables import cube_obj

from captures import CaptureError
from captures.images import write_image


def test_an_output_path_that_is_not_utf8_is_refused_by_name(tmp_path):
    """A name whose bytes are not UTF-8 (Python holds them escaped) is refused before any work,
    its bytes shown escaped: the image and JSON writers and the report take text (an internal
    error once the work was done)."""
    import os

    from captures.errors import InputError
    from captures.files import check_output

    bad = Path(os.fsdecode(os.fsencode(tmp_path) + b"/out\xff.png"))
    with pytest.raises(InputError, match=r"--out .*out\\xff\.png: the path is not UTF-8"):
        check_output(bad, "--out")
    assert check_output(tmp_path / "out-\u00e9.png", "--out").name == "out-\u00e9.png"


def test_input_files_whose_path_is_not_utf8_are_refused_by_name(tmp_path):
    """Images, masks, RAWs and meshes under a name that is not UTF-8 are refused in one line
    with the bytes escaped (OpenImageIO's open raised a TypeError: an internal error)."""
    import os

    from captures.geometry import check_obj
    from captures.images import image_problem, read_image, read_linear
    from captures.raw import read_raw

    folder = Path(os.fsdecode(os.fsencode(tmp_path) + b"/caf\xe9"))
    folder.mkdir()
    write_image(tmp_path / "v.png", np.full((4, 4, 3), 0.5, np.float32))  # its writer: no
    (tmp_path / "v.png").rename(folder / "v.png")
    cube_obj(folder / "cube.obj")
    for read in (read_image, lambda p: read_linear(p, "srgb"), read_raw):
        with pytest.raises(CaptureError, match=r"caf\\xe9/v.png: the path is not UTF-8"):
            read(folder / "v.png")
    with pytest.raises(CaptureError, match=r"caf\\xe9/cube.obj: the path is not UTF-8"):
        check_obj(folder / "cube.obj")
    assert "not a UTF-8 path" in image_problem(folder / "v.png")


def test_a_folder_given_for_an_output_file_names_the_fix(tmp_path):
    """`--sheet some/folder`: it said "unsupported file type '(none)'"."""
    from captures.errors import InputError
    from captures.files import check_output

    with pytest.raises(InputError, match=r"--sheet .*: is a folder; give a file's name in it"):
        check_output(tmp_path, "--sheet", suffixes=(".png",))
    assert check_output(tmp_path / "s.png", "--sheet", suffixes=(".png",)) == tmp_path / "s.png"


def test_an_output_folder_names_only_whole_files_as_its_own(tmp_path):
    """`--force` replaces a folder whole: only files its main file names, as whole names, are
    the tool's (a `data.exr` reference does not make a user's `a.exr` the export's)."""
    from captures.files import foreign_entries

    (tmp_path / "material.xml").write_text(
        '<string name="filename" value="data.exr"/>\n<string value="textures/glaze.mask.exr"/>'
    )
    for name in ("data.exr", "a.exr", "glaze.mask.exr", "mask.exr", "notes.txt"):
        (tmp_path / name).write_text("x")
    (tmp_path / "meshes").mkdir()
    found = foreign_entries(tmp_path, tmp_path / "material.xml")
    assert found == ["a.exr", "mask.exr", "meshes", "notes.txt"]


def test_an_atomic_file_is_on_disk_before_its_name_points_at_it(tmp_path, monkeypatch):
    """A file written through `atomic_path` is synced before the rename (a power cut after the
    rename left an empty file on filesystems that delay allocation); an error leaves neither the
    file nor its temporary."""
    import os

    from captures.files import write_text

    order = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: (order.append("fsync"), real_fsync(fd))[1])
    monkeypatch.setattr(
        os, "replace", lambda a, b: (order.append("replace"), real_replace(a, b))[1]
    )
    write_text(tmp_path / "summary.json", "{}")
    assert order == ["fsync", "replace"] and (tmp_path / "summary.json").read_text() == "{}"
    monkeypatch.setattr(os, "fsync", lambda fd: (_ for _ in ()).throw(OSError(5, "I/O error")))
    with pytest.raises(OSError, match="I/O error"):
        write_text(tmp_path / "preset.toml", "x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]
