"""Relighting real photographs (`layerfit bench --only relight`): a fit of a photometric-stereo
capture (a DiLiGenT folder: one distant light per photograph, ground-truth normals) scored on the
lights it did not fit, against the classic per-pixel models fitted to the same lights and scored
on the same held-out ones, with the same relative RMSE (`fit.commands.run_folder`: per view,
sqrt(sum w (render - photo)^2 / sum w photo^2) over its valid pixels, at the fit's resolution).

The per-pixel models are fitted at full resolution on the ground-truth normals, their relit
images area-averaged like the photographs (`Capture.downscaled`):

- one Lambert colour for every pixel;
- a Lambert colour per pixel (the photometric-stereo albedo: least squares per pixel and
  channel over the fitted lights);
- a Lambert colour per pixel plus one Cook-Torrance lobe shared by every pixel (Beckmann
  distribution, Schlick's Fresnel from an ior of 1.5, Smith's shadowing; its RGB strength and
  roughness fitted, the colours again per pixel for each).

None casts shadows (a pixel sees its light wherever its normal faces it); the path tracer does."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from captures.capture import Capture

from .common import Table, machine

#: The view direction of a DiLiGenT capture (camera frame: towards the camera).
VIEW = np.array([0.0, 0.0, 1.0])


@dataclasses.dataclass
class Data:
    """A DiLiGenT capture's fitted and held-out lights at full resolution: photos (lights x
    pixels x 3), validity weights (lights x pixels), unit normals (pixels x 3) of the mask's
    pixels, and the directions towards the lights."""

    photos: np.ndarray
    weights: np.ndarray
    normals: np.ndarray
    towards: np.ndarray
    pixels: np.ndarray  # the mask's pixel indices (flat) in the full image


def load(capture: Capture, folder: Path) -> Data:
    """The per-pixel models' data of a full-resolution DiLiGenT `capture` read from `folder`."""
    from captures.importers import read_normal_map

    mask = capture.scene.meta["mask"]
    normals, bad = read_normal_map(folder / "Normal_gt.mat", mask)
    pixels = np.flatnonzero(mask & ~bad)
    photos = np.stack([v.image.reshape(-1, 3)[pixels] for v in capture.views])
    weights = np.stack([v.weight.reshape(-1)[pixels] for v in capture.views])
    towards = np.stack([-np.asarray(v.lights[0].direction, float) for v in capture.views])
    n = normals.reshape(-1, 3)[pixels]
    return Data(photos, weights, n / np.linalg.norm(n, axis=1, keepdims=True), towards, pixels)


def _cosines(data: Data) -> np.ndarray:
    """max(0, n . l): lights x pixels."""
    return np.maximum(data.towards @ data.normals.T, 0.0)


def _lobe(data: Data, alpha: float, ior: float = 1.5) -> np.ndarray:
    """A unit Cook-Torrance lobe's radiance (Beckmann D, Schlick F, Smith G) times n . l:
    lights x pixels."""
    n, v = data.normals, VIEW
    cos_o = np.clip(n @ v, 1e-4, 1.0)[None]
    cos_i = np.clip(data.towards @ n.T, 0.0, 1.0)
    h = data.towards[:, None, :] + v
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    cos_h = np.clip(np.einsum("lpk,pk->lp", h, n), 1e-4, 1.0)
    tan2 = (1.0 - cos_h**2) / cos_h**2
    d = np.exp(-tan2 / alpha**2) / (np.pi * alpha**2 * cos_h**4)
    f0 = ((ior - 1.0) / (ior + 1.0)) ** 2
    f = f0 + (1.0 - f0) * (1.0 - np.clip(np.einsum("lpk,k->lp", h, v), 0.0, 1.0)) ** 5

    def smith(cos):
        a = cos / (alpha * np.sqrt(np.maximum(1.0 - cos**2, 1e-12)))
        return np.where(a < 1.6, (3.535 * a + 2.181 * a**2) / (1 + 2.276 * a + 2.577 * a**2), 1.0)

    g = smith(cos_i) * smith(np.broadcast_to(cos_o, cos_i.shape))
    return np.where(cos_i > 0, d * f * g / (4.0 * cos_o), 0.0)


def _albedo(photos, weights, shading, fitted) -> np.ndarray:
    """Each pixel's least-squares Lambert colour over the `fitted` lights (pixels x 3)."""
    w = weights[fitted][..., None]
    c = shading[fitted][..., None]
    return np.sum(w * c * photos[fitted], 0) / np.maximum(np.sum(w * c * c, 0), 1e-12)


