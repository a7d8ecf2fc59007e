"""Importers of other formats into the in-memory `Capture`: the peer renderer's targets and the
DiLiGenT photometric-stereo benchmark."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .capture import Capture, View, check_valid, check_view_names, pixel_warnings
from .errors import CaptureError
from .geometry import block_normals, covered_blocks, covered_pixels, normal_map_mesh
from .images import (
    colour_channels,
    image_part,
    read_image,
    read_linear,
    read_mask,
    srgb_encode,
)
from .peer import load_peer_scene
from .scene import Camera, DirectionalLight, MeshArrays, Scene, Sphere
from .weights import validity

log = logging.getLogger(__name__)


#: The model the shared peer targets declare (`material.model`): the glaze with the paper's
#: coupling and exact Fresnel, its diffuse lobe Cycles' (EON with `diffuse_roughness` > 0).
PEER_MODEL = (
    "mix(fresnel_dielectric(ior, shading normal), oren_nayar(base_color, diffuse_roughness), "
    "beckmann_reflection(alpha = specular_roughness**2, white))"
)
GLAZE_MODEL = "".join(PEER_MODEL.split())


def peer_capture(scene_json: str | Path) -> Capture:
    """The peer target (`scene.json` + its views) as a capture with its `[truth]`.

    Views are linear radiance (EXR, HDR, PFM: floating point, as stored); an 8- or 16-bit file
    (PNG, TIFF, JPEG) is taken as sRGB-encoded, with a warning (a renderer's display output). The
    truth holds the material table's keys that are present (`base_color`, `specular_roughness`,
    `ior`, `diffuse_roughness`); a missing one is a warning, not an error. A diffuse roughness
    above 0 is Cycles' EON roughness: the glaze's sigma with `diffuse = "eon"`
    (`Capture.truth_options`), not the qualitative Oren-Nayar's."""
    scene = load_peer_scene(scene_json)
    views, warnings = [], list(scene.meta.get("warnings", ()))
    check_view_names(scene.meta["images"], scene_json)
    for i, (camera, path) in enumerate(zip(scene.cameras, scene.meta["images"], strict=True)):
        levels = _integer_levels(path)
        encoding = "linear" if levels is None else "srgb"
        _check_opaque_film(path, f"{scene_json}: views[{i}]")
        image, saturated, warned = read_linear(path, encoding)
        warnings += warned
        if encoding == "srgb":
            warnings.append(
                f"{path}: an integer image; read as sRGB-encoded (a peer's views are usually "
                "linear EXR: give those for exact radiance)"
            )
        if image.shape[:2] != (camera.height, camera.width):
            raise CaptureError(
                f"{scene_json}: views[{i}]: {Path(path).name} is {image.shape[1]}x"
                f"{image.shape[0]} but width and height say {camera.width}x{camera.height}; "
                "give the image's size (a render at another resolution percentage, or cropped, "
                "or with overscan, is not the camera's view)"
            )
        # the object's pixels: any that differ from the constant environment (any coverage), by
        # more than a code value of an integer file (its background varies by its rounding)
        environment = np.asarray(scene.environment, np.float32)
        if levels is None:
            mask = np.abs(image - environment).sum(-1) > 1e-4
        else:
            codes = np.abs(srgb_encode(image) - srgb_encode(environment)) * levels
            mask = codes.max(-1) > 1.5
        warnings += pixel_warnings(image, path)
        image, weight = validity(image, saturated)
        check_valid(weight, f"{scene_json}: views[{i}].image: {Path(path).name}")
        views.append(View(Path(path).stem, image, weight, camera, mask=mask, mask_coverage=0.0))
    material = scene.meta["material"]
    if not isinstance(material, dict):
        raise CaptureError(
            f"{scene_json}: material is {type(material).__name__}; give a table of its values"
        )
    read = ("model", "base_color", "specular_roughness", "ior", "diffuse_roughness")
    extra = sorted(k for k in material if k not in read)
    if extra:  # another exporter's inputs (a Principled BSDF's coat, specular level): not scored
        warnings.append(
            f"{scene_json}: material has field(s) {', '.join(map(repr, extra))} this version "
            f"does not read: ignored, though they may change the picture (it reads "
            f"{', '.join(read)}); the truth is scored as if they were absent"
        )
    truth, missing = {}, []
    for key, name, size, low, high in (
        ("glaze.pigment", "base_color", 3, 0.0, 1.0),
        ("glaze.roughness", "specular_roughness", 1, 0.0, 1.0),
        ("glaze.ior", "ior", 1, 1.0, 10.0),
        ("glaze.sigma", "diffuse_roughness", 1, 0.0, 1.0),
    ):
        if name not in material:
            missing.append(name)
            continue
        value = material[name]
        values = value if isinstance(value, list) else [value]
        if not (
            len(values) == size
            and all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)
            and all(low <= v <= high for v in values)
        ):
            what = f"{size} numbers" if size > 1 else "a number"
            raise CaptureError(
                f"{scene_json}: material.{name} = {value!r}; give {what} in [{low:g}, {high:g}]"
            )
        floats = [float(v) for v in values]
        if name == "specular_roughness":  # Cycles' roughness r: Beckmann alpha = r^2
            floats = [floats[0] ** 2]
        truth[key] = floats if size > 1 else floats[0]
    model = material.get("model")
    if isinstance(model, str) and "".join(model.split()) != GLAZE_MODEL:
        warnings.append(
            f"{scene_json}: material.model = {model!r} is not the glaze's model ({PEER_MODEL}): "
            "its values are scored against a different BSDF, expect the fit to differ"
        )
    options = {}
    if truth.get("glaze.sigma", 0.0) > 0:
        # Cycles' diffuse roughness is the roughness of Fujii's improved Oren-Nayar with the
        # OpenPBR multiple-scattering term (EON), a number in [0, 1]: the glaze's sigma with
        # `diffuse = "eon"`, not the qualitative Oren-Nayar's facet slope in radians
        options["glaze.diffuse"] = "eon"
    if missing:
        warnings.append(
            f"{scene_json}: the material table has no {', '.join(missing)}: those parameters "
            "have no truth to score against"
        )
    for message in warnings:
        log.warning(message)
    return Capture(scene, views, truth, Path(scene_json), warnings, options)


