"""A fit's run folder written from a (possibly partial) result: the summary, the report's
renders, the preset and fitted textures, each file atomically."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import html
import json
import logging
import math
import os
import re
import socket
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from captures.errors import InputError
from captures.images import TEXTURE_SUFFIXES, write_image

from .. import timing
from ..config import config_identity
from ..errors import OutputError
from ..material import (
    at_bounds,
    provenance,
    save_preset,
    to_physical,
)
from ..material.preset import software_versions
from ..output import ViewPanel, write_report, write_text
from ..solvers import Checkpoint
from ..solvers.textures import uniform_sd

log = logging.getLogger(__name__)

#: Samples per pixel of the renders in the report (and the per-view residuals).
REPORT_SPP = 64


#: What a write into a run folder fails with that its user can fix (space, quota, permissions).
WRITE_ERRORS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EROFS, errno.EPERM})


@contextlib.contextmanager
def writing(out: Path, checkpoint: Checkpoint | None):
    """A run folder that cannot be written (a full disk) is one line saying what was kept."""
    try:
        yield
    except OSError as err:
        inside = isinstance(err.filename, str) and Path(err.filename).resolve().is_relative_to(
            Path(out).resolve()
        )
        if err.errno not in WRITE_ERRORS and not inside:  # not the folder's: not this
            raise
        kept = (
            f"its checkpoint {checkpoint.path} is kept: free space (or fix permissions) and run "
            "the same command with --resume"
            if checkpoint is not None and checkpoint.path.exists()
            else "no checkpoint was saved: free space (or fix permissions) and run it again"
        )
        raise OutputError(
            f"{out}: could not write the run folder ({err.strerror or err}"
            f"{f': {err.filename}' if err.filename else ''}); {kept}"
        ) from None


def write_run(
    cfg, out, capture, held, problem, start, result, wall, interrupted=False, starts=None
) -> dict:
    """The run folder's files from a (possibly partial) result (`starts`: a multi-start's).
    Images an earlier run wrote into this folder (`--force`) and this one did not (a view or a
    fitted texture it no longer has) are removed once the new files are in place; other files
    are left alone."""
    before = _outputs(out)
    free = problem.free
    textures = {  # fitted textures as images next to the summary and in the preset
        f.key: np.asarray(result.values[f.key], np.float32).reshape(f.shape)
        for f in free
        if f.shape
    }
    with timing.timed("report: renders of the fitted views"):
        panels = _panels(cfg, capture, held, problem, result)
    began = time.perf_counter()
    from .prepare import fit_phases  # it imports this module's lock

    phases = fit_phases(cfg, problem)
    summary = _summary(cfg, capture, held, start, result, wall, panels, interrupted, free, phases)
    if starts is not None:
        summary["starts"] = starts
    for key, texels in textures.items():
        write_image(out / f"{key}.exr", texels)
    for key, sd in (result.texture_std or {}).items():  # each texel's sd, beside its texture
        write_image(out / f"{key}.sd.exr", sd)
    # the fitted textures' files: the report's masks are baked from them (it showed the start's)
    fitted_material = cfg.material.with_values(result.values).with_textures(
        {key: out / f"{key}.exr" for key in textures}
    )
    if interrupted:  # no preset of a fit that did not end (nor an earlier run's beside it)
        (out / "preset.toml").unlink(missing_ok=True)
    else:
        std = {k: v for k, v in (result.std or {}).items() if k in cfg.material.params}
        save_preset(
            fitted_material,
            out / "preset.toml",
            provenance(cfg.capture, cfg.path, result.loss, std or None),
            textures,
        )
    shown = masks(fitted_material)
    true_material = truth_material(cfg.material, capture)
    if true_material is not None:  # fitted and true masks side by side, scored where seen
        true_masks = masks(true_material)
        layers = fitted_material.bsdf["layers"].split(",")
        height, width = next(iter(shown.values())).shape
        seen = scored_texels(capture.scene, cfg.downscale, width, height)
        iou = summary["mask_iou"] = mask_iou(shown, true_masks, layers, seen)
        rmse = summary["mask_rmse"] = mask_rmse(shown, true_masks, layers, seen)
        sizes = {  # the free masks whose truth is painted
            k: t.shape[1::-1]
            for k, t in textures.items()
            if k.endswith(".mask.texture") and k in capture.truth_textures
        }
        held = summary["mask_iou_resampled"] = resampled_iou(true_material, true_masks, sizes, seen)
        beside = {}
        for key, texels in shown.items():
            beside[key] = texels
            layer = key.removesuffix(".mask")
            caption = f"seen share's IoU {iou[layer]:.2f}, RMSE {rmse[layer]:.3f}"
            if layer in held:
                caption += f"; the truth at the fitted texels' {held[layer]:.2f}"
            beside[f"{key}: truth ({caption})"] = true_masks[key]
        shown = beside
    for key, texels in textures.items():
        shown[key] = texels if texels.shape[-1] == 3 else texels[..., 0]
        if key in (result.texture_std or {}):
            sd = result.texture_std[key]
            shown[f"{key} sd"] = sd if sd.shape[-1] == 3 else sd[..., 0]
    title = f"{cfg.path.name}{' (interrupted)' if interrupted else ''}"
    write_report(out, summary, panels, shown, title)
    timing.add("report: figures, preset and files", time.perf_counter() - began)
    summary["timings_s"] = timing.recorded()  # empty outside `layerfit fit`'s recording
    # the summary last: beside no checkpoint, it marks a finished run folder (batches skip those)
    write_text(out / "summary.json", json.dumps(_finite(summary), indent=2, allow_nan=False))
    for path, inode in before.items():  # every file is written anew (atomic: a new inode)
        if path.exists() and path.stat().st_ino == inode:
            path.unlink()
    return summary


def _outputs(out: Path) -> dict[Path, int]:
    """The images an earlier fit wrote into this run folder that are there now, with their
    inodes: the PNGs its `report.html` shows, the texture files its `preset.toml` names as the
    preset writes them (`preset.<key>.<ext>`), and fitted textures named by a parameter of its
    `summary.json` (`<key>.exr`, its sd `<key>.sd.exr`). Nothing else a user keeps there (a
    PNG of their own in `report/`, a texture a hand-edited preset names: both were deleted by
    `--force`)."""
    try:
        keys = set(json.loads((out / "summary.json").read_text())["values"])
    except (OSError, ValueError, KeyError, TypeError):
        keys = set()
    try:
        preset = tomllib.loads((out / "preset.toml").read_text())
    except (OSError, ValueError):
        preset = {}
    try:
        page = (out / "report.html").read_text(errors="replace")
    except OSError:
        page = ""
    shown = {html.unescape(name) for name in re.findall(r"src='report/([^'/]+\.png)'", page)}
    paths = [out / "report" / name for name in sorted(shown)]
    paths += [out / name for name in _images_named(preset) if name.startswith("preset.")]
    paths += [p for p in out.glob("*.exr") if p.stem in keys or p.stem.removesuffix(".sd") in keys]
    return {p: p.stat().st_ino for p in paths if p.is_file()}


def _images_named(value) -> list[str]:
    """Every string in a TOML document that is the bare name (no folder) of an image file."""
    if isinstance(value, dict):
        return [s for v in value.values() for s in _images_named(v)]
    if isinstance(value, list):
        return [s for v in value for s in _images_named(v)]
    if isinstance(value, str) and value and Path(value).name == value:
        return [value] if Path(value).suffix.lower() in TEXTURE_SUFFIXES else []
    return []


def _panels(cfg, capture, held, problem, result) -> list[ViewPanel]:
    """Every view (held-out ones too) rendered at the fitted values, with its relative RMSE."""
    from ..render import Renderer

    n = problem.n_material
    x = np.asarray(to_physical(problem.free, np.asarray(result.u)[:n]), np.float32)
    flat = Renderer(capture, cfg.material, problem.free).render(x, cfg.seed + 7, REPORT_SPP)
    panels, offset = [], 0
    for i, view in enumerate(capture.views):
        size = view.image.size
        render = flat[offset : offset + size].reshape(view.image.shape)
        offset += size
        gain = result.values.get(f"gain.{view.name}", [1.0, 1.0, 1.0])
        render = render * np.asarray(gain, np.float32)
        w = view.weight[..., None]
        rmse = math.sqrt(
            float(np.sum(w * (render - view.image) ** 2))
            / max(float(np.sum(w * view.image**2)), 1e-30)
        )
        panels.append(ViewPanel(view.name, view.image, render, view.weight, i in held, rmse))
    return panels


def truth_material(material, capture):
    """`material` at the capture's truth, its masks' painted textures the truth's
    (`Capture.truth_textures`), or None where the truth holds no texture of this material's.
    The masks' structure (each fbm's scale, octaves and seed) is the material's own: a config
    whose masks are built otherwise than the capture's is scored against other masks."""
    files = {k: v for k, v in capture.truth_textures.items() if k in material.texture_files()}
    if not files:
        return None
    return material.with_values(capture.truth).with_textures(files)


