"""`glaze`: a dielectric coat (Beckmann / Cook-Torrance, Fresnel-weighted) over a pigment.

With `v = wi` (towards the viewer), `l = wo`, `spec = D G / (4 (n.l)(n.v))` and
`rho_d = pigment / pi * OrenNayar(sigma)` (or OpenPBR's EON with roughness `sigma`, `diffuse =
"eon"`):

- `coupling = "paper"` (the paper's, Blender's Fresnel-mix): `f = (1 - F(n.v)) rho_d + F(n.v) spec`;
- `coupling = "reciprocal"`: `f = F(v.h) spec + (1 - F(n.l)) (1 - F(n.v)) rho_d`;

with `F` Schlick's (`fresnel = "schlick"`) or the exact dielectric one (`"exact"`).

The paper's two noises are off unless asked for, and then they are declared parameters:
`pigment_noise` scales the pigment by `1 + a (2 fbm(uv) - 1)`, and `normal_noise` tilts the coat's
normal by `a` times the slope of an fbm height (per noise cell); their scales (`*_scale`, noise
cells per UV unit) and `noise_seed` are fixed options.

Sampling picks a
lobe with probability from an estimate of the lobes' weights (at least `_NARROW_LOBE_PROB` for a
narrow specular lobe, which emitter sampling cannot find), then samples Beckmann half-vectors
(Walter et al. 2007) or a cosine-weighted direction; `pdf` is the matching mixture. Sampling
decisions are detached from the AD graph; the returned weight is `f cos / detach(pdf)`.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ._plugin import read_float, read_option, read_params
from .microfacet import beckmann_d, cook_torrance_g, eon, fresnel, oren_nayar, sample_beckmann
from .noise import fbm
from .params import GLAZE

_GLOSSY = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
_DIFFUSE = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
# A lobe is never sampled with probability below this: keeps both lobes reachable for MIS.
_MIN_LOBE_PROB = 0.05
# A narrow specular lobe is sampled with probability at least `_NARROW_LOBE_PROB` at roughness
# `_NARROW_ALPHA` and below, a share that falls linearly to none at `_WIDE_ALPHA`. Its weight
# estimate (Fresnel against the pigment: 0.12 for a mid-grey glaze at normal incidence) gave a
# highlight a few BSDF samples a pixel, where emitter sampling cannot find a lobe narrower than
# the light: at alpha 0.02 on the recovery sweep's sphere (three 160x120 views) a 16-spp
# gradient's Newton step had an sd of 151 % of alpha, 45 % with this share (the torus 303 % and
# 86 %); at alpha 0.25 a share of 0.6 changed nothing (BENCHMARKS, "A narrow lobe's samples").
# Diffuse light keeps emitter sampling.
_NARROW_LOBE_PROB, _NARROW_ALPHA, _WIDE_ALPHA = 0.75, 0.05, 0.2
# UV step of the finite differences that give the normal noise's slope; octaves of both noises.
_NOISE_EPS = 1e-4
_NOISE_OCTAVES = 4


class Glaze(mi.BSDF):
    """Glazed ceramic. Parameters and options: see `materials.params.GLAZE`."""

    DECL = GLAZE
    PARAMS = GLAZE.params

    def __init__(self, props: mi.Properties):
        mi.BSDF.__init__(self, props)
        self.pigment, self.sigma, self.roughness, self.ior = read_params(
            props, GLAZE, "pigment", "sigma", "roughness", "ior"
        )
        options = {k: read_option(props, o, "glaze") for k, o in GLAZE.options.items()}
        self.coupling, self.fresnel = options["coupling"], options["fresnel"]
        self.diffuse = options["diffuse"]
        self.pigment_noise = self.normal_noise = None
        if "pigment_noise" in props:
            self.pigment_noise = read_float(props, self.PARAMS["pigment_noise"], "glaze")
            self.pigment_noise_scale = options["pigment_noise_scale"]
        if "normal_noise" in props:
            self.normal_noise = read_float(props, self.PARAMS["normal_noise"], "glaze")
            self.normal_noise_scale = options["normal_noise_scale"]
        self.noise_seed = options["noise_seed"]
        self.m_components = [_GLOSSY, _DIFFUSE]
        self.m_flags = _GLOSSY | _DIFFUSE
        if self.pigment_noise is not None or self.normal_noise is not None:
            self.m_flags |= mi.BSDFFlags.SpatiallyVarying

    # Noises ---------------------------------------------------------------------------------------

    def eval_pigment(self, si, active=True):
        """The pigment at `si`, its noise applied (what exports bake to a texture)."""
        pigment = self.pigment.eval(si, active)
        if self.pigment_noise is None:
            return pigment
        noise = fbm(si.uv, self.pigment_noise_scale, _NOISE_OCTAVES, self.noise_seed)
        return dr.clip(pigment * (1.0 + self.pigment_noise * (2.0 * noise - 1.0)), 0.0, 1.0)

    def _coat_frame(self, si):
        """The noise-tilted normal's frame in local coordinates, or None without normal noise."""
        if self.normal_noise is None:
            return None
        scale, seed = self.normal_noise_scale, self.noise_seed + 1
        f0 = fbm(si.uv, scale, _NOISE_OCTAVES, seed)
        du = fbm(si.uv + mi.Vector2f(_NOISE_EPS, 0.0), scale, _NOISE_OCTAVES, seed) - f0
        dv = fbm(si.uv + mi.Vector2f(0.0, _NOISE_EPS), scale, _NOISE_OCTAVES, seed) - f0
        slope = self.normal_noise / (_NOISE_EPS * scale)  # noise slope per cell times amount
        return mi.Frame3f(dr.normalize(mi.Vector3f(-slope * du, -slope * dv, 1.0)))

    def _in_coat(self, si, wo, active):
        """(si, wo, active) expressed in the coat's frame (unchanged without normal noise)."""
        frame = self._coat_frame(si)
        if frame is None:
            return si, wo, active
        tilted = mi.SurfaceInteraction3f(si)
        tilted.wi = frame.to_local(si.wi)
        wo_t = frame.to_local(wo)
        active = active & (mi.Frame3f.cos_theta(tilted.wi) * mi.Frame3f.cos_theta(si.wi) > 0)
        active &= mi.Frame3f.cos_theta(wo_t) * mi.Frame3f.cos_theta(wo) > 0
        return tilted, wo_t, active

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
        pigment = self.eval_pigment(si, active)
        if self.diffuse == "eon":
            diffuse = eon(wi, wo, self.sigma, pigment) * cos_l
        else:
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
            w_diff = (1.0 - f_v) * dr.mean(self.eval_pigment(si, active))
            prob = f_v / dr.maximum(f_v + w_diff, 1e-12)
            narrow = dr.clip((_WIDE_ALPHA - self.roughness) / (_WIDE_ALPHA - _NARROW_ALPHA), 0, 1)
            prob = dr.maximum(prob, _NARROW_LOBE_PROB * narrow)
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
        frame = self._coat_frame(si)
        if frame is None:
            return self._sample(ctx, si, sample1, sample2, active)
        tilted = mi.SurfaceInteraction3f(si)
        tilted.wi = frame.to_local(si.wi)
        active &= mi.Frame3f.cos_theta(tilted.wi) * mi.Frame3f.cos_theta(si.wi) > 0
        bs, weight = self._sample(ctx, tilted, sample1, sample2, active)
        bs.wo = frame.to_world(bs.wo)
        valid = mi.Frame3f.cos_theta(bs.wo) > 0
        bs.pdf = dr.select(valid, bs.pdf, 0.0)
        return bs, dr.select(valid, weight, 0.0)

    def _sample(self, ctx, si, sample1, sample2, active):
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
        si, wo, active = self._in_coat(si, wo, active)
        spec, diffuse = self._lobes(si, wo, active)
        return self._enabled_value(ctx, spec, diffuse)

    def pdf(self, ctx, si, wo, active=True):
        si, wo, active = self._in_coat(si, wo, active)
        return self._mixture_pdf(ctx, si, wo, active)

    def eval_pdf(self, ctx, si, wo, active=True):
        si, wo, active = self._in_coat(si, wo, active)
        spec, diffuse = self._lobes(si, wo, active)
        return self._enabled_value(ctx, spec, diffuse), self._mixture_pdf(ctx, si, wo, active)

    def _scalars(self):
        names = ["sigma", "roughness", "ior", "pigment_noise", "normal_noise"]
        return {n: getattr(self, n) for n in names if getattr(self, n) is not None}

    def traverse(self, callback):
        callback.put("pigment", self.pigment, mi.ParamFlags.Differentiable)
        for name, value in self._scalars().items():
            callback.put(name, value, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        dr.make_opaque(*self._scalars().values())

    def to_string(self):
        return (
            f"Glaze[roughness={self.roughness}, ior={self.ior}, sigma={self.sigma}, "
            f"coupling={self.coupling}, fresnel={self.fresnel}, diffuse={self.diffuse}]"
        )
