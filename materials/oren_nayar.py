"""`oren_nayar`: a rough diffuse BSDF (clay, lime scale, stains).

`diffuse = "qualitative"` (the default): `f cos = reflectance / pi * (A + B max(0, cos dphi) sin a
tan b) * cos(theta_o)`, the qualitative Oren-Nayar. `diffuse = "eon"`: OpenPBR's energy-preserving
Oren-Nayar with `sigma` its roughness (`microfacet.eon`). Sampled cosine-weighted. `sigma = 0` is
Lambert in both, identical to Mitsuba's `diffuse`. One-sided, like Mitsuba's own BSDFs (wrap in
`twosided` for a sheet).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ._plugin import read_option, read_params
from .microfacet import eon, oren_nayar
from .params import OREN_NAYAR

_FLAGS = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide


class OrenNayar(mi.BSDF):
    """Rough diffuse reflection. Parameters: see `materials.params.OREN_NAYAR_PARAMS`."""

    PARAMS = OREN_NAYAR.params

    def __init__(self, props: mi.Properties):
        mi.BSDF.__init__(self, props)
        self.reflectance, self.sigma = read_params(props, OREN_NAYAR, "reflectance", "sigma")
        self.diffuse = read_option(props, OREN_NAYAR.options["diffuse"], "oren_nayar")
        self.m_components = [_FLAGS]
        self.m_flags = _FLAGS

    def _value(self, si, wo, active):
        """`f cos` in the local frame, zero outside the upper hemisphere."""
        wi = si.wi
        active &= (mi.Frame3f.cos_theta(wi) > 0) & (mi.Frame3f.cos_theta(wo) > 0)
        albedo = self.reflectance.eval(si, active)
        if self.diffuse == "eon":
            value = eon(wi, wo, self.sigma, albedo) * mi.Frame3f.cos_theta(wo)
        else:
            value = albedo * (dr.inv_pi * oren_nayar(wi, wo, self.sigma) * mi.Frame3f.cos_theta(wo))
        return dr.select(active, value, 0.0), active

    def sample(self, ctx, si, sample1, sample2, active=True):
        bs = dr.zeros(mi.BSDFSample3f)
        enabled = ctx.is_enabled(mi.BSDFFlags.DiffuseReflection)
        bs.wo = mi.warp.square_to_cosine_hemisphere(sample2)
        bs.pdf = mi.warp.square_to_cosine_hemisphere_pdf(bs.wo)
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
        bs.sampled_component = mi.UInt32(0)
        value, valid = self._value(si, bs.wo, active)
        valid &= enabled & (bs.pdf > 0)
        bs.pdf = dr.select(valid, bs.pdf, 0.0)
        return bs, dr.select(valid, value / dr.detach(dr.maximum(bs.pdf, 1e-20)), 0.0)

    def eval(self, ctx, si, wo, active=True):
        if not ctx.is_enabled(mi.BSDFFlags.DiffuseReflection):
            return mi.Color3f(0.0)
        return self._value(si, wo, active)[0]

    def pdf(self, ctx, si, wo, active=True):
        if not ctx.is_enabled(mi.BSDFFlags.DiffuseReflection):
            return mi.Float(0.0)
        valid = active & (mi.Frame3f.cos_theta(si.wi) > 0) & (mi.Frame3f.cos_theta(wo) > 0)
        return dr.select(valid, mi.warp.square_to_cosine_hemisphere_pdf(wo), 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

    def traverse(self, callback):
        callback.put("reflectance", self.reflectance, mi.ParamFlags.Differentiable)
        callback.put("sigma", self.sigma, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        dr.make_opaque(self.sigma)

    def to_string(self):
        return (
            f"OrenNayar[reflectance={self.reflectance}, sigma={self.sigma}, diffuse={self.diffuse}]"
        )
