"""Look at a capture: a per-view table and a contact sheet (images, weights, silhouette overlay)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from captures.capture import Capture
from captures.images import srgb_encode

from ..output import pyplot, save_figure
from ..render import coverage_dict, load_scene, render


def silhouettes(capture: Capture, spp: int = 16) -> list[np.ndarray]:
    """Each view's rendered object coverage in [0, 1]."""
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