def per_pixel(data: Data, fitted: np.ndarray, lobe: bool) -> np.ndarray:
    """Relit photos (lights x pixels x 3) of the per-pixel Lambert model, with one shared
    Cook-Torrance lobe when `lobe` (its strength and roughness by least squares over the
    fitted lights)."""
    from scipy.optimize import minimize

    cos = _cosines(data)
    if not lobe:
        return cos[..., None] * _albedo(data.photos, data.weights, cos, fitted)[None]

    def relit(params):
        strength, alpha = np.exp(params[:3]), float(np.exp(params[3]))
        spec = _lobe(data, alpha)[..., None] * strength
        albedo = _albedo(data.photos - spec, data.weights, cos, fitted)
        return cos[..., None] * np.maximum(albedo, 0.0)[None] + spec

    def loss(params):
        r = relit(params)[fitted] - data.photos[fitted]
        return float(np.sum(data.weights[fitted][..., None] * r**2))

    scale = float(np.median(data.photos[fitted][data.weights[fitted] > 0]))
    best = min(
        (
            minimize(loss, [np.log(scale)] * 3 + [np.log(a)], method="Nelder-Mead")
            for a in (0.05, 0.15, 0.4)
        ),
        key=lambda r: r.fun,
    )
    return relit(best.x)


def uniform(data: Data, fitted: np.ndarray) -> np.ndarray:
    """Relit photos of one Lambert colour for every pixel."""
    cos = _cosines(data)
    w = data.weights[fitted][..., None]
    c = cos[fitted][..., None]
    colour = np.sum(w * c * data.photos[fitted], (0, 1)) / np.sum(w * c * c, (0, 1))
    return cos[..., None] * colour


def scores(capture: Capture, data: Data, relit: np.ndarray, downscale: int) -> np.ndarray:
    """Each light's relative RMSE of `relit` against the photos at the fit's resolution."""
    from captures.weights import downscale as area_average

    small = capture.downscaled(downscale)
    out = []
    for k, (view, target) in enumerate(zip(capture.views, small.views, strict=True)):
        image = np.zeros(view.image.shape, np.float32).reshape(-1, 3)
        image[data.pixels] = relit[k]
        weight = np.zeros(view.weight.shape, np.float32).reshape(-1)
        weight[data.pixels] = 1.0
        render, _ = area_average(
            image.reshape(view.image.shape), weight.reshape(view.weight.shape), downscale
        )
        w = target.weight[..., None]
        out.append(
            np.sqrt(
                np.sum(w * (render - target.image) ** 2) / max(np.sum(w * target.image**2), 1e-30)
            )
        )
    return np.asarray(out)


def relight_table(fit_config: Path, progress=None) -> Table:
    """The fit of `fit_config` (a DiLiGenT capture with `fit.holdout` lights) and the per-pixel
    models, each scored on the fit's held-out lights (and its fitted ones)."""
    import tempfile

    from captures import InputError, open_capture

    from ..commands.fit import fit
    from ..commands.prepare import held_out
    from ..config import load_fit_config

    cfg = load_fit_config(fit_config)
    folder = Path(cfg.capture)
    if not (folder / "Normal_gt.mat").is_file():
        raise InputError(
            f"{fit_config}: capture {folder} is not a DiLiGenT folder with Normal_gt.mat; the "
            "relight table compares per-pixel models on ground-truth normals"
        )
    if cfg.holdout == 0:
        raise InputError(f"{fit_config}: fit.holdout is 0; hold out lights to score on")
    capture = open_capture(folder)
    held = held_out(len(capture.views), cfg.holdout)
    fitted = np.array([i not in held for i in range(len(capture.views))])
    data = load(capture, folder)
    rows = []
    for name, make in (
        ("one Lambert colour", lambda: uniform(data, fitted)),
        ("Lambert colour per pixel", lambda: per_pixel(data, fitted, lobe=False)),
        ("per pixel + one Cook-Torrance lobe", lambda: per_pixel(data, fitted, lobe=True)),
    ):
        began = time.perf_counter()
        rmse = scores(capture, data, make(), cfg.downscale)
        rows.append((name, rmse, time.perf_counter() - began))
    with tempfile.TemporaryDirectory() as tmp:
        began = time.perf_counter()
        summary, _ = fit(fit_config, Path(tmp) / "run", progress=progress)
        wall = time.perf_counter() - began
    rmse = np.array([v["rmse"] for v in summary["views"]])
    rows.append((f"layerfit ({fit_config.name})", rmse, wall))
    return Table(
        f"Relighting {folder.name}: relative RMSE on {len(held)} held-out lights",
        ["model", "held-out lights (mean)", "worst held-out", "fitted lights (mean)", "time (s)"],
        [
            [
                name,
                f"{r[~fitted].mean():.3f}",
                f"{r[~fitted].max():.3f}",
                f"{r[fitted].mean():.3f}",
                f"{seconds:.1f}",
            ]
            for name, r, seconds in rows
        ],
        [
            f"{fitted.sum()} lights fitted, {len(held)} held out "
            f"({', '.join(capture.views[i].name for i in held)}); photos area-averaged by "
            f"{cfg.downscale}; relative RMSE per light over its valid pixels",
            "per-pixel models: ground-truth normals, no cast shadows (fit/bench/relight.py)",
            machine(),
        ],
    )