def shares(baked: dict[str, np.ndarray], layers: list[str]) -> dict[str, np.ndarray]:
    """Each masked layer's share of the surface (`<name>.mask` -> texels) from its baked mask
    (`masks`), as the layered material picks layers: a layer's mask times one minus each mask
    above it (what of it the photographs can see)."""
    out, above = {}, None
    for name in reversed(layers[1:]):
        mask = baked[f"{name}.mask"]
        out[name] = mask if above is None else mask * above
        above = (1.0 - mask) if above is None else above * (1.0 - mask)
    return out


#: A layer is present where its share exceeds this (`mask_iou`).
MASK_LEVEL = 0.5


def mask_iou(fitted: dict, true: dict, layers: list[str], seen: np.ndarray) -> dict[str, float]:
    """Layer name -> intersection over union of where the fitted and the true masks (baked,
    `masks`) give the layer a share above `MASK_LEVEL`, over the texels the views see."""
    a, b = shares(fitted, layers), shares(true, layers)
    out = {}
    for name in a:
        fit_on, true_on = (a[name] > MASK_LEVEL) & seen, (b[name] > MASK_LEVEL) & seen
        union = np.count_nonzero(fit_on | true_on)
        out[name] = float(np.count_nonzero(fit_on & true_on) / union) if union else 1.0
    return out


