"""Camera RAW to linear Rec.709 with rawpy (LibRaw's decoder), every step explicit.

Black levels are subtracted per channel and the white level scales to 1; the Bayer mosaic is
demosaiced by 2x2 superpixels (each RGGB block becomes one pixel: exact linear values, half
resolution, no interpolation); the white balance is the camera's as-shot one (as rawpy reports it),
given multipliers, or none; the camera RGB is mapped to linear Rec.709 by the file's colour matrix
(LibRaw's `color_matrix`, whose rows sum to 1, so a balanced neutral stays neutral).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rawpy

from .errors import CaptureError

#: A RAW whose pixels are this share or more at or below black carries no picture.
MAX_BLACK_SHARE = 0.99


@dataclass(frozen=True)
class RawImage:
    """Camera RGB (H, W, 3), black-subtracted, white level = 1, before white balance; per-pixel
    saturation (any sensel of the superpixel at the white level); metadata."""

    camera_rgb: np.ndarray
    saturated: np.ndarray
    camera_wb: np.ndarray  # as-shot multipliers (R, G, B), G = 1
    color_matrix: np.ndarray  # white-balanced camera RGB -> linear Rec.709 (3, 3)


def read_raw(path: str | Path) -> RawImage:
    path = Path(path)
    if not path.exists():
        raise CaptureError(f"{path}: no such RAW file")
    try:
        with rawpy.imread(str(path)) as raw:
            mosaic = raw.raw_image_visible.astype(np.float32)
            colors = raw.raw_colors_visible.copy()
            pattern = raw.raw_pattern.copy()
            desc = raw.color_desc.decode()
            black = np.asarray(raw.black_level_per_channel, dtype=np.float32)
            white = float(raw.white_level)
            wb = np.asarray(raw.camera_whitebalance[:3], dtype=np.float64)
            cmatrix = np.asarray(raw.color_matrix, dtype=np.float64)[:, :3]
            rgb_xyz = np.asarray(raw.rgb_xyz_matrix, dtype=np.float64)[:3]
    except (rawpy.LibRawError, OSError, ValueError) as err:
        raise CaptureError(
            f"{path}: LibRaw cannot decode this RAW file ({type(err).__name__}: {err}); "
            "convert it to DNG or TIFF and declare the encoding"
        ) from None
    if desc not in ("RGBG", "RGGB") or pattern.shape != (2, 2):
        raise CaptureError(f"{path}: colour filter {desc!r} is not a Bayer RGB mosaic")
    level = black[colors]
    if np.mean(mosaic <= level) > MAX_BLACK_SHARE:
        raise CaptureError(
            f"{path}: {np.mean(mosaic <= level):.1%} of the raw pixels are at or below the black "
            "level: the file holds no usable picture (a thumbnail-only or metadata stub?)"
        )
    if white <= black.max():
        raise CaptureError(f"{path}: white level {white} is not above the black level")
    normalised = np.clip((mosaic - level) / (white - level), 0.0, None)
    saturated = mosaic >= white

    # 2x2 superpixels: R, the mean of the greens, B
    h, w = (s // 2 * 2 for s in mosaic.shape)
    channel_of = {"R": 0, "G": 1, "B": 2}
    sums = np.zeros((h // 2, w // 2, 3), np.float32)
    counts = np.zeros(3)
    sat = np.zeros((h // 2, w // 2), bool)
    for i in range(2):
        for j in range(2):
            c = channel_of[desc[pattern[i, j]]]
            sums[..., c] += normalised[i:h:2, j:w:2]
            counts[c] += 1
            sat |= saturated[i:h:2, j:w:2]
    camera_rgb = sums / counts

    if not np.any(wb) or wb[1] == 0:
        raise CaptureError(f"{path}: the file has no as-shot white balance; give multipliers")
    if np.any(cmatrix):
        matrix = cmatrix
    elif np.any(rgb_xyz):  # camera <- XYZ given: invert, then XYZ -> Rec.709
        from .color import XYZ_TO_REC709

        matrix = XYZ_TO_REC709 @ np.linalg.inv(rgb_xyz)
        matrix /= matrix.sum(axis=1, keepdims=True)
    else:
        raise CaptureError(f"{path}: the file has no colour matrix to map camera RGB to Rec.709")
    return RawImage(camera_rgb, sat, wb / wb[1], matrix)


def develop(raw: RawImage, white_balance: str | np.ndarray = "camera") -> np.ndarray:
    """Linear Rec.709 (H, W, 3) float32: white balance ("camera", "none" or RGB multipliers),
    then the colour matrix; negative values (out of gamut) are clipped to 0."""
    if isinstance(white_balance, str):
        multipliers = {"camera": raw.camera_wb, "none": np.ones(3)}[white_balance]
    else:
        multipliers = np.asarray(white_balance, dtype=np.float64)
    balanced = raw.camera_rgb * multipliers.astype(np.float32)
    return np.clip(balanced @ raw.color_matrix.T.astype(np.float32), 0.0, None)


def white_balance_from_patch(raw: RawImage, x: int, y: int, half: int = 6) -> np.ndarray:
    """Camera-space multipliers (G = 1) that make the mean of the box of `2 half` pixels centred
    at (x, y) of the developed (half-resolution) image neutral."""
    box = raw.camera_rgb[y - half : y + half, x - half : x + half].reshape(-1, 3)
    if box.size == 0:
        raise CaptureError(f"white-balance box at ({x}, {y}) is outside the image")
    mean = box.mean(axis=0).astype(np.float64)
    if np.any(mean <= 0):
        raise CaptureError(f"white-balance box at ({x}, {y}) is black in a channel")
    return mean[1] / mean
