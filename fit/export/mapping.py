"""Numerical maps from the native lobes to the GGX / EON lobes of other renderers (numpy only).

No published mapping exists from a Beckmann alpha to a GGX roughness, or from the qualitative
Oren-Nayar sigma to OpenPBR's energy-preserving Oren-Nayar (EON) roughness. Both are fitted here,
noise-free, on the lobes themselves (`python -m fit.export.mapping` fits them again and prints the
tables with their residuals):

- **Beckmann -> GGX** (`ggx_roughness`): for a Beckmann alpha `a` with Cook-Torrance shadowing,
  the GGX roughness `r` (alpha_GGX = r^2, height-correlated Smith shadowing: OpenPBR,
  UsdPreviewSurface) whose microfacet lobe `D G / (4 n.v)` (`f cos theta_o`) is nearest in
  relative L2 over the outgoing hemisphere, root-mean-square over views at 0-75 degrees from the
  normal. The Fresnel factors differ by model (the glaze's `paper` coupling
  takes F at n.v, the others at v.h) and no roughness can absorb that: `main` also reports the
  residual with them, at ior 1.5.
- **Oren-Nayar -> EON** (`eon_roughness`): for a sigma (radians), the `base_diffuse_roughness`
  in [0, 1] and a factor on the base colour whose EON lobe (single scatter plus its
  multiple-scattering term, as MaterialX 1.39 implements it) is nearest in relative L2, at albedo
  0.5, views 0-75 degrees. The qualitative model loses energy as sigma grows (A < 1), EON does
  not: the factor gives the energy back. `lambert_scale` is the same fit for a Lambertian
  (Mitsuba's `diffuse`, UsdPreviewSurface), which has no roughness.
- **The glaze's diffuse albedo** (`glaze_diffuse_albedo`, closed form): its pigment's white-sky
  albedo through the coat, which portable Mitsuba's `roughplastic` is scaled to.

`GGX_TABLE` and `EON_TABLE` hold the fitted points with the relative residual left at each; the
maps interpolate between them (in log alpha for Beckmann).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar

#: View angles (degrees from the normal) over which both fits sum their residuals.
VIEWS_DEG = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0)
#: The ior at which the specular residual is also reported with each model's Fresnel factor; the
#: albedo of the diffuse fit.
FIT_IOR = 1.5
FIT_ALBEDO = 0.5

#: (Beckmann alpha, GGX roughness r, relative L2 residual of the lobe), fitted by `fit_ggx`.
GGX_TABLE: tuple[tuple[float, float, float], ...] = (
    # albedo within 0.1%; with Fresnel at ior 1.5: residual 0.209, albedo within 0.1%
    (0.002, 0.0430, 0.2089),
    # albedo within 0.1%; with Fresnel at ior 1.5: residual 0.209, albedo within 0.1%
    (0.0025, 0.0481, 0.2089),
    # albedo within 0.1%; with Fresnel at ior 1.5: residual 0.209, albedo within 0.1%
    (0.004, 0.0608, 0.2089),
    # albedo within 0.1%; with Fresnel at ior 1.5: residual 0.209, albedo within 0.1%
    (0.0063, 0.0763, 0.2089),
    # albedo within 0.1%; with Fresnel at ior 1.5: residual 0.209, albedo within 0.3%
    (0.01, 0.0962, 0.2089),
    # albedo within 0.3%; with Fresnel at ior 1.5: residual 0.210, albedo within 0.7%
    (0.0158, 0.1209, 0.2090),
    # albedo within 0.6%; with Fresnel at ior 1.5: residual 0.211, albedo within 1.7%
    (0.0251, 0.1523, 0.2093),
    # albedo within 1.4%; with Fresnel at ior 1.5: residual 0.213, albedo within 4.2%
    (0.0398, 0.1917, 0.2100),
    # albedo within 2.9%; with Fresnel at ior 1.5: residual 0.219, albedo within 9.3%
    (0.0631, 0.2411, 0.2119),
    # albedo within 3.9%; with Fresnel at ior 1.5: residual 0.232, albedo within 17.6%
    (0.1, 0.3027, 0.2170),
    # albedo within 5.1%; with Fresnel at ior 1.5: residual 0.260, albedo within 30.3%
    (0.1585, 0.3789, 0.2287),
    # albedo within 8.3%; with Fresnel at ior 1.5: residual 0.308, albedo within 46.3%
    (0.2512, 0.4723, 0.2528),
    # albedo within 13.0%; with Fresnel at ior 1.5: residual 0.371, albedo within 61.0%
    (0.3981, 0.5855, 0.2919),
    # albedo within 20.9%; with Fresnel at ior 1.5: residual 0.441, albedo within 71.9%
    (0.631, 0.7204, 0.3403),
    # albedo within 30.5%; with Fresnel at ior 1.5: residual 0.493, albedo within 79.5%
    (1.0, 0.8829, 0.3708),
)
#: (Oren-Nayar sigma, EON roughness, colour scale, relative L2 residual), fitted by `fit_eon`.
EON_TABLE: tuple[tuple[float, float, float, float], ...] = (
    (0.0, 0.0000, 1.0000, 0.0000),  # albedo within 0.0%
    (0.1, 0.0307, 0.9955, 0.0069),  # albedo within 0.9%
    (0.2, 0.0981, 0.9770, 0.0217),  # albedo within 2.9%
    (0.3, 0.1683, 0.9429, 0.0365),  # albedo within 4.8%
    (0.4, 0.2292, 0.9004, 0.0488),  # albedo within 6.5%
    (0.5, 0.2802, 0.8571, 0.0588),  # albedo within 7.8%
    (0.6, 0.3230, 0.8177, 0.0669),  # albedo within 8.8%
    (0.7, 0.3590, 0.7838, 0.0735),  # albedo within 9.7%
    (0.8, 0.3895, 0.7555, 0.0790),  # albedo within 10.4%
    (0.9, 0.4152, 0.7321, 0.0835),  # albedo within 11.0%
    (1.0, 0.4369, 0.7128, 0.0873),  # albedo within 11.5%
)
#: (Oren-Nayar sigma, colour scale of a Lambertian, relative L2 residual), by `fit_eon(s, 0)`.
LAMBERT_TABLE: tuple[tuple[float, float, float], ...] = (
    (0.0, 1.0000, 0.0000),  # albedo within 0.0%
    (0.1, 0.9918, 0.0137),  # albedo within 1.2%
    (0.2, 0.9656, 0.0427),  # albedo within 3.6%
    (0.3, 0.9242, 0.0715),  # albedo within 6.1%
    (0.4, 0.8762, 0.0953),  # albedo within 8.1%
    (0.5, 0.8293, 0.1144),  # albedo within 9.7%
    (0.6, 0.7873, 0.1299),  # albedo within 11.0%
    (0.7, 0.7516, 0.1424),  # albedo within 12.1%
    (0.8, 0.7219, 0.1528),  # albedo within 13.0%
    (0.9, 0.6975, 0.1613),  # albedo within 13.7%
    (1.0, 0.6776, 0.1683),  # albedo within 14.3%
)


# Lobes --------------------------------------------------------------------------------------------


def _fresnel(cos, ior):
    """Exact unpolarised dielectric Fresnel reflectance from outside."""
    cos = np.clip(cos, 0.0, 1.0)
    sin_t2 = (1.0 - cos**2) / ior**2
    cos_t = np.sqrt(np.maximum(1.0 - sin_t2, 0.0))
    rs = (cos - ior * cos_t) / (cos + ior * cos_t)
    rp = (ior * cos - cos_t) / (ior * cos + cos_t)
    return 0.5 * (rs**2 + rp**2)


def _beckmann_lobe(cos_h, cos_v, cos_l, v_dot_h, alpha, ior):
    """The glaze's specular `F(n.v) D G / (4 n.v)` (`f cos theta_o`; F = 1 without `ior`)."""
    c2 = cos_h**2
    d = np.exp((c2 - 1.0) / (alpha**2 * c2)) / (np.pi * alpha**2 * c2**2)
    g = np.minimum(1.0, 2.0 * cos_h * np.minimum(cos_v, cos_l) / v_dot_h)
    return (1.0 if ior is None else _fresnel(cos_v, ior)) * d * g / (4.0 * cos_v)


