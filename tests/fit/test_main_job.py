"""The main job (README's first command): `layerfit fit configs/cup-fit.toml` on the bundled cup
capture. Slow (about 4 minutes on 2 cores)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fit.entry import run as main

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_main_job_fits_the_cup_within_its_reported_sd(tmp_path, monkeypatch):
    """Every fitted parameter within 3 reported sd of the truth; ior and the thresholds within
    the main job's targets, each layer's mask IoU at least 0.9 (alpha and the colours are
    within their sd, which this capture does not make small enough to promise 5 % and 0.02:
    BENCHMARKS, "The main job")."""
    monkeypatch.chdir(ROOT)
    with pytest.raises(SystemExit) as exit_:
        main(["fit", "configs/cup-fit.toml", "--out", str(tmp_path / "run")])
    assert exit_.value.code == 0
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    for key, z in summary["error_over_std"].items():
        assert z is not None and np.all(np.abs(z) <= 3), (key, z)
    error = summary["error"]
    assert abs(error["glaze.ior"]) <= 0.03
    for layer in ("glaze", "lime", "stain"):
        assert abs(error[f"{layer}.mask.threshold"]) <= 0.05
    # the given masks at the fitted thresholds against the truth's, where the views see
    # (measured 0.96-1.0)
    assert min(summary["mask_iou"].values()) >= 0.9, summary["mask_iou"]
    assert "truth (seen share" in (tmp_path / "run" / "report.html").read_text()
