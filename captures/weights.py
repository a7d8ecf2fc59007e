"""Per-pixel validity weights (scikit-image morphology) and resampling by area averaging."""

from __future__ import annotations

import numpy as np

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
    if saturated is not None and saturated.any():
        from skimage.morphology import dilation, disk  # 0.18 s to import: only where clipped

        sat = saturated if dilate == 0 else dilation(saturated, disk(dilate))
        weight &= ~sat
    weight &= ~np.all(np.where(finite[..., None], image, 0.0) <= black, axis=-1)
    if object_mask is not None:
        weight &= object_mask
    return np.where(finite[..., None], image, 0.0).astype(np.float32), weight.astype(np.float32)


def downscaled_size(width: int, height: int, factor: float) -> tuple[int, int]:
    """The (width, height) of an image area-averaged by `factor`: square pixels `width / new
    width` input pixels wide (so any size works; a divisor gives exact blocks)."""
    new_width = max(1, round(width / factor))
    return new_width, max(1, round(height * new_width / width))


def _box(n_out: int, n_in: int, size: float, start: float) -> np.ndarray:
    """(n_out, n_in): output pixel o covers input span [start + o size, start + (o + 1) size);
    each row holds its overlap with every input pixel, divided by `size` (spans outside the
    image count as nothing)."""
    lo = start + size * np.arange(n_out)[:, None]
    edges = np.arange(n_in)[None, :]
    overlap = np.clip(np.minimum(lo + size, edges + 1) - np.maximum(lo, edges), 0.0, None)
    return overlap / size


def downscale(image: np.ndarray, weight: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Area-average by `factor`: each output pixel is the weighted mean of the input area it
    covers (invalid pixels do not count) and its weight the area's valid share.

    Output pixels are square, `s = width / new width` input pixels wide (`downscaled_size`), and
    centred on the image: a camera with the same field of view and the new size sees exactly
    these areas. When `factor` divides the size they are the `factor` x `factor` blocks;
    otherwise the top and bottom rows may reach up to half an output pixel past the image (that
    part counts as invalid)."""
    if factor == 1:
        return image, weight
    if factor < 1:
        raise CaptureError(f"downscale = {factor} must be >= 1")
    h, w = weight.shape
    new_w, new_h = downscaled_size(w, h, factor)
    size = w / new_w
    rows = _box(new_h, h, size, (h - new_h * size) / 2)
    cols = _box(new_w, w, size, 0.0)
    w_mean = rows @ weight.astype(np.float64) @ cols.T
    weighted = image.astype(np.float64) * weight[..., None]
    # two matrix products (BLAS): `np.einsum` without a plan looped in Python's C, about 45 s a
    # 3000x2000 view, the time growing with the cube of the side
    by_rows = (rows @ weighted.reshape(h, -1)).reshape(new_h, w, -1)
    sums = cols @ by_rows  # (new_w, w) @ (new_h, w, c): (new_h, new_w, c)
    out = np.where(w_mean[..., None] > 0, sums / np.maximum(w_mean[..., None], 1e-12), 0.0)
    return out.astype(np.float32), w_mean.astype(np.float32)
