"""`fbm`: a layer mask `m(uv) = texture(uv) * sigmoid((fbm(uv * scale) - threshold) / softness)`.

The fbm noise (`materials.noise.fbm`) is evaluated in UV space with a fixed number of octaves and
a seed, so a mask can be baked to a texture. `texture` is optional (a painted mask, default 1);
`threshold` and `softness` are differentiable.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ._plugin import read_option, read_params
from .noise import fbm
from .params import FBM


class FbmMask(mi.Texture):
    """Scalar mask texture in [0, 1]. Options: `scale` (noise cells per UV unit, integer so that
    the noise tiles), `octaves`, `seed`; parameters: see `materials.params.FBM`."""

    DECL = FBM
    PARAMS = FBM.params

    def __init__(self, props: mi.Properties):
        mi.Texture.__init__(self, props)
        self.scale, self.octaves, self.seed = (
            read_option(props, FBM.options[k], "fbm") for k in ("scale", "octaves", "seed")
        )
        self.threshold, self.softness = read_params(props, FBM, "threshold", "softness")
        self.texture = props.get_texture("texture") if "texture" in props else None

    def noise(self, uv):
        """The raw fbm value (about [0, 1]) at `uv`."""
        return fbm(uv, self.scale, self.octaves, self.seed)

    def eval_1(self, si, active=True):
        # sigmoid((f - t) / s); the clip keeps exp and its derivative finite for sharp edges
        # (sigmoid(+-40) is 0 or 1 to float32 precision anyway)
        x = dr.clip((self.threshold - self.noise(si.uv)) / self.softness, -40.0, 40.0)
        value = dr.rcp(1.0 + dr.exp(x))
        if self.texture is not None:
            value *= self.texture.eval_1(si, active)
        return value

    def eval(self, si, active=True):
        return mi.Color3f(self.eval_1(si, active))

    def eval_3(self, si, active=True):
        return mi.Color3f(self.eval_1(si, active))

    def mean(self):
        return 0.5

    def is_spatially_varying(self):
        return True

    def traverse(self, callback):
        callback.put("threshold", self.threshold, mi.ParamFlags.Differentiable)
        callback.put("softness", self.softness, mi.ParamFlags.Differentiable)
        if self.texture is not None:
            callback.put("texture", self.texture, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        dr.make_opaque(self.threshold, self.softness)

    def to_string(self):
        return (
            f"FbmMask[scale={self.scale}, octaves={self.octaves}, seed={self.seed}, "
            f"threshold={self.threshold}, softness={self.softness}]"
        )
