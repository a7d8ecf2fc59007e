"""The small project the bad-input tests copy and the glazed sphere's problems, once a module."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from bad_inputs_cases import FIT, OBJ, ROOT

from captures.images import write_image


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """A tiny valid project: a render config (16x12), its synthetic capture (one view, with
    [truth]), a fit config, a texture, an env map, a mesh, and a small DiLiGenT-style folder."""
    from fit.commands.synth import synthesize
    from fit.config import load_render_config
    from fit.material import save_preset

    root = tmp_path_factory.mktemp("base")
    text = (ROOT / "configs" / "glazed-sphere.toml").read_text()
    text = text.replace("width = 480", "width = 16").replace("height = 360", "height = 12")
    (root / "render.toml").write_text(text.replace("spp = 256", "spp = 2"))
    cfg = load_render_config(root / "render.toml")
    synthesize(cfg.scene, cfg.material, root / "cap", spp=2)
    save_preset(cfg.material, root / "preset.toml")
    (root / "fit.toml").write_text(FIT)
    write_image(root / "tex.png", np.full((4, 4, 3), 0.5, np.float32))
    write_image(root / "sky.exr", np.full((4, 8, 3), 0.1, np.float32))
    (root / "m.obj").write_text(OBJ)
    dili = root / "dili"
    dili.mkdir()
    yy, xx = np.mgrid[0:20, 0:24]
    disc = ((xx - 12) ** 2 + (yy - 10) ** 2 < 49).astype(np.float32)
    write_image(dili / "mask.png", np.repeat(disc[..., None], 3, -1))
    write_image(dili / "001.png", np.repeat(0.3 * disc[..., None] + 0.01, 3, -1))
    write_image(dili / "002.png", np.repeat(0.2 * disc[..., None] + 0.01, 3, -1))
    (dili / "filenames.txt").write_text("001.png\n002.png\n")
    (dili / "light_directions.txt").write_text("0.1 0.2 0.97\n-0.3 0.1 0.95\n")
    (dili / "light_intensities.txt").write_text("1.0 1.1 0.9\n0.8 1.0 1.2\n")
    return root


@pytest.fixture(scope="module")
def problem():
    from sphere_problems import sphere_problem  # after the variant is chosen

    return sphere_problem(48, 36)


@pytest.fixture(scope="module")
def larger():
    """At 48x36 the highlight spans a few pixels and short Adam schedules land alpha anywhere
    from +6 % to -32 % by seed (measured, seeds 0-3); at 96x72 within -2 to -7 %."""
    from sphere_problems import sphere_problem

    return sphere_problem(96, 72)
