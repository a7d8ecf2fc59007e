"""Pictures of a fit: each view's photo, the render at the fitted values and where they differ;
the loss per phase."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from captures.images import srgb_encode

from ..material import to_physical
from ..solvers import Problem, Result
from .figures import pyplot, save_figure


def comparison_sheet(
    problem: Problem, u, out: Path, spp: int = 64, seed: int = 0, max_views: int = 6
) -> Path:
    """Rows: views (up to `max_views`); columns: the photo and the fitted render (sRGB, one
    exposure per view: the photo's 99th percentile), and the weighted difference
    (render - photo) / exposure in a diverging map. Written whole or not at all."""
    plt = pyplot()
    u = np.asarray(u, np.float32)
    x = np.asarray(to_physical(problem.free, u[: problem.n_material]), np.float32)
    flat = problem.renderer().render(x, seed, spp)
    if problem.gains:
        flat = flat * np.asarray(problem.gain_multipliers(u[problem.n_material :]))
    views = problem.capture.views[:max_views]
    fig, axes = plt.subplots(len(views), 3, figsize=(9.6, 2.6 * len(views)), squeeze=False)
    offset = 0
    for i, view in enumerate(problem.capture.views):
        n = view.image.size
        rendered = flat[offset : offset + n].reshape(view.image.shape)
        offset += n
        if i >= max_views:
            break
        valid = view.weight > 0
        scale = max(float(np.percentile(view.image[valid], 99)) if valid.any() else 1.0, 1e-12)
        diff = np.where(valid, (rendered - view.image).mean(axis=-1) / scale, np.nan)
        rel = np.nanmean(np.abs(diff)) if valid.any() else float("nan")
        axes[i, 0].imshow(srgb_encode(np.clip(view.image / scale, 0, 1)))
        axes[i, 0].set_title(f"{view.name}: photo", fontsize=8)
        axes[i, 1].imshow(srgb_encode(np.clip(rendered / scale, 0, 1)))
        axes[i, 1].set_title(f"fitted render ({spp} spp)", fontsize=8)
        shown = axes[i, 2].imshow(diff, cmap="coolwarm", vmin=-0.2, vmax=0.2)
        axes[i, 2].set_title(f"(render - photo) / exposure, mean |.| {rel:.3f}", fontsize=8)
        fig.colorbar(shown, ax=axes[i, 2], fraction=0.046)
        for ax in axes[i]:
            ax.axis("off")
    fig.tight_layout()
    return save_figure(fig, out)


def loss_plot(result: Result, phases, path: Path) -> Path:
    """The loss per step, one colour per phase (phases at another resolution or loss scale are
    not comparable in level; LM and BFGS phases show their final loss as one point)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.2))
    begin = 0
    for k, (phase, end) in enumerate(zip(phases, result.phase_ends, strict=True)):
        steps = np.arange(begin, end)
        label = f"{k + 1}: {phase.describe()}"
        ax.semilogy(steps, result.history[begin:end], "o" if end - begin == 1 else "-", label=label)
        begin = end
    ax.set_xlabel("step")
    ax.set_ylabel("loss (weighted)")
    ax.set_title("per phase at its own resolution and spp", fontsize=8)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path, dpi=100)