#: A peer view with alpha 0 on more than this share of its pixels was rendered on a transparent
#: film: its background is not the environment the scene declares.
TRANSPARENT_SHARE = 0.01


def _check_opaque_film(path: Path, where: str) -> None:
    """Refuse a view rendered with a transparent film (Blender: Render > Film > Transparent): its
    background is black with alpha 0, not the declared environment, so the object's mask came
    out wrong and the fit compared the environment with black (it warned only that alpha was
    ignored, then of a poor silhouette overlap blaming the mesh's axes)."""
    try:
        part, spec, _ = image_part(path)
    except CaptureError:
        return  # `read_linear` names the problem
    chosen = colour_channels(list(spec.channelnames))  # a multi-layer file's pass too
    if isinstance(chosen, str) or chosen[1] is None:
        return
    k = chosen[1]
    alpha = read_image(path, (k, k + 1), part)[..., 0]
    share = float(np.mean(alpha <= 0.0))
    if share > TRANSPARENT_SHARE:
        raise CaptureError(
            f"{where}: {path.name} has alpha 0 on {share:.0%} of its pixels: it was rendered "
            "on a transparent film, so its background is not the scene's environment; render "
            "it with the film opaque (Blender: Render > Film > Transparent off)"
        )


def _integer_levels(path: Path) -> int | None:
    """The top code of an integer image file (255, 65535, ...), None for floating point (and for
    a file OpenImageIO cannot open: `read_linear` names the problem)."""
    import OpenImageIO as oiio

    buf = oiio.ImageInput.open(str(path)) if Path(path).is_file() else None
    if buf is None:
        return None
    try:
        kind = buf.spec().format.basetype
    finally:
        buf.close()
    return {oiio.UINT8: 255, oiio.UINT16: 65535, oiio.UINT32: 2**32 - 1}.get(kind)


