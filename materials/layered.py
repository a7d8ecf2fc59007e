"""`layered`: BSDFs stacked by masks, one layer chosen per interaction, with bump from the masks.

Layers are listed bottom to top in `layers` ("clay, glaze, lime"); each is a nested BSDF property of
that name (any BSDF, `layered` included) and every layer but the bottom one has a mask texture
`<name>_mask` (usually `fbm`) with values in [0, 1]. Layer k's share is
`w_k = m_k * prod_{j > k} (1 - m_j)` (the bottom mask is 1), the Russian roulette of the paper
walked from the top.

One layer is chosen per interaction with probability `p_k = (1 - K MIN_PICK) detach(w_k) +
MIN_PICK` (K layers), and its BSDF is evaluated alone (`dr.switch`: lanes run only their layer's
code) with weight `w_k / p_k`, about 1 but carrying the masks' gradients. Every layer keeps a
chance of `MIN_PICK`: a layer whose share is exactly 0 (a fitted mask's texel on its bound) is
still picked now and then, so the gradient of its share there has the layer's own term (picked with
its share alone, a layer of share 0 is never evaluated, and its mask's gradient there lacks that
term: a brighter layer's texel at 0 would be pushed further down). The choice comes from a hash of
the interaction (its position and UV, salted by the stack's layer names), so `eval`, `pdf` and
`sample` at one interaction agree on the layer; over the hits of a pixel the choice is uniform, so
the expected BSDF is `sum_k w_k f_k` (equal to `blendbsdf` for a constant two-layer mask).

With `bump > 0` the masks form a height field `H = bump * sum_{k > 0} m_k` (metres) that bends the
shading normal, giving each layer visible thickness. The bumped normal is built in the tangent
plane of the smooth shading normal (not the geometric one), so a coarse mesh does not facet.
"""

from __future__ import annotations

import zlib

import drjit as dr
import mitsuba as mi

from ._plugin import read_float
from .params import LAYERED_PARAMS

# UV step of the finite differences that give the height field's slope.
_BUMP_EPS = 1e-4
#: The least probability of picking any layer (see the module): the samples spent on a layer of
#: share 0 (a cup's four layers, its masks mostly 0 or 1: under 1 %) return 0.
MIN_PICK = 0.002


def _uniform(si, salt: int):
    """A deterministic number in [0, 1) per interaction: a hash of its position, UV and `salt`."""
    bits = [dr.reinterpret_array(mi.UInt32, c) for c in (si.p.x, si.p.y, si.p.z, si.uv.x, si.uv.y)]
    h = mi.UInt32((salt * 0x9E3779B9) & 0xFFFFFFFF)
    for b in bits:
        h = (h ^ b) * 0x85EBCA6B
        h ^= h >> 13
        h *= 0xC2B2AE35
        h ^= h >> 16
    return mi.Float(h >> 8) * (1.0 / 16777216.0)