def _ggx_lobe(cos_h, cos_v, cos_l, v_dot_h, r, ior):
    """GGX `F(v.h) D G2 / (4 n.v)` (`f cos theta_o`), alpha = r^2, height-correlated Smith G2;
    F = 1 without `ior`."""
    a2 = r**4
    c2 = cos_h**2
    d = a2 / (np.pi * (c2 * (a2 - 1.0) + 1.0) ** 2)

    def lam(c):
        t2 = (1.0 - c**2) / c**2
        return 0.5 * (np.sqrt(1.0 + a2 * t2) - 1.0)

    g2 = 1.0 / (1.0 + lam(cos_v) + lam(cos_l))
    return (1.0 if ior is None else _fresnel(v_dot_h, ior)) * d * g2 / (4.0 * cos_v)


def _half_vector_grid(alpha: float, n_theta: int = 240, n_phi: int = 96):
    """Half vectors dense around the normal (tan theta_h up to 40 alpha) and their solid angles."""
    s = np.concatenate(
        [np.linspace(0, 4, n_theta // 2, endpoint=False), np.geomspace(4, 40, n_theta // 2)]
    )
    theta = np.arctan(alpha * s)
    theta = theta[theta < np.radians(89.5)]
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    dtheta = np.gradient(theta)[:, None]
    d_omega = np.sin(th) * dtheta * (2 * np.pi / n_phi)
    h = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    return h, d_omega


def specular_lobes(alpha: float, r: float, ior: float | None = None, views=VIEWS_DEG):
    """Per view: (Beckmann `f cos`, GGX `f cos`, solid angle) over outgoing directions; with
    `ior`, each with its Fresnel factor (the glaze's at n.v, GGX's at v.h)."""
    h, d_omega_h = _half_vector_grid(min(alpha, 0.5))
    out = []
    for deg in views:
        v = np.array([np.sin(np.radians(deg)), 0.0, np.cos(np.radians(deg))])
        v_dot_h = h @ v
        wo = 2 * v_dot_h[..., None] * h - v
        ok = (wo[..., 2] > 1e-6) & (v_dot_h > 1e-6)
        cos_h, cos_v, cos_l, vh = h[..., 2][ok], v[2], wo[..., 2][ok], v_dot_h[ok]
        d_omega = 4.0 * vh * d_omega_h[ok]  # d omega_o = 4 (v.h) d omega_h
        beck = _beckmann_lobe(cos_h, cos_v, cos_l, vh, alpha, ior)
        ggx = _ggx_lobe(cos_h, cos_v, cos_l, vh, r, ior)
        out.append((beck, ggx, d_omega))
    return out


def _on_factor(wi, wo, sigma):
    """The qualitative Oren-Nayar factor of `materials.microfacet.oren_nayar`."""
    s2 = sigma**2
    a = 1.0 - 0.5 * s2 / (s2 + 0.33)
    b = 0.45 * s2 / (s2 + 0.09)
    projected = np.maximum(wi[0] * wo[..., 0] + wi[1] * wo[..., 1], 0.0)
    return a + b * projected / np.maximum(np.maximum(wi[2], wo[..., 2]), 1e-12)


_FUJII_1 = 0.5 - 2.0 / (3.0 * np.pi)
_FUJII_2 = 2.0 / 3.0 - 28.0 / (15.0 * np.pi)


def _fujii_albedo(cos, r):
    a = 1.0 / (1.0 + _FUJII_1 * r)
    si = np.sqrt(np.maximum(0.0, 1.0 - cos**2))
    g = (
        si * (np.arccos(np.clip(cos, -1, 1)) - si * cos)
        + 2.0 * ((si / cos) * (1.0 - si**3) - si) / 3.0
    )
    return a + r * a * g / np.pi


def _eon(wi, wo, r, rho):
    """OpenPBR's EON `f * pi / rho`-free form: `f` of MaterialX 1.39's
    `mx_oren_nayar_compensated_diffuse` (times 1/pi)."""
    cos_v, cos_l = wi[2], wo[..., 2]
    s = wo @ wi - cos_l * cos_v
    stinv = np.where(s > 0, s / np.maximum(cos_l, cos_v), s)
    a = 1.0 / (1.0 + _FUJII_1 * r)
    single = rho * a * (1.0 + r * stinv)
    avg = a * (1.0 + _FUJII_2 * r)
    eps = np.finfo(np.float32).eps
    multi = rho**2 * avg / (1.0 - rho * max(0.0, 1.0 - avg))
    multi = (
        multi
        * np.maximum(eps, 1.0 - _fujii_albedo(cos_v, r))
        * np.maximum(eps, 1.0 - _fujii_albedo(cos_l, r))
        / max(eps, 1.0 - avg)
    )
    return (single + multi) / np.pi


def diffuse_lobes(sigma: float, r: float, rho: float = FIT_ALBEDO, views=VIEWS_DEG):
    """Per view: (Oren-Nayar `f cos`, EON `f cos`, solid angle) over outgoing directions."""
    n_theta, n_phi = 64, 128
    theta = (np.arange(n_theta) + 0.5) * (np.pi / 2) / n_theta
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    wo = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    d_omega = np.sin(th) * (np.pi / 2 / n_theta) * (2 * np.pi / n_phi)
    out = []
    for deg in views:
        wi = np.array([np.sin(np.radians(deg)), 0.0, np.cos(np.radians(deg))])
        on = rho / np.pi * _on_factor(wi, wo, sigma) * wo[..., 2]
        eon = _eon(wi, wo, r, rho) * wo[..., 2]
        out.append((on, eon, d_omega))
    return out


def lobe_residual(lobes) -> float:
    """Relative L2 distance of two lobes, root-mean-square over the views."""
    errors = [np.sum((a - b) ** 2 * w) / np.sum(a**2 * w) for a, b, w in lobes]
    return float(np.sqrt(np.mean(errors)))


def albedo_error(lobes) -> float:
    """Largest relative difference of the directional albedos over the views."""
    return float(max(abs(np.sum(b * w) / np.sum(a * w) - 1.0) for a, b, w in lobes))


# Fits ---------------------------------------------------------------------------------------------


def fit_ggx(alpha: float) -> tuple[float, float]:
    """(GGX roughness r, relative residual) whose lobe is nearest the Beckmann `alpha`'s."""
    res = minimize_scalar(
        lambda r: lobe_residual(specular_lobes(alpha, r)),
        bounds=(0.02, 1.0),
        method="bounded",
        options={"xatol": 1e-5},
    )
    return float(res.x), float(res.fun)


def best_scale(lobes) -> tuple[float, float]:
    """(k, residual): the factor k on the second lobe that minimises `lobe_residual`, and the
    residual left with it."""
    norms = [np.sum(a**2 * w) for a, _, w in lobes]
    ab = sum(np.sum(a * b * w) / n for (a, b, w), n in zip(lobes, norms, strict=True))
    bb = sum(np.sum(b * b * w) / n for (_, b, w), n in zip(lobes, norms, strict=True))
    k = ab / bb
    return float(k), lobe_residual([(a, k * b, w) for a, b, w in lobes])


def fit_eon(sigma: float, fixed_r: float | None = None) -> tuple[float, float, float]:
    """(EON roughness, colour scale, relative residual) whose lobe, its albedo scaled, is nearest
    the Oren-Nayar `sigma`'s; with `fixed_r` only the scale is fitted (0: a Lambertian)."""
    if fixed_r is not None:
        return (fixed_r, *best_scale(diffuse_lobes(sigma, fixed_r)))
    res = minimize_scalar(
        lambda r: best_scale(diffuse_lobes(sigma, r))[1],
        bounds=(0.0, 1.0),
        method="bounded",
        options={"xatol": 1e-5},
    )
    return (float(res.x), *best_scale(diffuse_lobes(sigma, float(res.x))))


def ggx_roughness(alpha: float) -> float:
    """The GGX roughness r (alpha_GGX = r^2) for a Beckmann alpha, from `GGX_TABLE`."""
    a, r, _ = np.array(GGX_TABLE).T
    return float(np.interp(np.log(alpha), np.log(a), r))


def eon_roughness(sigma: float) -> tuple[float, float]:
    """(OpenPBR's `base_diffuse_roughness`, the factor on the base colour) for an Oren-Nayar
    sigma (radians), from `EON_TABLE`."""
    s, r, k, _ = np.array(EON_TABLE).T
    return float(np.interp(sigma, s, r)), float(np.interp(sigma, s, k))


def lambert_scale(sigma: float) -> float:
    """The factor on a Lambertian's albedo that best stands in for Oren-Nayar `sigma`."""
    s, k, _ = np.array(LAMBERT_TABLE).T
    return float(np.interp(sigma, s, k))


def eon_lambert_factor(colour, r: float):
    """Per channel, the factor on an EON lobe's colour (roughness `r`) that gives a Lambertian of
    the same hemispherical albedo, `E_avg + rho_ms (1 - E_avg) / rho` (OpenPBR's EON: exact, its
    average albedo is closed-form); 1 at `r = 0` and for a white colour."""
    rho = np.asarray(colour, np.float64)
    a = 1.0 / (1.0 + _FUJII_1 * r)
    average = a * (1.0 + _FUJII_2 * r)
    return average + rho * average * (1.0 - average) / (1.0 - rho * (1.0 - average))


def as_lambert(colour, sigma: float, diffuse: str = "qualitative"):
    """A diffuse lobe's colour (an RGB triple or an image) as a Lambertian's: the qualitative
    Oren-Nayar's scaled by `lambert_scale`, EON's by `eon_lambert_factor`."""
    colour = np.asarray(colour, np.float64)
    if diffuse == "eon":
        return colour * eon_lambert_factor(colour, sigma)
    return colour * lambert_scale(sigma)


def glaze_diffuse_albedo(ior: float, fresnel: str = "schlick", coupling: str = "paper") -> float:
    """The hemispherical (white-sky) albedo of a glaze's diffuse part per unit of a Lambertian
    pigment: the pigment seen through the coat once, `2 int (1 - F(mu)) mu dmu` (the `paper`
    coupling weighs it by 1 - F(n.v)), or twice, its square (`reciprocal`: (1 - F(n.l))
    (1 - F(n.v))); F Schlick's or the exact one, as the glaze's `fresnel` option."""
    nodes, weights = np.polynomial.legendre.leggauss(64)
    mu = 0.5 * (nodes + 1.0)
    if fresnel == "schlick":
        f0 = ((ior - 1.0) / (ior + 1.0)) ** 2
        reflected = f0 + (1.0 - f0) * (1.0 - mu) ** 5
    else:
        reflected = _fresnel(mu, ior)
    once = float(np.sum(0.5 * weights * 2.0 * mu * (1.0 - reflected)))
    return once if coupling == "paper" else once**2


def as_eon(sigma: float, diffuse: str = "qualitative") -> tuple[float, float]:
    """(OpenPBR's `base_diffuse_roughness`, the factor on the base colour) for a layer's diffuse
    lobe: EON's own roughness as it is, the qualitative model's through `eon_roughness`."""
    return (float(sigma), 1.0) if diffuse == "eon" else eon_roughness(sigma)


def ggx_residual(alpha: float) -> float:
    """The relative lobe residual at `alpha`, interpolated from `GGX_TABLE`."""
    a, _, e = np.array(GGX_TABLE).T
    return float(np.interp(np.log(alpha), np.log(a), e))


def eon_residual(sigma: float, lambert: bool = False) -> float:
    """The relative lobe residual at `sigma` (of EON, or of a Lambertian), from the tables."""
    if lambert:
        s, _, e = np.array(LAMBERT_TABLE).T
    else:
        s, _, _, e = np.array(EON_TABLE).T
    return float(np.interp(sigma, s, e))


#: alpha's lower bound, then every fifth of a decade to 1
GGX_ALPHAS = (0.002, *(float(a) for a in np.round(np.geomspace(10**-2.6, 1.0, 14), 4)))
EON_SIGMAS = tuple(float(s) for s in np.round(np.linspace(0.0, 1.0, 11), 2))


def main() -> None:
    """Fit both tables again and print them as Python (paste over the tables above)."""
    print("GGX_TABLE = (")
    for a in GGX_ALPHAS:
        r, e = fit_ggx(a)
        albedo = albedo_error(specular_lobes(a, r))
        fresnel = specular_lobes(a, r, FIT_IOR)
        print(
            f"    # albedo within {albedo:.1%}; with Fresnel at ior {FIT_IOR}: residual "
            f"{lobe_residual(fresnel):.3f}, albedo within {albedo_error(fresnel):.1%}"
        )
        print(f"    ({a}, {r:.4f}, {e:.4f}),")
    print(")")
    for name, fixed in (("EON_TABLE", None), ("LAMBERT_TABLE", 0.0)):
        print(f"{name} = (")
        for s in EON_SIGMAS:
            r, k, e = fit_eon(s, fixed)
            albedo = albedo_error([(a, k * b, w) for a, b, w in diffuse_lobes(s, r)])
            fitted = f"{k:.4f}" if fixed is not None else f"{r:.4f}, {k:.4f}"
            print(f"    ({s}, {fitted}, {e:.4f}),  # albedo within {albedo:.1%}")
        print(")")


if __name__ == "__main__":
    main()
