"""Pure Dr.Jit functions shared by the BSDFs: Beckmann, Cook-Torrance, Fresnel, Oren-Nayar.

All directions are unit vectors in the local shading frame (normal = +z). Every function is safe at
the extremes the plugins allow (alpha >= 0.01, ior >= 1.01, cosines down to 0): no 0/0, no log(0).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

_TINY = 1e-12


def beckmann_d(cos_h, alpha):
    """Beckmann NDF `exp(((n.h)^2 - 1) / (a^2 (n.h)^2)) / (pi a^2 (n.h)^4)`, 0 below the horizon."""
    c2 = dr.maximum(cos_h * cos_h, _TINY)
    a2 = alpha * alpha
    # One exp of a log-space sum: the separate factor 1 / (pi a^2 c^4) overflows float32 (and its
    # derivative gives 0 * inf = NaN) near the horizon at small alpha, where D itself is 0.
    d = dr.exp((c2 - 1.0) / (a2 * c2) - dr.log(dr.pi * a2) - 2.0 * dr.log(c2))
    return dr.select(cos_h > 0, d, 0.0)


def sample_beckmann(sample, alpha):
    """Half-vector with density `D(h) (n.h)` (Walter et al. 2007). Returns `(h, pdf_h)`."""
    tan2 = -(alpha * alpha) * dr.log(dr.maximum(1.0 - sample.x, _TINY))
    cos_h = dr.rsqrt(1.0 + tan2)
    sin_h = dr.safe_sqrt(1.0 - cos_h * cos_h)
    sin_phi, cos_phi = dr.sincos(2.0 * dr.pi * sample.y)
    h = mi.Vector3f(sin_h * cos_phi, sin_h * sin_phi, cos_h)
    return h, beckmann_d(cos_h, alpha) * cos_h


def cook_torrance_g(cos_h, cos_v, cos_l, v_dot_h):
    """Cook-Torrance masking-shadowing `min(1, 2(n.h)(n.v)/(v.h), 2(n.h)(n.l)/(v.h))`."""
    return dr.minimum(1.0, 2.0 * cos_h * dr.minimum(cos_v, cos_l) / dr.maximum(v_dot_h, _TINY))


def f0_from_ior(ior):
    """Normal-incidence reflectance of a dielectric, `((ior - 1) / (ior + 1))^2`."""
    return dr.square((ior - 1.0) / (ior + 1.0))


def fresnel(cos_theta, ior, kind: str):
    """Fresnel reflectance from outside: Schlick's `F0 + (1 - F0)(1 - c)^5` or the exact
    unpolarised dielectric formula (`kind` = "schlick" | "exact")."""
    cos_theta = dr.clip(cos_theta, 0.0, 1.0)
    if kind == "schlick":
        f0 = f0_from_ior(ior)
        return f0 + (1.0 - f0) * dr.power(1.0 - cos_theta, 5)
    return mi.fresnel(cos_theta, ior)[0]


def oren_nayar(wi, wo, sigma):
    """Qualitative Oren-Nayar factor `A + B max(0, cos(phi_i - phi_o)) sin(a) tan(b)`.

    With `a = max(theta_i, theta_o)`, `b = min(...)`: `cos(dphi) sin(theta_i) sin(theta_o)` is
    the dot product of the projected directions and `sin(a) tan(b) = sin_i sin_o / max(cos_i,
    cos_o)`, so the factor needs no azimuths and no division by a sine.
    """
    s2 = sigma * sigma
    a = 1.0 - 0.5 * s2 / (s2 + 0.33)
    b = 0.45 * s2 / (s2 + 0.09)
    projected = dr.maximum(wi.x * wo.x + wi.y * wo.y, 0.0)
    cos_max = dr.maximum(dr.maximum(wi.z, wo.z), _TINY)
    return a + b * projected / cos_max