class Layered(mi.BSDF):
    """A mask-weighted stack of BSDFs. Parameters: `bump` (see `materials.params.LAYERED_PARAMS`),
    and each layer's and mask's own under `<layer>.` and `<layer>.mask.`."""

    PARAMS = LAYERED_PARAMS

    def __init__(self, props: mi.Properties):
        mi.BSDF.__init__(self, props)
        if "layers" not in props:
            raise ValueError('layered plugin: needs "layers", the layer names bottom to top')
        self.names = [n.strip() for n in props.get("layers").split(",") if n.strip()]
        if len(self.names) < 1 or len(set(self.names)) != len(self.names):
            raise ValueError(f"layered plugin: layers = {self.names}; give distinct names")
        self.layers, self.masks = [], []
        for k, name in enumerate(self.names):
            if name not in props:
                raise ValueError(f"layered plugin: layer {name!r} has no BSDF property {name!r}")
            self.layers.append(props.get(name))
            mask = f"{name}_mask"
            if k == 0 and mask in props:
                raise ValueError(f"layered plugin: the bottom layer {name!r} takes no mask")
            if k > 0 and mask not in props:
                raise ValueError(f"layered plugin: layer {name!r} needs a mask texture {mask!r}")
            self.masks.append(props.get_texture(mask) if k > 0 else None)
        self.bump = read_float(props, self.PARAMS["bump"], "layered") if "bump" in props else None
        # per-stack salt (from the layer names, so it does not depend on loading order): nested
        # stacks choose independently
        self.salt = zlib.crc32(",".join(self.names).encode()) | 1
        self.m_components = [c for layer in self.layers for c in layer.m_components]
        self.m_flags = 0
        for layer in self.layers:
            self.m_flags |= layer.m_flags
        if len(self.layers) > 1:
            self.m_flags |= mi.BSDFFlags.SpatiallyVarying

    # Layer choice ---------------------------------------------------------------------------------

    def _mask_values(self, si, active):
        return [mask.eval_1(si, active) for mask in self.masks[1:]]

    def shares(self, si, active=True):
        """`[w_0, ..., w_top]`: each layer's share at `si` (they sum to 1)."""
        return self._shares(self._mask_values(si, active))

    @staticmethod
    def _shares(mask_values):
        masks = [mi.Float(1.0), *mask_values]
        shares, remaining = [None] * len(masks), mi.Float(1.0)
        for k in reversed(range(len(masks))):
            shares[k] = masks[k] * remaining
            remaining = remaining * (1.0 - masks[k])
        return shares

    def _prepare(self, si, active):
        """(layer index, weight `w_k / p_k`, interaction in the bumped frame)."""
        mask_values = self._mask_values(si, active)
        shares = self._shares(mask_values)
        keep = 1.0 - len(shares) * MIN_PICK
        picks = [keep * dr.detach(w) + MIN_PICK for w in shares]
        u = _uniform(si, self.salt)
        index, weight, cumulative = mi.UInt32(0), mi.Float(0.0), mi.Float(0.0)
        for k, p in enumerate(picks[:-1]):
            cumulative += p
            index = dr.select(u >= cumulative, mi.UInt32(k + 1), index)
        for k, (w, p) in enumerate(zip(shares, picks, strict=True)):
            weight = dr.select(index == k, w / p, weight)
        return index, weight, self._bumped(si, mask_values, active)

    # Bump mapping ---------------------------------------------------------------------------------

    def _bumped(self, si, mask_values, active):
        """A copy of `si` whose shading frame is bent by the height field (or `si` itself)."""
        if self.bump is None or not mask_values:
            return si
        h0 = self.bump * sum(mask_values)
        shifted = mi.SurfaceInteraction3f(si)
        shifted.uv = si.uv + mi.Vector2f(_BUMP_EPS, 0.0)
        dh_du = (self.bump * sum(self._mask_values(shifted, active)) - h0) / _BUMP_EPS
        shifted.uv = si.uv + mi.Vector2f(0.0, _BUMP_EPS)
        dh_dv = (self.bump * sum(self._mask_values(shifted, active)) - h0) / _BUMP_EPS

        n = si.sh_frame.n
        dp_du = si.dp_du + n * (dh_du - dr.dot(n, si.dp_du))
        dp_dv = si.dp_dv + n * (dh_dv - dr.dot(n, si.dp_dv))
        normal = dr.cross(dp_du, dp_dv)
        length = dr.norm(normal)
        normal = dr.select(length > 1e-12, normal / dr.maximum(length, 1e-12), n)
        normal = dr.select(dr.dot(normal, n) < 0, -normal, normal)

        bumped = mi.SurfaceInteraction3f(si)
        bumped.sh_frame = mi.Frame3f(normal)
        bumped.wi = bumped.to_local(si.to_world(si.wi))
        return bumped

    # BSDF interface -------------------------------------------------------------------------------

    def sample(self, ctx, si, sample1, sample2, active=True):
        index, weight, bumped = self._prepare(si, active)
        bs, value = dr.switch(
            index, [layer.sample for layer in self.layers], ctx, bumped, sample1, sample2, active
        )
        if bumped is not si:
            wo = si.to_local(bumped.to_world(bs.wo))
            valid = mi.Frame3f.cos_theta(wo) * mi.Frame3f.cos_theta(bs.wo) > 0
            bs.wo = wo
            bs.pdf = dr.select(valid, bs.pdf, 0.0)
            value = dr.select(valid, value, 0.0)
        return bs, value * weight

    def eval(self, ctx, si, wo, active=True):
        index, weight, bumped = self._prepare(si, active)
        wo_b, active = self._to_bumped(si, bumped, wo, active)
        value = dr.switch(index, [layer.eval for layer in self.layers], ctx, bumped, wo_b, active)
        return dr.select(active, value * weight, 0.0)

    def pdf(self, ctx, si, wo, active=True):
        index, _, bumped = self._prepare(si, active)
        wo_b, active = self._to_bumped(si, bumped, wo, active)
        pdf = dr.switch(index, [layer.pdf for layer in self.layers], ctx, bumped, wo_b, active)
        return dr.select(active, pdf, 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        index, weight, bumped = self._prepare(si, active)
        wo_b, active = self._to_bumped(si, bumped, wo, active)
        value, pdf = dr.switch(
            index, [layer.eval_pdf for layer in self.layers], ctx, bumped, wo_b, active
        )
        return dr.select(active, value * weight, 0.0), dr.select(active, pdf, 0.0)

    @staticmethod
    def _to_bumped(si, bumped, wo, active):
        """`wo` in the bumped frame; inactive where it crosses a horizon between the frames."""
        if bumped is si:
            return wo, active
        wo_b = bumped.to_local(si.to_world(wo))
        return wo_b, active & (mi.Frame3f.cos_theta(wo) * mi.Frame3f.cos_theta(wo_b) > 0)

    def traverse(self, callback):
        if self.bump is not None:
            callback.put("bump", self.bump, mi.ParamFlags.Differentiable)
        for name, layer, mask in zip(self.names, self.layers, self.masks, strict=True):
            callback.put(name, layer, mi.ParamFlags.Differentiable)
            if mask is not None:
                callback.put(f"{name}.mask", mask, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        if self.bump is not None:
            dr.make_opaque(self.bump)

    def to_string(self):
        return f"Layered[layers={self.names}, bump={self.bump}]"
