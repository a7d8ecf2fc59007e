"""`texels`: an image texture whose texels are one tensor parameter (`data`), looked up where
they are: bilinear, repeating, laid out and decoded as Mitsuba's `bitmap` reads the same file.

A fit writes a free texture's texels between renders, and renders are Dr.Jit frozen functions.
Mitsuba 3.9.1's `bitmap` keeps a second copy of its texels inside its Dr.Jit texture, refreshed
by `parameters_changed`; a reverse pass, which attaches derivatives to the texels inside the
recording, runs that refresh there, and the replays read stale memory: wrong images and
crashed reverse passes (Dr.Jit 1.5, LLVM). Here the lookups read the `data` tensor itself and
`parameters_changed` does nothing, so texels written into that tensor in place (a scatter) are
what the next replay reads. (A new tensor assigned between replays was read stale here too.)
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


class Texels(mi.Texture):
    """Properties: `filename` (any image Mitsuba's `bitmap` reads: 1 or 3 channels), `raw`
    (bool: no sRGB decoding of an 8-bit file; a mask's texels are linear). Parameter: `data`,
    the texels as a tensor (height, width, channels)."""

    def __init__(self, props: mi.Properties):
        mi.Texture.__init__(self, props)
        bitmap = mi.Bitmap(props["filename"])
        if props.get("raw", False):
            bitmap.set_srgb_gamma(False)  # an 8-bit file's values as they are
        grey = bitmap.pixel_format() in (mi.Bitmap.PixelFormat.Y, mi.Bitmap.PixelFormat.YA)
        pixel_format = mi.Bitmap.PixelFormat.Y if grey else mi.Bitmap.PixelFormat.RGB
        linear = bitmap.convert(pixel_format, mi.Struct.Type.Float32, srgb_gamma=False)
        shape = (linear.height(), linear.width(), linear.channel_count())
        self.data = mi.TensorXf(np.array(linear, dtype=np.float32).reshape(shape))

    def _lookup(self, si) -> list:
        """Each channel's value at `si.uv`: bilinear between the four nearest texel centres
        (texel (r, c) centred at uv ((c + 0.5) / width, (r + 0.5) / height)), wrapping."""
        height, width, channels = self.data.shape
        uv = si.uv - dr.floor(si.uv)  # repeat
        x = uv.x * width - 0.5
        y = uv.y * height - 0.5
        x0, y0 = dr.floor(x), dr.floor(y)
        wx, wy = x - x0, y - y0
        x0, y0 = mi.Int32(x0), mi.Int32(y0)
        x0 = dr.select(x0 < 0, x0 + width, x0)
        y0 = dr.select(y0 < 0, y0 + height, y0)
        x1 = dr.select(x0 + 1 >= width, x0 + 1 - width, x0 + 1)
        y1 = dr.select(y0 + 1 >= height, y0 + 1 - height, y0 + 1)
        corners = [(x0, y0, (1 - wx) * (1 - wy)), (x1, y0, wx * (1 - wy))]
        corners += [(x0, y1, (1 - wx) * wy), (x1, y1, wx * wy)]
        out = []
        for c in range(channels):
            value = mi.Float(0.0)
            for cx, cy, weight in corners:
                index = mi.UInt32((cy * width + cx) * channels + c)
                value += weight * dr.gather(mi.Float, self.data.array, index)
            out.append(value)
        return out

    def eval_1(self, si, active=True):
        values = self._lookup(si)
        return values[0] if len(values) == 1 else mi.luminance(mi.Color3f(*values))

    def eval(self, si, active=True):
        values = self._lookup(si)
        return mi.Color3f(values[0]) if len(values) == 1 else mi.Color3f(*values)

    def eval_3(self, si, active=True):
        return self.eval(si, active)

    def mean(self):
        return dr.mean(self.data.array)

    def resolution(self):
        return mi.ScalarVector2i(self.data.shape[1], self.data.shape[0])

    def is_spatially_varying(self):
        return True

    def traverse(self, callback):
        callback.put("data", self.data, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        pass

    def to_string(self):
        height, width, channels = self.data.shape
        return f"Texels[{width}x{height}, {channels} channels]"