def mask_rmse(fitted: dict, true: dict, layers: list[str], seen: np.ndarray) -> dict[str, float]:
    """Layer name -> root-mean-square difference of the fitted and the true share (`shares`) over
    the texels the views see. Beside `mask_iou`, which counts only which side of `MASK_LEVEL` a
    share lies: a layer painted at about half strength (the cup's stain ring, 0.3-0.6 over most
    of it) flips texels across the level with errors of a few hundredths."""
    a, b = shares(fitted, layers), shares(true, layers)
    return {
        name: float(np.sqrt(np.mean((a[name][seen] - b[name][seen]) ** 2))) if seen.any() else 0.0
        for name in a
    }


def scored_texels(scene, downscale: int, width: int, height: int) -> np.ndarray:
    """The texels `mask_iou` scores: those the views see (`seen_texels`), found by rays as dense
    as the photographs' full resolution whatever `fit.downscale` (at half resolution 2x2 rays a
    pixel missed a third of them: the cup's 27 % of its UV square seen against 42 %)."""
    from ..render import seen_texels

    return seen_texels(scene, width, height, supersample=2 * downscale)


def resampled_iou(true_material, true_masks: dict, sizes: dict, seen) -> dict[str, float]:
    """What free mask textures of these sizes (key -> (width, height)) can hold: layer name ->
    `mask_iou` of the truth with those painted textures resampled to the sizes (as a fit starts
    from a file: `start_texels`) against the truth itself (`true_masks`, `masks`), over `seen`.
    Below one where the truth paints finer than a texel (the cup's bands at 64x32 texels:
    stain 0.76, lime 0.88)."""
    if not sizes:
        return {}
    import tempfile

    from ..material.textures import start_texels

    layers = true_material.bsdf["layers"].split(",")
    with tempfile.TemporaryDirectory(prefix="layerfit-resampled-") as folder:
        files = {}
        for key, size in sizes.items():
            files[key] = Path(folder) / f"{key}.exr"
            write_image(files[key], start_texels(true_material, key, tuple(size)))
        resampled = masks(true_material.with_textures(files))
    iou = mask_iou(resampled, true_masks, layers, seen)
    return {k.removesuffix(".mask.texture"): iou[k.removesuffix(".mask.texture")] for k in sizes}


def masks(material) -> dict[str, np.ndarray]:
    """Each layer's mask (texture x fbm at the fitted values) baked in UV space."""
    from ..render import bake_texture

    bsdf = material.bsdf
    if bsdf.get("type") != "layered":
        return {}
    return {
        f"{name}.mask": bake_texture(bsdf[f"{name}_mask"], 256, 256)
        for name in bsdf["layers"].split(",")
        if f"{name}_mask" in bsdf
    }


def _labels(values: dict) -> list[str]:
    """One label per component of the solver's vector (`glaze.pigment[0]`, `glaze.ior`)."""
    out = []
    for key, value in values.items():
        size = np.size(value)
        out += [key] if size == 1 else [f"{key}[{i}]" for i in range(size)]
    return out


