"""Image files written through OpenImageIO with a chosen pixel type and attributes."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _oiio_write(path: Path, pixels: np.ndarray, fmt, **attributes) -> Path:
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], fmt)
    for name, value in attributes.items():
        spec.attribute(name, value)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(pixels)
    out.close()
    return path