def fit_sphere_to_mask(mask: np.ndarray) -> tuple[float, float, float]:
    """(centre x, centre y, radius) in pixels of a disc mask: its centroid and equal-area radius
    (pixel centres at +0.5)."""
    ys, xs = np.nonzero(mask)
    if len(xs) < 10:
        raise CaptureError("the object mask has fewer than 10 pixels: cannot fit a sphere")
    return float(xs.mean() + 0.5), float(ys.mean() + 0.5), float(np.sqrt(len(xs) / np.pi))


def _diligent_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CaptureError(
            f"{path}: missing; a DiLiGenT folder holds filenames.txt, light_directions.txt, "
            "light_intensities.txt and mask.png"
        ) from None
    except UnicodeDecodeError:
        raise CaptureError(f"{path}: not text; give the benchmark's file") from None
    except OSError as err:
        raise CaptureError(f"{path}: cannot read ({err.strerror})") from None


def _diligent_rows(path: Path) -> np.ndarray:
    """The (N, 3) finite numbers of a DiLiGenT light file, or a one-line `CaptureError`."""
    rows = []
    for number, line in enumerate(_diligent_text(path).splitlines(), 1):
        if not line.strip():
            continue
        try:
            values = [float(v) for v in line.split()]
        except ValueError:
            raise CaptureError(
                f"{path}: row {number} is {line.strip()[:40]!r}; each row is three numbers"
            ) from None
        if len(values) != 3 or not all(np.isfinite(values)):
            raise CaptureError(
                f"{path}: row {number} is {line.strip()[:40]!r}; each row is three finite numbers"
            )
        rows.append(values)
    return np.asarray(rows, dtype=np.float64).reshape(-1, 3)


def diligent_capture(folder: str | Path, downscale: int = 1) -> Capture:
    """A DiLiGenT object folder: one orthographic view per light, lights as distant sources from
    `light_directions.txt` (camera frame: x right, y up, z towards the camera), each image divided
    by its `light_intensities.txt` row; the sphere fitted to `mask.png`.

    World frame = camera frame, in pixels: the camera looks down -z from +z, the image's x to the
    right, y up; the sphere sits at z = 0.

    Geometry (`diligent_geometry`): the sphere fitted to `mask.png` where the object is a ball,
    else the height field of its `Normal_gt.mat`.
    """
    folder = Path(folder)
    names = _diligent_text(folder / "filenames.txt").split()
    directions = _diligent_rows(folder / "light_directions.txt")
    intensities = _diligent_rows(folder / "light_intensities.txt")
    if not (len(names) == len(directions) == len(intensities)):
        raise CaptureError(
            f"{folder}: filenames.txt has {len(names)} names but light_directions.txt "
            f"{len(directions)} rows and light_intensities.txt {len(intensities)}; give one row "
            "per image in each"
        )
    listed = folder / "filenames.txt"
    seen: dict[str, int] = {}
    for row, (name, direction, intensity) in enumerate(
        zip(names, directions, intensities, strict=True), 1
    ):
        if name in seen:  # two views of one name: a manifest's or a peer's are refused too
            raise CaptureError(
                f"{listed}: row {row} ({name}) repeats row {seen[name]}; list each image once "
                "(and its rows in light_directions.txt and light_intensities.txt)"
            )
        seen[name] = row
        if not (folder / name).resolve().is_relative_to(folder.resolve()):
            raise CaptureError(
                f"{listed}: row {row} ({name}) is outside the folder; keep the images in it"
            )
        if not np.linalg.norm(direction) > 1e-6:
            raise CaptureError(
                f"{folder / 'light_directions.txt'}: row {row} ({name}) is the zero vector; give "
                "the unit direction towards the light"
            )
        if not np.all(intensity > 0):
            raise CaptureError(
                f"{folder / 'light_intensities.txt'}: row {row} ({name}) is {intensity.tolist()}; "
                "every intensity must be > 0 (each image is divided by its row)"
            )
    mask = read_mask(folder / "mask.png")
    h, w = mask.shape
    warnings: list[str] = []
    geometry, covered = diligent_geometry(folder, mask, warnings, downscale)
    for message in warnings:
        log.warning(message)
    camera = Camera(
        origin=(0.0, 0.0, 10.0 * max(w, h)),
        target=(0.0, 0.0, 0.0),
        up=(0.0, 1.0, 0.0),
        fov_x_deg=0.0,
        width=w,
        height=h,
        kind="orthographic",
        ortho_width=float(w),
    )
    scene = Scene(
        geometry,
        (camera,),
        (),
        (0.0, 0.0, 0.0),
        integrator="prb",
        max_depth=2,
        meta={"mask": mask},
    )
    views, absent = [], []
    for row, (name, direction, intensity) in enumerate(
        zip(names, directions, intensities, strict=True), 1
    ):
        path = folder / name
        if not path.exists():
            absent.append(f"{name} (row {row})")
            continue  # the benchmark's subsets ship some of the 96 images
        image, saturated, _ = read_linear(path, "linear")
        if image.shape[:2] != (h, w):
            raise CaptureError(
                f"{path}: {image.shape[1]}x{image.shape[0]}, mask.png is {w}x{h}; give every "
                "image the mask's size (crop or scale them alike)"
            )
        image, weight = validity(image / intensity.astype(np.float32), saturated, covered)
        light = DirectionalLight(tuple(-direction / np.linalg.norm(direction)), (1.0, 1.0, 1.0))
        views.append(View(path.stem, image, weight, camera, 1.0, (light,), mask))
    if not views:
        raise CaptureError(f"{folder}: none of the images in filenames.txt is present")
    if absent:  # a typo drops its view: said, not silent
        shown = ", ".join(absent[:5]) + (f" and {len(absent) - 5} more" if len(absent) > 5 else "")
        warnings.append(f"{listed}: {len(absent)} of {len(names)} images absent, left out: {shown}")
    return Capture(scene, views, {}, folder, warnings).downscaled(downscale)


