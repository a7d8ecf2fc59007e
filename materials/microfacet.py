"""Pure Dr.Jit functions shared by the BSDFs: Beckmann, Cook-Torrance, Fresnel, Oren-Nayar (the
qualitative model and OpenPBR's energy-preserving EON).

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


# EON (Portsmouth, Kutz, Hill 2025, OpenPBR's diffuse lobe): Fujii's Oren-Nayar plus a
# multiple-scattering lobe that gives back the energy the single scatter loses.
_FON_1 = 0.5 - 2.0 / (3.0 * dr.pi)
_FON_2 = 2.0 / 3.0 - 28.0 / (15.0 * dr.pi)


def _fon_loss(cos_theta):
    """`(1 - E_FON(mu)) (1 + c1 r) / r`, the same at every roughness r: the share of light that
    Fujii's model does not reflect, from OpenPBR's polynomial fit of `G / pi` (the albedo within
    0.0005 of the exact one at r = 1, measured); never negative (the fit dips 0.0004 below zero
    at grazing angles)."""
    m = 1.0 - dr.clip(cos_theta, 0.0, 1.0)
    m2 = m * m
    g_over_pi = 0.0571085289 * m + 0.491881867 * m2 + m2 * (-0.332181442 * m + 0.0714429953 * m2)
    return dr.maximum(_FON_1 - g_over_pi, 0.0)


def eon(wi, wo, r, albedo):
    """OpenPBR's EON BRDF `f` (without the cosine) for roughness `r` in [0, 1] and `albedo`.

    Single scatter (Fujii): `albedo / pi * A (1 + r s / t)`, `A = 1 / (1 + c1 r)`, `s = wi.wo -
    cos_i cos_o`, `t = max(cos_i, cos_o)` where `s > 0` (else 1). Multiple scatter: `rho_ms / pi
    (1 - E(cos_i)) (1 - E(cos_o)) / (1 - E_avg)`, `rho_ms = albedo^2 E_avg / (1 - albedo (1 -
    E_avg))`. The two losses and `1 - E_avg` each carry a factor `r / (1 + c1 r)`, divided out
    here so that `r = 0` is exactly Lambert with no 0 / 0. White (albedo 1) it reflects all the
    light at every angle."""
    s = dr.dot(wi, wo) - wi.z * wo.z
    t = dr.select(s > 0, dr.maximum(dr.maximum(wi.z, wo.z), _TINY), 1.0)
    a = 1.0 / (1.0 + _FON_1 * r)
    single = a * (1.0 + r * s / t)
    average = a * (1.0 + _FON_2 * r)
    rho_ms = albedo * albedo * average / (1.0 - albedo * (1.0 - average))
    multi = rho_ms * (r * a / (_FON_1 - _FON_2)) * _fon_loss(wi.z) * _fon_loss(wo.z)
    return dr.inv_pi * (albedo * single + multi)
