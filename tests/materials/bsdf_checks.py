"""Helpers for proving BSDFs: directions, interactions, AD and finite-difference derivatives."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


def direction(theta_deg, phi_deg=0.0) -> np.ndarray:
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.stack(
        np.broadcast_arrays(np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)), -1
    )


def hemisphere(n: int, seed: int = 1, min_cos: float = 0.0) -> np.ndarray:
    """`n` random unit vectors of the upper hemisphere with cos(theta) > `min_cos`."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(4 * n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[:, 2] = np.abs(v[:, 2])
    return v[v[:, 2] > min_cos][:n]


def vec(a: np.ndarray) -> mi.Vector3f:
    a = np.atleast_2d(a)
    return mi.Vector3f(a[:, 0], a[:, 1], a[:, 2])


def interaction(wi: np.ndarray, uv=None, p=None) -> mi.SurfaceInteraction3f:
    """Interactions on the plane z = 0 with the world frame as shading frame, `dp/du = x`,
    `dp/dv = y` (so bump mapping has tangents), at `uv` (N, 2) and positions `p` (N, 3)."""
    n = len(np.atleast_2d(wi))
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = vec(wi)
    si.uv = mi.Point2f(0.5, 0.5) if uv is None else mi.Point2f(uv[:, 0], uv[:, 1])
    if p is not None:
        si.p = mi.Point3f(p[:, 0], p[:, 1], p[:, 2])
    si.n = mi.Normal3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(si.n)
    si.dp_du = mi.Vector3f(1, 0, 0)
    si.dp_dv = mi.Vector3f(0, 1, 0)
    return si


def rgb(color) -> np.ndarray:
    """(N, 3) numpy from a Color3f / Spectrum."""
    return np.stack([np.asarray(c) for c in color], axis=-1)


def set_param(bsdf, key: str, value):
    """Set a traversed parameter (a float or an RGB triple) and return the new Dr.Jit value."""
    params = mi.traverse(bsdf)
    current = params[key]
    new = type(current)(*value) if np.ndim(value) else type(current)(value)
    params[key] = new
    params.update()
    return params[key]


def eval_value(bsdf, wi, wo) -> np.ndarray:
    return rgb(bsdf.eval(mi.BSDFContext(), interaction(wi), vec(wo)))


def ad_derivative(bsdf, key: str, value, fn, channel: int | None = None) -> np.ndarray:
    """Forward-mode derivative of `fn(bsdf)` (a Color3f) with respect to parameter `key` at
    `value`; for an RGB parameter, along `channel`."""
    params = mi.traverse(bsdf)
    x = type(params[key])(*value) if np.ndim(value) else type(params[key])(value)
    dr.enable_grad(x)
    params[key] = x
    params.update()
    x = params[key]
    if channel is None:
        dr.set_grad(x, 1.0)
    else:
        tangent = [0.0, 0.0, 0.0]
        tangent[channel] = 1.0
        dr.set_grad(x, type(x)(*tangent))
    out = fn(bsdf)
    dr.forward_to(out)
    grad = rgb(dr.grad(out))
    params[key] = dr.detach(x)
    params.update()
    return grad


def fd_derivative(bsdf, key: str, value, fn, h: float, channel: int | None = None):
    """Richardson-extrapolated central difference of `fn(bsdf)` (steps `h` and `h / 2`, truncation
    error O(h^4)) and a bound on its rounding error.

    The BSDF computes in float32, so each value carries a relative rounding error of a few tens of
    ulps; divided by the step that bounds how far the quotient can be from the truth besides
    truncation. Returns `(derivative, rounding_error)`, both float64 arrays.
    """

    def at(offset):
        v = np.array(value, dtype=float)
        if channel is None:
            v = v + offset
        else:
            v[channel] += offset
        set_param(bsdf, key, v.tolist() if v.ndim else float(v))
        return rgb(fn(bsdf)).astype(np.float64)

    values = {k: at(k * h / 2) for k in (-2, -1, 1, 2)}
    set_param(bsdf, key, value)
    coarse = (values[2] - values[-2]) / (2 * h)
    fine = (values[1] - values[-1]) / h
    size = np.max(np.abs(np.stack(list(values.values()))), axis=0)
    rounding = 3 * 64 * np.finfo(np.float32).eps * size / h
    return (4 * fine - coarse) / 3, rounding


