"""Look at a capture: a per-view table and a contact sheet (images, weights, silhouette overlay)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from captures.capture import Capture
from captures.images import srgb_encode

from ..output import pyplot, save_figure
from .common import start, stopping

#: `inspect` notes views above this many pixels, with the `--downscale` that shows them at 1 M.
LARGE_VIEW = 2_000_000
#: The views a contact sheet shows (the table lists all).
SHEET_VIEWS = 8


def silhouettes(capture: Capture, spp: int = 16) -> list[np.ndarray]:
    """Each view's rendered object coverage in [0, 1]."""
    from ..render import coverage_dict, load_scene, render

    return [
        render(load_scene(coverage_dict(capture.scene_of(i), 0, spp)), spp)[..., 0]
        for i in range(len(capture.views))
    ]


def iou(coverage: np.ndarray, mask: np.ndarray, threshold: float) -> float:
    rendered = coverage > threshold
    union = (rendered | mask).sum()
    return float((rendered & mask).sum() / union) if union else 0.0


def summary(capture: Capture, coverage: list[np.ndarray] | None) -> list[dict]:
    rows = []
    for i, view in enumerate(capture.views):
        row = {
            "view": view.name,
            "size": f"{view.camera.width}x{view.camera.height}",
            "gain": view.gain,
            "valid": float((view.weight > 0).mean()),
            "max": float(view.image.max()),
        }
        if coverage is not None and view.mask is not None:
            row["iou"] = iou(coverage[i], view.mask, view.mask_coverage)
        rows.append(row)
    return rows


def contact_sheet(
    capture: Capture, coverage: list[np.ndarray] | None, out: Path, max_views: int = 8
) -> Path:
    """Rows: views; columns: the image (sRGB, exposed to its 99th percentile), its validity
    weight, and the rendered silhouette over the image (with IoU when the object is known)."""
    plt = pyplot()
    views = capture.views[:max_views]
    cols = 3 if coverage is not None else 2
    fig, axes = plt.subplots(
        len(views), cols, figsize=(3.2 * cols, 2.6 * len(views)), squeeze=False
    )
    for i, view in enumerate(views):
        scale = np.percentile(view.image[view.weight > 0], 99) if (view.weight > 0).any() else 1
        shown = srgb_encode(view.image / max(scale, 1e-12))
        axes[i, 0].imshow(shown)
        axes[i, 0].set_title(f"{view.name} (gain {view.gain:.3g})", fontsize=8)
        axes[i, 1].imshow(view.weight, cmap="gray", vmin=0, vmax=1)
        axes[i, 1].set_title(f"weight: {(view.weight > 0).mean():.1%} valid", fontsize=8)
        if coverage is not None:
            overlay = shown.copy()
            edge = (coverage[i] > 0.05) & (coverage[i] < 0.95)
            overlay[coverage[i] > 0.5] = 0.6 * overlay[coverage[i] > 0.5] + 0.4 * np.array(
                [0, 1, 0]
            )
            overlay[edge] = [1, 0, 1]
            axes[i, 2].imshow(overlay)
            title = "rendered silhouette"
            if view.mask is not None:
                title += f", IoU {iou(coverage[i], view.mask, view.mask_coverage):.3f}"
            axes[i, 2].set_title(title, fontsize=8)
        for ax in axes[i]:
            ax.axis("off")
    if len(capture.views) > len(views):  # said, not silently cut
        fig.suptitle(
            f"the first {len(views)} of {len(capture.views)} views (the table lists all)",
            fontsize=9,
        )
    fig.tight_layout()
    return save_figure(fig, out)


@dataclasses.dataclass(frozen=True)
class Inspection:
    """What `inspect` found: the capture, one row per view (`summary`), the sheet written (and
    how many views it shows) and a warning where the views barely see the object."""

    capture: Capture
    rows: list[dict]
    sheet: Path
    shown: int
    warning: str | None


def inspect(
    capture: Path,
    sheet: Path | None = None,
    silhouette: bool = True,
    downscale: int = 1,
    force: bool = False,
    variant: str | None = None,
    note: Callable[[str], None] = lambda text: None,
) -> Inspection:
    """`layerfit inspect`: open a capture (a capture.toml or its folder, a peer scene.json, a
    DiLiGenT folder), render its silhouettes (`silhouette`) and draw a contact sheet (default
    `out/inspect-<name>.png`, never inside the capture). `note(text)` hears of views so large
    that their silhouettes take minutes."""
    from captures import open_capture
    from captures.capture import MIN_SIDE
    from captures.errors import InputError
    from captures.files import check_output

    from ..output.figures import drawn_by_layerfit

    named = capture.resolve()  # `.` is named by its folder (the sheet was "inspect-.png")
    if named.name in ("scene.json", "capture.toml"):
        named = named.parent
    given, sheet = sheet is not None, sheet or Path("out") / f"inspect-{named.stem}.png"
    cap = open_capture(capture, downscale, "--downscale")
    small = min(cap.views, key=lambda v: min(v.camera.width, v.camera.height))
    if min(small.camera.width, small.camera.height) < MIN_SIDE:
        raise InputError(
            f"--downscale {downscale}: leaves view {small.name} "
            f"{small.camera.width}x{small.camera.height}: at least {MIN_SIDE} pixels a "
            "side; give a smaller factor"
        )
    folder = Path(cap.path or capture)
    folder = folder if folder.is_dir() else folder.parent
    if sheet.resolve().is_relative_to(folder.resolve()):
        what = f"--sheet {sheet}" if given else f"the default sheet {sheet} (give --sheet)"
        raise InputError(
            f"{what}: is inside the capture folder {folder}; write the sheet "
            "elsewhere (a capture's files are never overwritten)"
        )
    # run again, inspect redraws its own default sheet (tagged by layerfit); a sheet named
    # with --sheet, or a file layerfit did not draw, only with --force
    redraw = force or (not given and drawn_by_layerfit(sheet))
    check_output(sheet, "--sheet", force=redraw, inputs=[capture], suffixes=(".png",))
    big = max(cap.views, key=lambda v: v.camera.width * v.camera.height).camera
    if silhouette and big.width * big.height > LARGE_VIEW:  # 6000x4000 x 3: 2 min, 7 GB
        factor = downscale * math.ceil(math.sqrt(big.width * big.height / 1e6))
        note(
            f"views of up to {big.width}x{big.height}: rendering their silhouettes takes "
            f"minutes and gigabytes; --downscale {factor} shows them at about 1 M pixels (or "
            "--no-silhouette)"
        )
    start(variant)
    from ..render.scene import overlap_warning

    with stopping(lambda: "no sheet written"):
        coverage = silhouettes(cap) if silhouette else None
        rows = summary(cap, coverage)
        overlaps = {row["view"]: row["iou"] for row in rows if "iou" in row}
        warning = overlap_warning(str(capture), overlaps, len(rows))  # as `fit` warns
        out = contact_sheet(cap, coverage, sheet, SHEET_VIEWS)
    return Inspection(cap, rows, out, min(len(cap.views), SHEET_VIEWS), warning)
