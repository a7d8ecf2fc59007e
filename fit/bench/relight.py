"""Relighting real photographs (`layerfit bench --only relight`): a fit of a photometric-stereo
capture (a DiLiGenT folder: one distant light per photograph, ground-truth normals) scored on the
lights it did not fit, against the classic per-pixel models fitted to the same lights and scored
on the same held-out ones, with the same relative RMSE over the same pixels
(`fit.commands.run_folder`: per view, sqrt(sum w (render - photo)^2 / sum w photo^2) over the
pixels the fit's height field covers whole, at the fit's resolution).

The per-pixel models are fitted at full resolution on the ground-truth normals, their relit
images area-averaged like the photographs (`Capture.downscaled`):

- one Lambert colour for every pixel;
- a Lambert colour per pixel (the photometric-stereo albedo: least squares per pixel and
  channel over the fitted lights);
- a Lambert colour per pixel plus one Cook-Torrance lobe shared by every pixel (Beckmann
  distribution, Schlick's Fresnel from an ior of 1.5, Smith's shadowing; its RGB strength and
  roughness fitted with the colours, by least squares).

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
    Cook-Torrance lobe when `lobe`: for a roughness, each pixel's colour and the lobe's RGB
    strength are a linear least-squares problem (the colours eliminated pixel by pixel, the
    strength then in closed form per channel); the roughness minimises what is left (a bounded
    1-D search)."""
    from scipy.optimize import minimize_scalar

    cos = _cosines(data)
    if not lobe:
        return cos[..., None] * _albedo(data.photos, data.weights, cos, fitted)[None]
    w = data.weights[fitted][..., None]
    c = cos[fitted][..., None]
    photos = data.photos[fitted]
    norm = np.maximum(np.sum(w * c * c, 0), 1e-12)
    a = np.sum(w * c * photos, 0) / norm  # each pixel's colour without the lobe

    def solve(log_alpha):
        lobe_all = _lobe(data, float(np.exp(log_alpha)))[..., None]
        q = lobe_all[fitted]
        b = np.sum(w * c * q, 0) / norm  # the colour the unit lobe takes from each pixel
        left, unit = photos - a * c, q - b * c
        strength = np.sum(w * left * unit, (0, 1)) / np.maximum(
            np.sum(w * unit * unit, (0, 1)), 1e-12
        )
        strength = np.maximum(strength, 0.0)
        loss = float(np.sum(w * (left - strength * unit) ** 2))
        return loss, strength, lobe_all, np.maximum(a - strength * b, 0.0)

    best = minimize_scalar(
        lambda x: solve(x)[0], bounds=(np.log(0.005), np.log(1.0)), method="bounded"
    )
    _, strength, lobe_all, albedo = solve(best.x)
    return cos[..., None] * albedo[None] + lobe_all * strength


def uniform(data: Data, fitted: np.ndarray) -> np.ndarray:
    """Relit photos of one Lambert colour for every pixel."""
    cos = _cosines(data)
    w = data.weights[fitted][..., None]
    c = cos[fitted][..., None]
    colour = np.sum(w * c * data.photos[fitted], (0, 1)) / np.sum(w * c * c, (0, 1))
    return cos[..., None] * colour


def scores(
    capture: Capture, data: Data, relit: np.ndarray, downscale: int, small: Capture
) -> np.ndarray:
    """Each light's relative RMSE of `relit` (at `capture`'s full resolution) area-averaged by
    `downscale`, against the photos of `small`, the capture as the fit opens it (its pixels:
    those its height field covers whole)."""
    from captures.weights import downscale as area_average

    out = []
    for k, (view, target) in enumerate(zip(capture.views, small.views, strict=True)):
        image = np.zeros(view.image.shape, np.float32).reshape(-1, 3)
        image[data.pixels] = relit[k]
        weight = np.zeros(view.weight.shape, np.float32).reshape(-1)
        weight[data.pixels] = view.weight.reshape(-1)[data.pixels]  # the photo's own pixels
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


#: Samples per pixel of the fitted material's relit photos: a photograph has no Monte Carlo
#: noise, and the report's 64 spp added some to every light's error.
RELIGHT_SPP = 1024


def rendered_scores(preset: Path, small: Capture, seed: int) -> np.ndarray:
    """Each light's relative RMSE of a preset rendered at `RELIGHT_SPP` against the photos of
    `small` (the capture as the fit opens it)."""
    from ..material import load_preset
    from ..render import Renderer

    image = Renderer(small, load_preset(preset).material, []).render(
        np.zeros(0, np.float32), seed + 11, RELIGHT_SPP
    )
    out, offset = [], 0
    for view in small.views:
        render = image[offset : offset + view.image.size].reshape(view.image.shape)
        offset += view.image.size
        w = view.weight[..., None]
        out.append(
            np.sqrt(np.sum(w * (render - view.image) ** 2) / max(np.sum(w * view.image**2), 1e-30))
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
    small = open_capture(folder, cfg.downscale)  # the fit's photos and pixels
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
        rmse = scores(capture, data, make(), cfg.downscale, small)
        rows.append((name, rmse, time.perf_counter() - began))
    with tempfile.TemporaryDirectory() as tmp:
        began = time.perf_counter()
        _, run = fit(fit_config, Path(tmp) / "run", progress=progress)
        wall = time.perf_counter() - began
        rmse = rendered_scores(run / "preset.toml", small, cfg.seed)
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
            "per-pixel models: ground-truth normals, no cast shadows (fit/bench/relight.py); "
            f"layerfit's fitted preset relit at {RELIGHT_SPP} spp",
            machine(),
        ],
    )
