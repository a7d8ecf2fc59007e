"""The HTML report of a fit: its files, and that it opens cleanly in headless Chromium (every
image loads, no console errors, nothing fetched from outside, nothing wider than the window)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from fit.output import ViewPanel, write_report

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-dev-shm-usage",  # containers often have a small /dev/shm
]
IN_CI = os.environ.get("CI", "").lower() not in ("", "0", "false")
OUTCOME_KEYS = ("solver", "outcome", "steps", "rejected", "message", "loss", "seconds")
LABELS = ["glaze.pigment[0]", "glaze.pigment[1]", "glaze.pigment[2]", "glaze.roughness"]


def fake_fit(rng: np.random.Generator) -> tuple[dict, list[ViewPanel], dict]:
    """A summary.json as `layerfit fit` writes it, 3 views (the last held out), one mask."""
    summary = {
        "config": "configs/<glazed> & sphere-fit.toml",  # characters that need escaping
        "capture": "out/glazed-sphere-capture",
        "values": {
            "glaze.pigment": [0.61, 0.32, 0.2],
            "glaze.roughness": 0.18,
            "base.albedo": rng.random(48).tolist(),
            "glaze.ior": 1.52,
        },
        "std": {"glaze.pigment": [0.01, 0.01, 0.02], "glaze.roughness": 0.004, "glaze.ior": 0.3},
        "truth": {"glaze.pigment": [0.6, 0.3, 0.2], "glaze.roughness": 0.2, "glaze.ior": 1.5},
        "error": {"glaze.pigment": [0.01, 0.02, 0.0], "glaze.roughness": -0.02, "glaze.ior": 0.02},
        "start": {
            "glaze.pigment": [0.5, 0.5, 0.5],
            "glaze.roughness": 0.3,
            "base.albedo": [0.5] * 48,
            "glaze.ior": 1.5,
        },
        # an undetermined parameter's correlations are null (unknown): drawn grey
        "correlation": [
            [None if (i == 3) != (j == 3) else v for j, v in enumerate(row)]
            for i, row in enumerate(np.corrcoef(rng.random((4, 10))).tolist())
        ],
        "correlation_labels": LABELS,
        "history": (np.geomspace(1.0, 1e-3, 60) * (1 + 0.1 * rng.random(60))).tolist(),
        "phase_ends": [40, 59, 60],
        "phases": [
            {"solver": "adam", "steps": 40, "spp": 8, "downscale": 2},
            {"solver": "adam", "steps": 19, "spp": 32, "downscale": 1},
            {"solver": "lm", "steps": 10, "spp": 32, "downscale": 1},
        ],
        "outcomes": [
            dict(zip(OUTCOME_KEYS, row, strict=True))
            for row in [
                ("adam", "step_limit", 40, 0, "", 0.01, 12.5),
                ("adam", "converged", 19, 1, "one step <rejected> as non-finite", 0.002, 30.1),
                ("lm", "diverged", 1, 0, "kept the start", 0.002, 8.0),
            ]
        ],
        "poorly_determined": ["glaze.ior"],
        "wall_time_s": 51.3,
        "software": {"layerfit": "0.1.0", "mitsuba": "3.9.1"},
        "views": [{"name": f"view_{i:02d}", "rmse": 0.05, "held_out": i == 2} for i in range(3)],
    }
    views = []
    for i in range(3):
        photo = rng.random((24, 32, 3), dtype=np.float32)
        weight = np.ones((24, 32), np.float32)
        weight[:4] = 0  # an invalid band: grey in the difference
        render = (photo * rng.uniform(0.9, 1.1, photo.shape)).astype(np.float32)
        views.append(ViewPanel(f"view_{i:02d}", photo, render, weight, i == 2, 0.04 + 0.01 * i))
    masks = {"glaze.mask": rng.random((24, 32, 1), dtype=np.float32)}
    return summary, views, masks


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fit")
    summary, views, masks = fake_fit(np.random.default_rng(3))
    return write_report(out, summary, views, masks)


def test_report_files(report: Path):
    assert report == report.parent / "report.html"
    pngs = sorted(p.name for p in (report.parent / "report").iterdir())
    assert pngs == [
        "loss.png",
        "mask-00-glaze.mask.png",
        "view-00-view_00.png",
        "view-01-view_01.png",
        "view-02-view_02.png",
    ]
    text = report.read_text(encoding="utf-8")
    assert "&lt;glazed&gt; &amp; sphere-fit.toml" in text and "<glazed>" not in text
    assert text.count("class='badge'>held out") == 1
    assert "one step &lt;rejected&gt; as non-finite" in text
    assert "48 texels, mean" in text
    assert "<tr class='off'>" in text  # roughness is 5 std off: highlighted
    assert "<tr class='poor'>" in text  # glaze.ior
    assert not list(report.parent.rglob(".*partial*"))  # no temporary files left behind


def test_the_correlation_is_a_table_of_coloured_cells(report: Path):
    """One row per parameter, its label first and one cell per parameter: red for +1, blue for
    -1 (the colour map's ends), the value written; an undetermined parameter's cells grey."""
    import re

    import matplotlib

    from fit.output.report import CORR_CMAP, _hex

    text = report.read_text(encoding="utf-8")
    table = text[text.index("<table class='corr'>") :]
    table = table[: table.index("</table>")]
    rows = re.findall(r"<tr><th class='key'>([^<]*)</th>(.*?)</tr>", table)
    assert [label for label, _ in rows] == LABELS
    for i, (_, cells) in enumerate(rows):
        found = re.findall(r"<td ([^>]*)>([^<]*)</td>", cells)
        assert len(found) == len(LABELS)
        for j, (attributes, value) in enumerate(found):
            if (i == 3) != (j == 3):  # the fake fit's undetermined parameter
                assert "class='undetermined'" in attributes and value == ""
            elif i == j:
                red = _hex(matplotlib.colormaps[CORR_CMAP](1.0))
                assert f"background: {red}" in attributes and value == "1.00"
            else:
                assert re.fullmatch(r"-?[01]\.\d\d", value), value
    assert "undetermined (no correlation known)" in text


def test_a_large_correlation_is_coloured_without_its_values():
    """Past `CORR_WRITTEN` rows the cells are coloured and hold their values in titles alone;
    -1 is the colour map's blue end."""
    import matplotlib

    from fit.output.report import CORR_CMAP, CORR_WRITTEN, _correlation_table, _hex

    n = CORR_WRITTEN + 1
    corr = np.eye(n)
    corr[0, 1] = corr[1, 0] = -1.0
    html = _correlation_table(corr, [f"p{i}" for i in range(n)])
    assert html.count("<td ") == n * n and "1.00<" not in html
    assert f"background: {_hex(matplotlib.colormaps[CORR_CMAP](0.0))}" in html
    assert "title='p0 / p1: -1.000'" in html and "undetermined" not in html


def test_masks_are_shown_at_most_as_wide_and_as_tall_as_the_page_allows(tmp_path: Path):
    """A square or wide mask 200 px wide, a tall one (the cup's 32x128 texels) 300 px tall."""
    from fit.output.report import MASK_HEIGHT, MASK_WIDTH

    masks = {
        "wide": np.zeros((16, 64, 1), np.float32),
        "tall": np.zeros((128, 32, 1), np.float32),
    }
    html = write_report(tmp_path, {"values": {}}, [], masks).read_text("utf-8")
    assert f"alt='wide' style='width: {MASK_WIDTH}px'" in html
    assert f"alt='tall' style='width: {MASK_HEIGHT * 32 // 128}px'" in html


def test_a_mask_file_is_named_by_its_key_not_its_caption(tmp_path: Path):
    """The truth beside a fitted mask, captioned with its scores, is `mask-NN-<key>_truth.png`."""
    masks = {
        "stain.mask": np.zeros((8, 8), np.float32),
        "stain.mask: truth (seen share's IoU 0.77; the truth at the fitted texels' 0.98)": np.ones(
            (8, 8), np.float32
        ),
        "stain.mask.texture sd": np.ones((8, 8), np.float32),
    }
    html = write_report(tmp_path, {"values": {}}, [], masks).read_text("utf-8")
    names = sorted(p.name for p in (tmp_path / "report").iterdir())
    assert names == [
        "mask-00-stain.mask.png",
        "mask-01-stain.mask_truth.png",
        "mask-02-stain.mask.texture_sd.png",
    ]
    assert "seen share&#x27;s IoU 0.77" in html  # the caption keeps the scores


def test_report_without_optional_parts(tmp_path: Path):
    """A summary with every optional key missing still gives a page (dashes, no figures)."""
    html = write_report(tmp_path, {"values": {"glaze.roughness": 0.2}}, []).read_text("utf-8")
    assert "<title>fit</title>" in html and "No loss history." in html
    assert not (tmp_path / "report").exists()


@pytest.fixture(scope="module")
def browser():
    if not CHROMIUM.exists():
        if IN_CI:
            pytest.fail(
                f"{CHROMIUM} is missing: CI must install Debian's chromium (scripts/test.sh)"
            )
        pytest.skip(f"{CHROMIUM} not installed (apt-get install chromium; scripts/test.sh does)")
    if IN_CI:
        from playwright.sync_api import sync_playwright
    else:
        sync_playwright = pytest.importorskip("playwright.sync_api").sync_playwright
    with sync_playwright() as p:
        chromium = p.chromium.launch(
            executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS
        )
        yield chromium
        chromium.close()


def open_report(browser, html: Path) -> list[str]:
    """Problems of the page in Chromium: images that did not load, console errors, requests
    that left the report's folder, content wider than a 1280 px window."""
    problems = []
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    page.on("console", lambda m: m.type == "error" and problems.append(f"console: {m.text}"))
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.on(
        "request",
        lambda r: r.url.startswith("file://") or problems.append(f"external request: {r.url}"),
    )
    page.goto(html.resolve().as_uri(), wait_until="load")
    broken = page.evaluate(
        "Array.from(document.images)"
        ".filter(i => !i.complete || i.naturalWidth === 0).map(i => i.getAttribute('src'))"
    )
    problems += [f"image not loaded: {src}" for src in broken]
    if page.evaluate("document.documentElement.scrollWidth > window.innerWidth"):
        problems.append("the page is wider than the window")
    page.close()
    return problems


def test_report_opens_in_chromium(browser, report: Path):
    assert open_report(browser, report) == []


def test_broken_image_is_caught(browser, report: Path, tmp_path: Path):
    copy = tmp_path / "copy"
    shutil.copytree(report.parent, copy)
    (copy / "report" / "loss.png").unlink()
    problems = open_report(browser, copy / "report.html")
    assert "image not loaded: report/loss.png" in problems
    assert any(p.startswith("console:") for p in problems), problems


@pytest.mark.parametrize("height, width", [(120, 160), (56, 64), (300, 100), (17, 400), (1, 1)])
def test_a_views_png_holds_photo_render_and_difference(tmp_path: Path, height, width):
    """A view's PNG is the photo, the fitted render and their difference side by side at the
    view's own pixels, for tall, wide, tiny and odd sizes: the photo and render in sRGB over the
    photo's exposure, the difference coloured (no difference: the colour map's centre), pixels
    the fit does not use grey, white between the panels; tagged as drawn by layerfit."""
    import matplotlib
    from matplotlib.image import imread

    from captures.images import srgb_encode
    from fit.output import report
    from fit.output.figures import drawn_by_layerfit

    rng = np.random.default_rng(0)
    photo = rng.uniform(0.1, 1.0, (height, width, 3)).astype(np.float32)
    render = photo.copy()
    render[: height // 2] *= 1.5  # brighter over the top half: red there
    weight = np.ones((height, width), np.float32)
    weight[:, -1] = 0  # the last column is not fitted: grey in the difference
    view = ViewPanel("v", photo, render, weight, False, 0.05)
    png = report._view_png(view, tmp_path / "v.png")
    sheet = imread(png)[..., :3]
    panel, gap = report._view_columns(width)
    assert sheet.shape == (height, 3 * panel + 2 * gap, 3)
    assert drawn_by_layerfit(png)
    exposure = np.percentile(photo[weight > 0], 99) if (weight > 0).any() else 1.0
    shown = np.clip(srgb_encode(photo / exposure), 0, 1)
    np.testing.assert_allclose(sheet[:, :panel], shown, atol=1 / 255 + 1e-6)
    assert np.all(sheet[:, panel : panel + gap] == 1) and np.all(
        sheet[:, -panel - gap : -panel] == 1
    )
    diff = sheet[:, -panel:]
    np.testing.assert_allclose(diff[:, -1], report.INVALID_GREY, atol=1 / 255 + 1e-6)
    if width > 1 and height > 1:
        centre = np.asarray(matplotlib.colormaps[report.DIFF_CMAP](0.5)[:3])
        np.testing.assert_allclose(diff[-1, 0], centre, atol=1 / 255 + 1e-6)
        assert diff[0, 0, 0] > diff[0, 0, 2]  # brighter: red


def test_views_titles_sit_over_their_panels(browser, report: Path):
    """Each view's HTML titles (photo, fitted render, difference) are centred over their panel
    of the view's PNG as Chromium lays the page out."""
    from fit.output.report import _view_columns

    page = browser.new_page(viewport={"width": 1280, "height": 900})
    page.goto(report.resolve().as_uri(), wait_until="load")
    figures = page.evaluate(
        """Array.from(document.querySelectorAll('img.view')).map(img => {
          const box = img.getBoundingClientRect();
          const spans = Array.from(img.closest('figure').querySelectorAll('.titles span'))
            .filter(s => s.textContent).map(s => s.getBoundingClientRect());
          return {left: box.left, width: box.width, natural: img.naturalWidth,
                  centres: spans.map(s => s.left + s.width / 2)}; })"""
    )
    page.close()
    assert len(figures) == 3
    for fig in figures:
        # the panel width whose sheet is this wide
        panel, gap = next(
            _view_columns(w)
            for w in range(1, fig["natural"] + 1)
            if 3 * w + 2 * _view_columns(w)[1] == fig["natural"]
        )
        scale = fig["width"] / fig["natural"]
        assert len(fig["centres"]) == 3
        for k, centre in enumerate(fig["centres"]):
            middle = fig["left"] + scale * (k * (panel + gap) + panel / 2)
            assert abs(centre - middle) < scale * panel / 10, (k, centre, middle)
