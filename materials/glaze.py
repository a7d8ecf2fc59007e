"""`glaze`: a dielectric coat (Beckmann / Cook-Torrance, Fresnel-weighted) over a pigment.

With `v = wi` (towards the viewer), `l = wo`, `spec = D G / (4 (n.l)(n.v))` and
`rho_d = pigment / pi * OrenNayar(sigma)`:

- `coupling = "paper"` (the paper's, Blender's Fresnel-mix): `f = (1 - F(n.v)) rho_d + F(n.v) spec`;
- `coupling = "reciprocal"`: `f = F(v.h) spec + (1 - F(n.l)) (1 - F(n.v)) rho_d`;

with `F` Schlick's (`fresnel = "schlick"`) or the exact dielectric one (`"exact"`). Sampling picks a
lobe with probability from an estimate of the lobes' weights, then samples Beckmann half-vectors
(Walter et al. 2007) or a cosine-weighted direction; `pdf` is the matching mixture. Sampling
decisions are detached from the AD graph; the returned weight is `f cos / detach(pdf)`.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ._plugin import read_choice, read_float, read_texture
from .microfacet import beckmann_d, cook_torrance_g, fresnel, oren_nayar, sample_beckmann
from .params import GLAZE_PARAMS

COUPLINGS = ("paper", "reciprocal")
FRESNELS = ("schlick", "exact")
_GLOSSY = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
_DIFFUSE = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
# A lobe is never sampled with probability below this: keeps both lobes reachable for MIS.
_MIN_LOBE_PROB = 0.05


class Glaze(mi.BSDF):
    """Glazed ceramic. Parameters: see `materials.params.GLAZE_PARAMS`; options `coupling`,
    `fresnel`."""

    PARAMS = GLAZE_PARAMS

    def __init__(self, props: mi.Properties):
        mi.BSDF.__init__(self, props)
        self.pigment = read_texture(props, self.PARAMS["pigment"], "glaze")
        self.sigma = read_float(props, self.PARAMS["sigma"], "glaze")
        self.roughness = read_float(props, self.PARAMS["roughness"], "glaze")
        self.ior = read_float(props, self.PARAMS["ior"], "glaze")
        self.coupling = read_choice(props, "coupling", COUPLINGS, "glaze")
        self.fresnel = read_choice(props, "fresnel", FRESNELS, "glaze")
        self.m_components = [_GLOSSY, _DIFFUSE]
        self.m_flags = _GLOSSY | _DIFFUSE

    # Lobes ----------------------------------------------------------------------------------------

    def _lobes(self, si, wo, active):
        """`(specular f cos, diffuse f cos)` in the local frame, both zero where invalid."""
        wi = si.wi
        cos_v, cos_l = mi.Frame3f.cos_theta(wi), mi.Frame3f.cos_theta(wo)
        active &= (cos_v > 0) & (cos_l > 0)
        h = dr.normalize(wi + wo)
        v_dot_h = dr.dot(wi, h)

        # Specular: D G / (4 (n.l)(n.v)) times cos(theta_l)
        d = beckmann_d(h.z, self.roughness)
        g = cook_torrance_g(h.z, cos_v, cos_l, v_dot_h)
        spec = d * g / (4.0 * dr.maximum(cos_v, 1e-12))

        # Diffuse pigment: Oren-Nayar times cos(theta_l)
        pigment = self.pigment.eval(si, active)
        diffuse = pigment * (dr.inv_pi * oren_nayar(wi, wo, self.sigma) * cos_l)

        # Fresnel coupling of the two lobes
        f_v = fresnel(cos_v, self.ior, self.fresnel)
        if self.coupling == "paper":
            spec, diffuse = f_v * spec, (1.0 - f_v) * diffuse
        else:
            f_h = fresnel(v_dot_h, self.ior, self.fresnel)
            f_l = fresnel(cos_l, self.ior, self.fresnel)
            spec, diffuse = f_h * spec, (1.0 - f_l) * (1.0 - f_v) * diffuse
        return dr.select(active, spec, 0.0), dr.select(active, diffuse, 0.0)

    def _spec_prob(self, ctx, si, active):
        """Probability of sampling the specular lobe (detached), 0 or 1 if a lobe is disabled."""
        has_spec = ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0)
        has_diff = ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 1)
        if not has_diff:
            return mi.Float(1.0 if has_spec else 0.0)
        if not has_spec:
            return mi.Float(0.0)
        with dr.suspend_grad():
            f_v = fresnel(mi.Frame3f.cos_theta(si.wi), self.ior, self.fresnel)
            w_diff = (1.0 - f_v) * dr.mean(self.pigment.eval(si, active))
            prob = f_v / dr.maximum(f_v + w_diff, 1e-12)
            return dr.clip(prob, _MIN_LOBE_PROB, 1.0 - _MIN_LOBE_PROB)

    def _pdfs(self, si, wo, alpha):
        """Densities of the two sampling strategies (detached)."""
        wi = si.wi
        valid = (mi.Frame3f.cos_theta(wi) > 0) & (mi.Frame3f.cos_theta(wo) > 0)
        h = dr.normalize(wi + wo)
        pdf_spec = beckmann_d(h.z, alpha) * h.z / (4.0 * dr.maximum(dr.dot(wo, h), 1e-12))
        pdf_diff = mi.warp.square_to_cosine_hemisphere_pdf(wo)
        return dr.select(valid, pdf_spec, 0.0), dr.select(valid, pdf_diff, 0.0)

    def _mixture_pdf(self, ctx, si, wo, active):
        with dr.suspend_grad():
            p_spec = self._spec_prob(ctx, si, active)
            pdf_spec, pdf_diff = self._pdfs(si, wo, self.roughness)
            return dr.select(active, p_spec * pdf_spec + (1.0 - p_spec) * pdf_diff, 0.0)

    def _enabled_value(self, ctx, spec, diffuse):
        value = mi.Color3f(0.0)
        if ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0):
            value += spec
        if ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 1):
            value += diffuse
        return value

    # BSDF interface -------------------------------------------------------------------------------

    def sample(self, ctx, si, sample1, sample2, active=True):
        bs = dr.zeros(mi.BSDFSample3f)
        active &= mi.Frame3f.cos_theta(si.wi) > 0
        with dr.suspend_grad():
            p_spec = self._spec_prob(ctx, si, active)
            pick_spec = sample1 < p_spec
            h, _ = sample_beckmann(sample2, self.roughness)
            wo_spec = mi.reflect(si.wi, h)
            wo_diff = mi.warp.square_to_cosine_hemisphere(sample2)
            bs.wo = dr.select(pick_spec, wo_spec, wo_diff)
        bs.eta = 1.0
        bs.sampled_component = dr.select(pick_spec, mi.UInt32(0), mi.UInt32(1))
        bs.sampled_type = dr.select(
            pick_spec,
            mi.UInt32(+mi.BSDFFlags.GlossyReflection),
            mi.UInt32(+mi.BSDFFlags.DiffuseReflection),
        )
        bs.pdf = self._mixture_pdf(ctx, si, bs.wo, active)
        spec, diffuse = self._lobes(si, bs.wo, active)
        value = self._enabled_value(ctx, spec, diffuse)
        valid = active & (bs.pdf > 0)
        bs.pdf = dr.select(valid, bs.pdf, 0.0)
        return bs, dr.select(valid, value / dr.maximum(bs.pdf, 1e-20), 0.0)

    def eval(self, ctx, si, wo, active=True):
        spec, diffuse = self._lobes(si, wo, active)
        return self._enabled_value(ctx, spec, diffuse)

    def pdf(self, ctx, si, wo, active=True):
        return self._mixture_pdf(ctx, si, wo, active)

    def eval_pdf(self, ctx, si, wo, active=True):
        return self.eval(ctx, si, wo, active), self._mixture_pdf(ctx, si, wo, active)

    def traverse(self, callback):
        callback.put("pigment", self.pigment, mi.ParamFlags.Differentiable)
        for name in ("sigma", "roughness", "ior"):
            callback.put(name, getattr(self, name), mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        dr.make_opaque(self.sigma, self.roughness, self.ior)

    def to_string(self):
        return (
            f"Glaze[roughness={self.roughness}, ior={self.ior}, sigma={self.sigma}, "
            f"coupling={self.coupling}, fresnel={self.fresnel}]"
        )