def ad_and_fd(bsdf, key: str, value, fn, h: float, channel: int | None = None):
    """`fn(bsdf)`'s derivative with respect to `key` at `value` both ways: `(AD, FD, FD's rounding
    error)`, from `ad_derivative` and `fd_derivative` (step `h`)."""
    ad = ad_derivative(bsdf, key, value, fn, channel)
    return ad, *fd_derivative(bsdf, key, value, fn, h, channel)


def assert_derivative(ad, fd, rounding, rtol: float, what: str, min_fraction: float = 1.0) -> None:
    """AD equals FD within `rtol` plus FD's rounding error, plus 1e-5 of the largest derivative
    (FD's truncation error grows in a lobe's far tail, where the values are ~1e-8 of the peak),
    in at least `min_fraction` of the rows (directions). So where the value measurably depends on
    the parameter, AD cannot be silently zero.

    `min_fraction < 1` is for parameters that move lobes across the kinks of Cook-Torrance's min()
    or Oren-Nayar's max() (normals bent by bump or noise), where FD means nothing in a few rows.
    """
    assert np.all(np.isfinite(ad)), f"{what}: non-finite derivative"
    bound = rtol * np.abs(fd) + rounding + 1e-5 * np.abs(fd).max() + 1e-12
    bad = np.abs(ad - fd) > bound
    rows = bad.reshape(len(bad), -1).any(axis=1)
    assert rows.mean() <= 1.0 - min_fraction, (
        f"{what}: {rows.sum()} of {len(rows)} rows differ, e.g. AD {ad[bad][:3]} vs FD "
        f"{fd[bad][:3]} (allowed {bound[bad][:3]})"
    )


def albedo(bsdf, theta_deg: float, n: int = 1 << 18, seed: int = 0) -> np.ndarray:
    """Directional albedo (RGB) at incidence `theta_deg`: the mean sample weight over `n`
    stratified-random samples (an unbiased estimate; error ~ 1e-3 for these lobes)."""
    rng = np.random.default_rng(seed)
    wi = np.repeat(direction(theta_deg, 30.0)[None], n, axis=0)
    s1 = mi.Float(rng.random(n, dtype=np.float32))
    s2 = mi.Point2f(rng.random(n, dtype=np.float32), rng.random(n, dtype=np.float32))
    _, weight = bsdf.sample(mi.BSDFContext(), interaction(wi), s1, s2)
    return rgb(weight).astype(np.float64).mean(axis=0)


def assert_consistent(bsdf, si, wo, rtol: float, seed: int = 5) -> None:
    """`eval_pdf` returns `eval` and `pdf`; a sample's pdf is `pdf(wo)` and its weight is
    `eval(wo) / pdf(wo)`, all finite, for the interactions `si` and directions `wo` (Vector3f)."""
    ctx, n = mi.BSDFContext(), dr.width(si.wi)
    value, pdf = bsdf.eval_pdf(ctx, si, wo)
    np.testing.assert_allclose(rgb(value), rgb(bsdf.eval(ctx, si, wo)), rtol=rtol, atol=1e-7)
    np.testing.assert_allclose(np.asarray(pdf), np.asarray(bsdf.pdf(ctx, si, wo)), rtol=rtol)
    rng = np.random.default_rng(seed)
    s1 = mi.Float(rng.random(n, dtype=np.float32))
    s2 = mi.Point2f(rng.random(n, dtype=np.float32), rng.random(n, dtype=np.float32))
    bs, weight = bsdf.sample(ctx, si, s1, s2)
    assert np.all(np.isfinite(rgb(weight)))
    ok = np.asarray(bs.pdf) > 0
    assert ok.mean() > 0.5
    sample_rtol = max(rtol * 100, 1e-4)  # bs.wo round-trips through float32 before re-evaluation
    np.testing.assert_allclose(
        np.asarray(bs.pdf)[ok], np.asarray(bsdf.pdf(ctx, si, bs.wo))[ok], rtol=sample_rtol
    )
    expected = rgb(bsdf.eval(ctx, si, bs.wo))[ok] / np.asarray(bs.pdf)[ok, None]
    np.testing.assert_allclose(rgb(weight)[ok], expected, rtol=sample_rtol, atol=1e-5)
