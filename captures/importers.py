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


def diligent_capture(folder: str | Path, downscale: int = 1) -> Capture:
    """A DiLiGenT object folder: one orthographic view per light, lights as distant sources from
    `light_directions.txt` (camera frame: x right, y up, z towards the camera), each image divided
    by its `light_intensities.txt` row; the sphere fitted to `mask.png`.

    World frame = camera frame, in pixels: the camera looks down -z from +z, the image's x to the
    right, y up; the sphere sits at z = 0.
    """
    folder = Path(folder)
    try:
        names = (folder / "filenames.txt").read_text().split()
        directions = np.loadtxt(folder / "light_directions.txt")
        intensities = np.loadtxt(folder / "light_intensities.txt")
    except FileNotFoundError as err:
        raise CaptureError(
            f"{folder}: not a DiLiGenT folder ({Path(err.filename).name} missing)"
        ) from None
    if not (len(names) == len(directions) == len(intensities)):
        raise CaptureError(f"{folder}: filenames, light directions and intensities differ in count")
    mask = read_mask(folder / "mask.png")
    h, w = mask.shape
    cx, cy, radius = fit_sphere_to_mask(mask)
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