def _summary(cfg, capture, held, start, result, wall, panels, interrupted, free, phases) -> dict:
    truth = capture.truth
    errors, z = {}, {}
    for key, value in result.values.items():
        if key in truth:
            error = np.asarray(value, float) - np.asarray(truth[key], float)
            errors[key] = error.tolist()
            std = (result.std or {}).get(key)
            if std is not None:  # an undetermined (infinite) or zero sd gives no ratio
                sd = np.asarray(std, float)
                ratio = np.where(np.isfinite(sd) & (sd > 0), error / np.maximum(sd, 1e-30), np.nan)
                z[key] = ratio.tolist()
    return {
        "config": str(Path(cfg.path).resolve()),
        "capture": str(cfg.capture),
        "capture_warnings": list(capture.warnings),
        "interrupted": interrupted,
        "phases": [
            {**p.model_dump(exclude=set(p.model_extra or ())), **p.options.model_dump()}
            for p in phases
        ],
        "outcomes": [r.as_dict() for r in result.reports],
        "seed": cfg.seed,
        "downscale": cfg.downscale,  # the photos' area-averaging before any phase's own
        "config_identity": config_identity(cfg),
        # the material's structural choices (lobes, coupling, Fresnel, noise scales)
        "options": dict(cfg.material.options),
        "holdout": [capture.views[i].name for i in held],
        "start": start,
        "values": result.values,
        "std": result.std,
        "correlation": None if result.correlation is None else result.correlation.tolist(),
        # the correlation's: its scalars and gains (a texture's texels have none)
        "correlation_labels": _labels(
            {k: v for k, v in result.values.items() if k not in {f.key for f in free if f.shape}}
        ),
        "poorly_determined": result.poorly_determined,
        # values that ended at a bound: the truth there, past it, or a local minimum
        "at_bounds": at_bounds(free, result.values),
        "truth": {k: truth[k] for k in result.values if k in truth},
        "error": errors,
        "error_over_std": z,
        "views": [{"name": p.name, "rmse": p.rmse, "held_out": p.held_out} for p in panels],
        "textures": {
            key: {
                "file": f"{key}.exr",
                "sd_file": f"{key}.sd.exr",
                # over the texels the photographs say something of (below a uniform value's sd)
                "median_sd": _median_sd(sd, next(f for f in free if f.key == key)),
                "smoothness": (result.texture_weight or {}).get(key),
                "seen": (result.texture_seen or {}).get(key),
            }
            for key, sd in (result.texture_std or {}).items()
        },
        "loss": result.loss,
        "history": result.history,
        "phase_ends": result.phase_ends,
        "wall_time_s": wall,
        "software": software_versions(),
    }


def _median_sd(sd: np.ndarray, f) -> float | None:
    """The median texel sd of free texture `f` over the texels whose sd is below that of a value
    uniform over its bounds (what a texel no pixel sees is given); None where there are none."""
    cap = uniform_sd(f)
    below = np.asarray(sd)[np.asarray(sd) < cap * (1 - 1e-4)]
    return float(np.median(below)) if below.size else None


def _finite(value):
    """JSON-safe: non-finite floats become None (JSON has no NaN or Infinity)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, float | np.floating) and not math.isfinite(value):
        return None
    if isinstance(value, np.generic):
        return value.item()
    return value


#: The lock file of a run folder while a process writes it (removed when it ends).
LOCK = ".layerfit-lock"


@contextlib.contextmanager
def owned(out: Path) -> Iterator[None]:
    """Inside, this process owns the run folder `out` (created if need be): a second fit or
    batch task into it is refused with one line naming this process. The lock is the kernel's
    (`flock`), so a process killed while it held it holds it no longer: its lock file is taken
    over."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / LOCK
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.read(fd, 500).decode(errors="replace").strip()
            os.close(fd)
            raise _taken(out, holder) from None
        try:  # the file its last owner removed as we opened it is not the lock: open anew
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    stamp = time.strftime("%Y-%m-%d %H:%M:%S")
    os.ftruncate(fd, 0)
    os.write(fd, f"process {os.getpid()} on {socket.gethostname()}, since {stamp}".encode())
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            path.unlink()
        os.close(fd)


def check_free(out: Path) -> None:
    """Refuse a run folder another process owns (`owned`), naming it; before any other check of
    the folder, which would only say it is not empty."""
    try:
        fd = os.open(out / LOCK, os.O_RDONLY)
    except OSError:  # no lock file (or none readable: `owned` will tell)
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        raise _taken(out, os.read(fd, 500).decode(errors="replace").strip()) from None
    finally:
        os.close(fd)


def _taken(out: Path, holder: str) -> InputError:
    return InputError(
        f"--out {out}: another fit is writing this run folder ({holder or 'another process'}); "
        "wait for it to end, or choose another folder"
    )
