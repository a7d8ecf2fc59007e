"""Camera RAW to linear Rec.709 with rawpy (LibRaw's decoder), every step explicit.

The file's default crop (DNG DefaultCrop) is applied first. Black levels are subtracted per
channel and the white level scales to 1; sensels at the white level, or at a clipping plateau
below it (`clip_level`), are saturated; the Bayer mosaic is
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
from .files import require_utf8

#: A RAW whose pixels are this share or more at or below black carries no picture.
MAX_BLACK_SHARE = 0.99
#: A RAW file smaller than this many bits per sensel cannot hold its picture (lossless
#: compression of camera data reaches about 4 bits per sensel).
MIN_BITS_PER_SENSEL = 1.0
#: Sensels sharing the peak value (this share of them) mark a clipping plateau.
PLATEAU_SHARE = 1e-5


@dataclass(frozen=True)
class RawImage:
    """Camera RGB (H, W, 3), black-subtracted, white level = 1, before white balance; per-pixel
    saturation (any sensel of the superpixel at the white level); metadata."""

    camera_rgb: np.ndarray
    saturated: np.ndarray
    camera_wb: np.ndarray | None  # as-shot multipliers (R, G, B), G = 1; None: not recorded
    color_matrix: np.ndarray  # white-balanced camera RGB -> linear Rec.709 (3, 3)
    path: Path | None = None


def default_crop(sizes, shape: tuple[int, int]) -> tuple[int, int, int, int] | None:
    """(top, left, height, width) of the file's default crop (DNG DefaultCrop, LibRaw's first
    inset crop) inside the visible area of `shape`, or None when there is none or it is the whole
    area. LibRaw gives its origin in full-raw coordinates (the visible area's margins included);
    an origin that only fits as visible-area coordinates is read as such."""
    height, width = int(sizes.crop_height), int(sizes.crop_width)
    if height <= 0 or width <= 0:
        return None
    for top, left in (
        (sizes.crop_top_margin - sizes.top_margin, sizes.crop_left_margin - sizes.left_margin),
        (sizes.crop_top_margin, sizes.crop_left_margin),
    ):
        if 0 <= top and 0 <= left and top + height <= shape[0] and left + width <= shape[1]:
            if (top, left, height, width) == (0, 0, *shape):
                return None
            return int(top), int(left), height, width
    return None


def clip_level(mosaic: np.ndarray, black: float, white: float) -> float:
    """The raw value at which sensels clip: the white level, or lower when the data's peak is a
    plateau in the top quarter of the range (some cameras clip below their stated white level:
    a Blackmagic DNG peaks at 65472 for 65535). A plateau: at least `PLATEAU_SHARE` of the
    sensels (and 16) hold exactly the peak value."""
    peak = float(mosaic.max())
    if peak >= white or peak < black + 0.75 * (white - black):
        return white
    count = int(np.count_nonzero(mosaic == peak))
    return peak if count >= max(16, PLATEAU_SHARE * mosaic.size) else white


#: LibRaw's `sizes.flip`: what a viewer does with the sensor's picture.
RAW_FLIPS = {
    3: "turned 180 degrees",
    5: "turned 90 degrees anticlockwise",
    6: "turned 90 degrees clockwise",
}


def read_raw(path: str | Path) -> RawImage:
    """A RAW file's camera RGB (2x2 superpixels of its default crop), saturation and colour
    metadata, or a one-line `CaptureError`."""
    path = Path(path)
    require_utf8(path, CaptureError)
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
            sizes = raw.sizes
    except RuntimeError as err:  # rawpy: a linear DNG, sRAW or Foveon file ("not flat")
        raise CaptureError(
            f"{path}: not a Bayer mosaic ({err}); develop it to a linear 16-bit TIFF and declare "
            'encoding = "linear"'
        ) from None
    except (rawpy.LibRawError, OSError, ValueError) as err:
        raise CaptureError(
            f"{path}: LibRaw cannot decode this RAW file ({type(err).__name__}: {err}); "
            "convert it to DNG or TIFF and declare the encoding"
        ) from None
    if desc not in ("RGBG", "RGGB") or pattern.shape != (2, 2):
        raise CaptureError(f"{path}: colour filter {desc!r} is not a Bayer RGB mosaic")
    flip = int(getattr(sizes, "flip", 0) or 0)
    if flip in RAW_FLIPS:  # a camera held upright: viewers turn it, its sensels are as stored
        raise CaptureError(
            f"{path}: the camera recorded it {RAW_FLIPS[flip]} (viewers show it so), but its "
            "sensels are read as the sensor stored them; if its camera was set up on the photo "
            "as shown, develop it upright to a linear 16-bit TIFF (e.g. dcraw -4 -T) and "
            'declare encoding = "linear"; if on the sensor\'s own orientation, set its '
            "Orientation tag to 1 (exiftool -n -Orientation=1)"
        )
    size, sensels = path.stat().st_size, int(sizes.raw_width) * int(sizes.raw_height)
    if size * 8 < MIN_BITS_PER_SENSEL * sensels:  # LibRaw leaves the missing data undefined
        raise CaptureError(
            f"{path}: {size} bytes cannot hold {sizes.raw_width}x{sizes.raw_height} raw sensels: "
            "the file holds no usable picture (a thumbnail-only, metadata stub or truncated file?)"
        )
    crop = default_crop(sizes, mosaic.shape)
    if crop is not None:
        top, left, height, width = crop
        mosaic = mosaic[top : top + height, left : left + width]
        colors = colors[top : top + height, left : left + width]
    if min(mosaic.shape) < 2:
        raise CaptureError(f"{path}: the raw image is {mosaic.shape[1]}x{mosaic.shape[0]} sensels")
    level = black[colors]
    if np.mean(mosaic <= level) > MAX_BLACK_SHARE:
        raise CaptureError(
            f"{path}: {np.mean(mosaic <= level):.1%} of the raw pixels are at or below the black "
            "level: the file holds no usable picture (a thumbnail-only or metadata stub?)"
        )
    if white <= black.max():
        raise CaptureError(f"{path}: white level {white} is not above the black level")
    normalised = np.clip((mosaic - level) / (white - level), 0.0, None)
    saturated = mosaic >= clip_level(mosaic, float(black.max()), white)

    # 2x2 superpixels: R, the mean of the greens, B (the phase from the cropped colour indices)
    h, w = (s // 2 * 2 for s in mosaic.shape)
    channel_of = {"R": 0, "G": 1, "B": 2}
    sums = np.zeros((h // 2, w // 2, 3), np.float32)
    counts = np.zeros(3, np.float32)
    sat = np.zeros((h // 2, w // 2), bool)
    for i in range(2):
        for j in range(2):
            c = channel_of[desc[colors[i, j]]]
            sums[..., c] += normalised[i:h:2, j:w:2]
            counts[c] += 1
            sat |= saturated[i:h:2, j:w:2]
    if np.any(counts == 0):
        raise CaptureError(f"{path}: the 2x2 mosaic lacks a colour ({desc!r}); not a Bayer RAW")
    camera_rgb = (sums / counts).astype(np.float32)

    as_shot = None if not np.all(np.isfinite(wb)) or not np.any(wb) or wb[1] == 0 else wb / wb[1]
    if np.any(cmatrix):
        matrix = cmatrix
    elif np.any(rgb_xyz):
        matrix = camera_to_rec709(rgb_xyz)
    else:
        raise CaptureError(f"{path}: the file has no colour matrix to map camera RGB to Rec.709")
    return RawImage(camera_rgb, sat, as_shot, matrix, path)


def camera_to_rec709(rgb_xyz: np.ndarray) -> np.ndarray:
    """White-balanced camera RGB -> linear Rec.709 from a camera <- XYZ matrix, as LibRaw and
    dcraw make it: the camera's response to Rec.709 primaries, its rows scaled to sum 1 (white
    balance makes white (1, 1, 1)), inverted. (Scaling the inverse's rows instead kept greys
    grey but bent saturated colours: Rec.709 (0.5, 0.1, 0.1) came out (0.405, 0.042, 0.11).)"""
    from .color import XYZ_TO_REC709

    camera = np.asarray(rgb_xyz, np.float64)[:3] @ np.linalg.inv(XYZ_TO_REC709)
    camera /= camera.sum(axis=1, keepdims=True)
    return np.linalg.inv(camera)


def develop(raw: RawImage, white_balance: str | np.ndarray = "camera") -> np.ndarray:
    """Linear Rec.709 (H, W, 3) float32: white balance ("camera", "none" or RGB multipliers),
    then the colour matrix; negative values (out of gamut) are clipped to 0."""
    if isinstance(white_balance, str):
        multipliers = {"camera": raw.camera_wb, "none": np.ones(3)}[white_balance]
        if multipliers is None:
            raise CaptureError(
                f"{raw.path or 'the RAW file'}: the file records no as-shot white balance; set "
                "white_balance = [r, g, b] in [capture] (multipliers, G = 1)"
            )
    else:
        multipliers = np.asarray(white_balance, dtype=np.float64)
    balanced = raw.camera_rgb.astype(np.float32) * multipliers.astype(np.float32)
    developed = balanced @ raw.color_matrix.T.astype(np.float32)
    return np.clip(developed, 0.0, None).astype(np.float32)


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
