"""Importers of other formats into the in-memory `Capture`: the peer renderer's targets and the
DiLiGenT photometric-stereo benchmark."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .capture import Capture, View
from .errors import CaptureError
from .images import read_image, read_linear, read_mask
from .peer import load_peer_scene
from .scene import Camera, DirectionalLight, Scene, Sphere
from .weights import validity


def peer_capture(scene_json: str | Path) -> Capture:
    """The peer target (`scene.json` + its linear EXR views) as a capture with its `[truth]`."""
    scene = load_peer_scene(scene_json)
    views = []
    for camera, path in zip(scene.cameras, scene.meta["images"], strict=True):
        image = read_image(path)[..., :3]
        if image.shape[:2] != (camera.height, camera.width):
            raise CaptureError(
                f"{path}: {image.shape[1]}x{image.shape[0]} but scene.json says "
                f"{camera.width}x{camera.height}"
            )
        # the object's pixels: any that differ from the constant environment (any coverage)
        mask = np.abs(image - np.asarray(scene.environment, np.float32)).sum(-1) > 1e-4
        image, weight = validity(image)
        views.append(View(Path(path).stem, image, weight, camera, mask=mask, mask_coverage=0.0))
    m = scene.meta["material"]
    truth = {
        "glaze.pigment": list(m["base_color"]),
        "glaze.roughness": m["specular_roughness"] ** 2,
        "glaze.ior": m["ior"],
        "glaze.sigma": m["diffuse_roughness"],
    }
    return Capture(scene, views, truth, Path(scene_json))


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
    for row, (name, direction, intensity) in enumerate(
        zip(names, directions, intensities, strict=True), 1
    ):
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
    try:
        cx, cy, radius = fit_sphere_to_mask(mask)
    except CaptureError as err:
        raise CaptureError(f"{folder / 'mask.png'}: {err}; give the object's mask") from None
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
        Sphere((cx - w / 2, h / 2 - cy, 0.0), radius),
        (camera,),
        (),
        (0.0, 0.0, 0.0),
        integrator="prb",
        max_depth=2,
        meta={"mask": mask},
    )
    views = []
    for name, direction, intensity in zip(names, directions, intensities, strict=True):
        path = folder / name
        if not path.exists():
            continue  # the benchmark's subsets ship some of the 96 images
        image, saturated, _ = read_linear(path, "linear")
        if image.shape[:2] != (h, w):
            raise CaptureError(f"{path}: {image.shape[1]}x{image.shape[0]}, mask is {w}x{h}")
        image, weight = validity(image / intensity.astype(np.float32), saturated, mask)
        light = DirectionalLight(tuple(-direction / np.linalg.norm(direction)), (1.0, 1.0, 1.0))
        views.append(View(path.stem, image, weight, camera, 1.0, (light,), mask))
    if not views:
        raise CaptureError(f"{folder}: none of the images in filenames.txt is present")
    return Capture(scene, views, {}, folder).downscaled(downscale)
