"""Per-pixel validity weights and resampling by area averaging (scikit-image)."""

from __future__ import annotations

import numpy as np
from skimage.morphology import dilation, disk
from skimage.transform import downscale_local_mean

from .errors import CaptureError


def validity(
    image: np.ndarray,
    saturated: np.ndarray | None = None,
    object_mask: np.ndarray | None = None,
    dilate: int = 2,
    black: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """(image with non-finite pixels zeroed, weight in {0, 1}) for an (H, W, 3) linear image.

    Weight 0 where: any channel is NaN/Inf; any channel is saturated (`saturated`, dilated by
    `dilate` pixels: blooming spreads); every channel is at or below `black` (clipped); outside
    `object_mask`.
    """
    finite = np.all(np.isfinite(image), axis=-1)
    weight = finite.copy()
    if saturated is not None:
        sat = saturated if dilate == 0 else dilation(saturated, disk(dilate))
        weight &= ~sat
    weight &= ~np.all(np.where(finite[..., None], image, 0.0) <= black, axis=-1)
    if object_mask is not None:
        weight &= object_mask
    return np.where(finite[..., None], image, 0.0).astype(np.float32), weight.astype(np.float32)


def downscale(image: np.ndarray, weight: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Area-average by an integer `factor`: each output pixel is the weighted mean of its block
    (invalid pixels do not count) and its weight the block's valid share."""
    if factor == 1:
        return image, weight
    h, w = weight.shape
    if h % factor or w % factor:
        raise CaptureError(
            f"downscale = {factor} does not divide the image size {w}x{h}; choose a divisor"
        )
    w_mean = downscale_local_mean(weight, (factor, factor))
    sums = downscale_local_mean(image * weight[..., None], (factor, factor, 1))
    out = np.where(w_mean[..., None] > 0, sums / np.maximum(w_mean[..., None], 1e-12), 0.0)
    return out.astype(np.float32), w_mean.astype(np.float32)