#: A normal map this close to the sphere fitted to its mask (median angle, degrees) is that
#: sphere (the DiLiGenT ball: 0.66); a mask without normals must cover its fitted disc this well
#: (intersection over union; the ball's 0.99).
SPHERE_ANGLE_DEG, DISC_IOU = 3.0, 0.95
#: The largest share of a mask's pixels whose normal may be missing (left out of the fit).
MAX_BAD_NORMALS = 0.05


def diligent_geometry(folder: Path, mask: np.ndarray, warnings: list[str], downscale: int = 1):
    """(geometry, the pixels it covers whole) of a photometric-stereo object seen along -z:
    the analytic sphere fitted to `mask` when the object is a ball (its `Normal_gt.mat` agrees
    with the sphere's normals, or, without one, the mask is a disc); otherwise the height field
    of `Normal_gt.mat` (`normal_map_mesh`; its weights keep only the pixels it covers whole).
    What a user should know is appended to `warnings`. With `downscale` k (the capture's) the
    height field has a vertex per k x k block (`block_normals`): the fit renders at that
    resolution, and a large map builds in seconds."""
    try:
        cx, cy, radius = fit_sphere_to_mask(mask)
    except CaptureError as err:
        raise CaptureError(f"{folder / 'mask.png'}: {err}; give the object's mask") from None
    h, w = mask.shape
    sphere = Sphere((cx - w / 2, h / 2 - cy, 0.0), radius)
    rows, columns = np.nonzero(mask)
    x, y = (columns + 0.5 - cx) / radius, (cy - rows - 0.5) / radius
    path = folder / "Normal_gt.mat"
    if not path.exists() and (folder / "Normal_gt.png").exists():
        path = folder / "Normal_gt.png"
    if not path.exists():
        yy, xx = np.mgrid[0:h, 0:w]
        inside = (xx + 0.5 - cx) ** 2 + (yy + 0.5 - cy) ** 2 <= radius**2
        iou = (mask & inside).sum() / max((mask | inside).sum(), 1)
        if iou < DISC_IOU:
            raise CaptureError(
                f"{folder / 'mask.png'}: the object is not a ball (its mask covers {iou:.0%} of "
                f"the disc fitted to it, a ball's {DISC_IOU:.0%} or more) and {path.name} is "
                "missing: put the object's normal map beside mask.png (MATLAB v5, 'Normal_gt', "
                "H x W x 3, or Normal_gt.png storing (n + 1) / 2)"
            )
        return sphere, mask
    try:
        normals, bad = read_normal_map(path, mask)
    except CaptureError as err:
        png = folder / "Normal_gt.png"
        if path.suffix != ".mat" or not png.exists():
            raise
        warnings.append(f"{err}; read {png.name} instead")
        path = png
        normals, bad = read_normal_map(path, mask)
    check_orientation(path, normals, mask, ~bad)
    full = mask
    if bad.any():
        mask = mask & ~bad
        rows, columns = np.nonzero(mask)
        x, y = (columns + 0.5 - cx) / radius, (cy - rows - 0.5) / radius
    z = np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, 1.0))
    cosine = np.sum(normals[rows, columns] * np.stack([x, y, z], -1), -1)
    angle = float(np.degrees(np.median(np.arccos(np.clip(cosine, -1.0, 1.0)))))
    if angle <= SPHERE_ANGLE_DEG:
        return sphere, full  # the sphere's own normals: pixels without a stored one fit too
    k = max(1, min(int(downscale), min(h, w) // 8))
    coarse_normals, coarse = (normals, mask) if k == 1 else block_normals(normals, mask, k)
    covered = covered_pixels(mask) if k == 1 else covered_blocks(coarse, k, (h, w))
    if covered.sum() < MIN_COVERED * k * k:
        raise CaptureError(
            f"{folder / 'mask.png'}: the object is not a ball (its normals {angle:.0f} deg off the "
            f"sphere fitted to the mask) and too thin for a height field: "
            f"{int(covered.sum()) // (k * k)} {'pixels' if k == 1 else f'{k}x{k} blocks'} have "
            f"all eight neighbours in the mask, {MIN_COVERED} are needed; give a larger image "
            "of it" + (" or a smaller downscale" if k > 1 else "")
        )
    lost = int(full.sum() - covered.sum())
    warnings.append(
        f"{path}: not a ball (its normals a median {angle:.0f} deg off the sphere fitted to the "
        f"mask): fitted as the height field of the normal map, on the {int(covered.sum())} mask "
        f"pixels it covers whole ({lost} at the mask's edge"
        + (f" or next to the {int(bad.sum())} without a unit normal" if bad.any() else "")
        + " left out)"
    )
    data = normal_map_mesh(coarse_normals, coarse, k, (h, w))
    return MeshArrays(data, str(path)), covered


#: The fewest pixels a height field must cover whole to be fitted.
MIN_COVERED = 16


def check_orientation(path: Path, normals: np.ndarray, mask: np.ndarray, valid: np.ndarray) -> None:
    """Refuse a normal map in another convention than the camera frame (x right, y up, z
    towards the camera): normals that face away from the camera, or that point into the object
    along its silhouette (where true normals point out of the mask: an axis flipped, channels
    swapped). Only pixels with a `valid` normal are judged; the outline is `mask`'s."""
    away = mask & valid & (normals[..., 2] < -0.05)
    if away.sum() > 0.05 * mask.sum():
        raise CaptureError(
            f"{path}: {away.sum() / mask.sum():.0%} of the mask's normals face away from the "
            "camera (negative z); store them in the camera's frame: x right, y up, z towards "
            "the camera"
        )
    from scipy.ndimage import binary_erosion, gaussian_filter

    edge = mask & ~binary_erosion(mask, np.ones((3, 3), bool), border_value=1)
    edge[0, :] = edge[-1, :] = edge[:, 0] = edge[:, -1] = False  # image border: no silhouette
    smooth = gaussian_filter(mask.astype(np.float64), 2.0)
    d_row, d_column = np.gradient(smooth)
    out_x, out_y = -d_column, d_row  # out of the mask, in the camera frame (rows go down)
    slanted = edge & valid & (np.hypot(normals[..., 0], normals[..., 1]) > 0.3)
    slanted &= np.hypot(out_x, out_y) > 1e-6
    if slanted.sum() < 20:
        return  # too little silhouette to judge
    agree = normals[..., 0] * out_x + normals[..., 1] * out_y > 0
    share = float(agree[slanted].mean())
    if share < 0.8:
        raise CaptureError(
            f"{path}: along the mask's outline only {share:.0%} of the normals point out of the "
            "object (a silhouette's normals all do): an axis is flipped or the channels are "
            "swapped; store them in the camera's frame: x right, y up, z towards the camera "
            "(in a PNG: (n + 1) / 2 as R, G, B)"
        )


def read_normal_map(path: Path, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A photometric-stereo normal map (H x W x 3, the camera's frame) made unit length, and the
    pixels of `mask` without a unit normal (zero there; at most `MAX_BAD_NORMALS` of the mask).

    From a MATLAB v5 file (`Normal_gt`, or its one H x W x 3 array under another name), or from
    an image storing `(n + 1) / 2` (DiLiGenT's `Normal_gt.png`, 8 or 16 bits, not colour-coded)."""
    if path.suffix.lower() != ".mat":
        stored = read_image(path)
        if stored.shape[2] < 3:
            raise CaptureError(f"{path}: {stored.shape[2]} channel(s); a normal map needs 3")
        if stored.shape[:2] != mask.shape:
            raise CaptureError(
                f"{path}: {stored.shape[1]}x{stored.shape[0]}, mask.png "
                f"{mask.shape[1]}x{mask.shape[0]}; give normals of the mask's size"
            )
        return _unit_normals(path, stored[..., :3] * 2.0 - 1.0, mask)
    from scipy.io import loadmat

    try:
        contents = loadmat(path)
    except NotImplementedError:
        raise CaptureError(
            f"{path}: a MATLAB v7.3 (HDF5) file; save it as v7 or older "
            "(save(..., '-v7')) with the normals in 'Normal_gt'"
        ) from None
    except IsADirectoryError:
        raise CaptureError(f"{path}: is a folder; give the normal map's file") from None
    except Exception as err:  # scipy raises ValueError, TypeError, OSError... for non-MAT files
        raise CaptureError(f"{path}: not a MATLAB file ({err})") from None
    normals = contents.get("Normal_gt")
    arrays = {k: v for k, v in contents.items() if not k.startswith("__")}
    if normals is None:
        shaped = [v for v in arrays.values() if getattr(v, "shape", None) == (*mask.shape, 3)]
        if len(shaped) != 1:
            names = ", ".join(arrays) or "none"
            raise CaptureError(
                f"{path}: no 'Normal_gt' array (holds: {names}); store the normals under that name"
            )
        normals = shaped[0]
    if normals.ndim != 3 or normals.shape != (*mask.shape, 3):
        raise CaptureError(
            f"{path}: 'Normal_gt' is {'x'.join(map(str, normals.shape))}, mask.png "
            f"{mask.shape[0]}x{mask.shape[1]}; give H x W x 3 normals of the same size"
        )
    return _unit_normals(path, normals, mask)


def _unit_normals(path: Path, normals, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`read_normal_map`'s result from the stored normals."""
    if np.iscomplexobj(normals) or not np.issubdtype(np.asarray(normals).dtype, np.number):
        raise CaptureError(f"{path}: the normals are not real numbers; store floats")
    normals = np.asarray(normals, np.float64)
    length = np.linalg.norm(normals, axis=-1)
    bad = mask & ~(np.abs(length - 1.0) < 0.1)  # NaN compares False: bad
    if bad.any():
        log.info("%s: %d mask pixels without a unit normal", path, int(bad.sum()))
    if bad.sum() > MAX_BAD_NORMALS * mask.sum():
        row, column = (int(v[0]) for v in np.nonzero(bad))
        raise CaptureError(
            f"{path}: {int(bad.sum())} of the mask's {int(mask.sum())} pixels have no unit "
            f"normal (e.g. row {row}, column {column}: length {length[row, column]:.3g}); give "
            "unit normals inside the mask"
        )
    return np.where(bad[..., None], 0.0, normals / np.maximum(length, 1e-12)[..., None]), bad
