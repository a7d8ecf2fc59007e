"""Fit configs: the bundled ones load; mistakes name the file and the key."""

from __future__ import annotations

from pathlib import Path

import pytest

from captures import CaptureError
from fit.fitconfig import load_fit_config
from fit.free import resolve
from fit.run import start_values

ROOT = Path(__file__).resolve().parents[2]


def test_peer_config_loads(shared_data):
    cfg = load_fit_config(ROOT / "configs" / "peer-sphere.toml")
    assert cfg.capture.name == "scene.json" and cfg.material["fresnel"] == "exact"
    free = resolve(cfg.material, cfg.free)
    assert start_values(cfg.material, free) == {
        "glaze.pigment": [0.5, 0.5, 0.5],
        "glaze.roughness": 0.2,
        "glaze.ior": 1.3,
    }


@pytest.mark.parametrize(
    "edit, message",
    [
        (('solver = "schedule"', 'solver = "newton"'), "fit.solver = 'newton'; choose one of"),
        (("lm_spp = 64", "lm_spp = 0"), "fit.lm_spp = 0 must be >= 1"),
        (("[fit]", "[fit]\nfree_params = 1"), "unknown key(s) free_params in [fit]"),
        (('scene.json"', 'nothing.json"'), "nothing.json' does not exist"),
    ],
)
def test_fit_config_errors(tmp_path, shared_data, edit, message):
    text = (ROOT / "configs" / "peer-sphere.toml").read_text()
    text = text.replace('"../../shared/data', f'"{shared_data}')  # the copy lives elsewhere
    assert edit[0] in text
    path = tmp_path / "broken.toml"
    path.write_text(text.replace(edit[0], edit[1], 1))
    with pytest.raises(CaptureError) as err:
        load_fit_config(path)
    assert message in str(err.value) and "broken.toml" in str(err.value)
