"""Photometric-stereo folders (DiLiGenT's layout) of objects that are not balls: the geometry is
the height field of their normal map, and renders of it match the photographs.

The folders are made here: a torus (lying flat, or tilted so that its ring hides part of itself)
rendered orthographically under distant lights, its normal map and mask from the same renderer.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from captures.errors import CaptureError  # noqa: E402
from captures.geometry import MeshData  # noqa: E402
from captures.importers import diligent_capture, fit_sphere_to_mask  # noqa: E402
from captures.scene import Camera, MeshArrays, Sphere  # noqa: E402

W, H = 96, 80
#: Unit directions towards the lights (camera frame: x right, y up, z towards the camera).
LIGHTS = np.array([[0.0, 0.0, 1.0], [0.5, 0.3, 0.81], [-0.45, 0.2, 0.87], [0.1, -0.55, 0.83]])
INTENSITY = np.array([[1.0, 0.9, 0.8], [2.0, 2.0, 2.0], [1.5, 1.4, 1.6], [0.7, 0.8, 0.9]])
BSDF = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.35, 0.2]}}


def torus(major: float, minor: float, tilt_deg: float, n: int = 192) -> MeshData:
    """A torus about the z axis, tilted about x by `tilt_deg`, in pixels."""
    u, v = np.meshgrid(np.arange(n + 1) / n, np.arange(n // 2 + 1) / (n // 2), indexing="ij")
    phi, theta = 2 * np.pi * u, 2 * np.pi * v
    normal = np.stack([np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), np.sin(theta)])
    position = major * np.stack([np.cos(phi), np.sin(phi), 0 * phi]) + minor * normal
    t = np.radians(tilt_deg)
    rotate = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    position = np.einsum("ij,jab->abi", rotate, position).reshape(-1, 3)
    normal = np.einsum("ij,jab->abi", rotate, normal).reshape(-1, 3)
    faces = []
    for i in range(n):
        for j in range(n // 2):
            a, b = i * (n // 2 + 1) + j, (i + 1) * (n // 2 + 1) + j
            faces += [(a, b, b + 1), (a, b + 1, a + 1)]
    uv = np.stack([u, v], -1).reshape(-1, 2)
    return MeshData(position, np.asarray(faces, np.uint32), normal, uv)


def camera() -> Camera:
    """The camera `diligent_capture` builds for a W x H folder."""
    return Camera(
        (0.0, 0.0, 10.0 * max(W, H)), (0, 0, 0), (0, 1, 0), 0.0, W, H, "orthographic", 0.0, None, W
    )


def render_truth(
    data: MeshData, integrator: dict, light: np.ndarray | None, spp: int, bsdf: dict = BSDF
):
    from fit.render import render
    from fit.render.scene import mesh, sensor_dict

    scene = {
        "type": "scene",
        "integrator": integrator,
        "sensor": sensor_dict(camera(), spp),
        "object": mesh(data, "object", mi.load_dict(bsdf)),
    }
    if light is not None:
        scene["light"] = {
            "type": "directional",
            "direction": (-light).tolist(),
            "irradiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]},
        }
    return render(mi.load_dict(scene), spp)


def write_folder(folder, data: MeshData, bsdf: dict = BSDF, lights=LIGHTS) -> np.ndarray:
    """A DiLiGenT-layout folder of `data` with `bsdf` under `lights` (unit directions towards
    them): 16-bit linear PNGs (each scaled by its light's intensity), light files, mask.png and
    Normal_gt.mat. Returns the normal map."""
    import OpenImageIO as oiio
    from scipy.io import savemat

    folder.mkdir()
    normals = render_truth(data, {"type": "aov", "aovs": "nn:sh_normal"}, None, 64)
    length = np.linalg.norm(normals, axis=-1)
    mask = length > 0.98  # covered whole by the object
    normals = np.where(mask[..., None], normals / np.maximum(length, 1e-9)[..., None], 0.0)
    savemat(folder / "Normal_gt.mat", {"Normal_gt": normals})
    out = oiio.ImageOutput.create(str(folder / "mask.png"))
    out.open(str(folder / "mask.png"), oiio.ImageSpec(W, H, 1, "uint8"))
    out.write_image((mask[..., None] * 255).astype(np.uint8))  # (H, W, 1): OIIO misreads 2-D
    out.close()
    names = []
    intensities = np.resize(INTENSITY, (len(lights), 3))
    for k, (light, intensity) in enumerate(zip(lights, intensities, strict=True)):
        direction = light / np.linalg.norm(light)
        image = render_truth(data, {"type": "direct"}, direction, 64, bsdf)
        scaled = np.clip(image * intensity * 0.5, 0, 1)
        name = f"{k:03d}.png"
        out = oiio.ImageOutput.create(str(folder / name))
        out.open(str(folder / name), oiio.ImageSpec(W, H, 3, "uint16"))
        out.write_image(np.round(scaled * 65535).astype(np.uint16))
        out.close()
        names.append(name)
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", lights / np.linalg.norm(lights, axis=1)[:, None])
    np.savetxt(folder / "light_intensities.txt", intensities * 0.5)
    return normals


@pytest.mark.parametrize("tilt", [0.0, 70.0])
def test_a_torus_folder_renders_like_its_photographs(tmp_path, tilt):
    """A torus (tilted: its ring hides part of itself, depth jumps at the occluding edge) becomes
    a height field whose renders match the photographs; the fitted-disc sphere would not."""
    from fit.render import load_scene, render
    from fit.render.scene import scene_dict

    write_folder(tmp_path / "torus", torus(27.0, 10.0, tilt))
    capture = diligent_capture(tmp_path / "torus")
    assert isinstance(capture.scene.geometry, MeshArrays)
    errors = []
    for i, view in enumerate(capture.views):
        image = render(load_scene(scene_dict(capture.scene_of(i), BSDF, 0, 64)), 64)
        inside = view.weight > 0
        assert inside.sum() > 0.4 * view.mask.sum()  # the pixels the height field covers whole
        diff = (image - view.image)[inside]
        errors.append(np.sqrt(np.mean(diff**2)) / np.sqrt(np.mean(view.image[inside] ** 2)))
    # shading from the measured normals (measured 0.2-0.4 %); the tilted torus's cast shadows
    # come from the integrated heights, which bridge its depth jump (one light: 6.4 %)
    assert max(errors) < (0.02 if tilt == 0 else 0.1), errors
    # what the loader made of every folder before: the sphere fitted to the mask (38-74 %)
    mask = capture.scene.meta["mask"]
    cx, cy, radius = fit_sphere_to_mask(mask)
    sphere = Sphere((cx - W / 2, H / 2 - cy, 0.0), radius)
    ball = replace(capture, scene=replace(capture.scene, geometry=sphere))
    image = render(load_scene(scene_dict(ball.scene_of(1), BSDF, 0, 16)), 16)
    inside = capture.views[1].weight > 0
    diff = (image - capture.views[1].image)[inside]
    assert np.sqrt(np.mean(diff**2)) / np.sqrt(np.mean(capture.views[1].image[inside] ** 2)) > 0.3


def test_a_ball_folder_stays_a_sphere(tmp_path):
    """Normals that agree with the sphere fitted to the mask: the analytic sphere."""
    n = 128
    u, v = np.meshgrid(np.arange(n + 1) / n, np.arange(n // 2 + 1) / (n // 2), indexing="ij")
    phi, theta = 2 * np.pi * u, np.pi * v
    normal = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    normal = normal.transpose(1, 2, 0).reshape(-1, 3)
    faces = []
    for i in range(n):
        for j in range(n // 2):
            a, b = i * (n // 2 + 1) + j, (i + 1) * (n // 2 + 1) + j
            faces += [(a, b, b + 1), (a, b + 1, a + 1)]
    ball = MeshData(30.0 * normal, np.asarray(faces, np.uint32), normal, np.zeros((len(normal), 2)))
    write_folder(tmp_path / "ball", ball)
    capture = diligent_capture(tmp_path / "ball")
    assert isinstance(capture.scene.geometry, Sphere)
    assert capture.scene.geometry.radius == pytest.approx(30.0, rel=0.03)


def test_a_shape_without_normals_is_refused(tmp_path):
    write_folder(tmp_path / "torus", torus(27.0, 10.0, 0.0))
    (tmp_path / "torus" / "Normal_gt.mat").unlink()
    with pytest.raises(CaptureError, match=r"mask.png: the object is not a ball .*Normal_gt.mat"):
        diligent_capture(tmp_path / "torus")


@pytest.mark.parametrize(
    "contents, message",
    [
        ({"normals": np.zeros((H, W))}, r"no 'Normal_gt' array \(holds: normals\)"),
        ({"Normal_gt": np.zeros((H, W))}, rf"'Normal_gt' is {H}x{W}, mask.png {H}x{W}"),
        ({"Normal_gt": np.zeros((H, W, 3))}, r"\d+ of the mask's \d+ pixels have no unit normal"),
        (None, r"not a MATLAB file"),
    ],
)
def test_bad_normal_maps_are_named(tmp_path, contents, message):
    from scipy.io import savemat

    write_folder(tmp_path / "torus", torus(27.0, 10.0, 0.0))
    path = tmp_path / "torus" / "Normal_gt.mat"
    if contents is None:
        path.write_text("not a mat file")
    else:
        savemat(path, contents)
    with pytest.raises(CaptureError, match=f"Normal_gt.mat: {message}"):
        diligent_capture(tmp_path / "torus")


def test_a_few_pixels_without_normals_are_left_out(tmp_path, caplog):
    from scipy.io import savemat

    normals = write_folder(tmp_path / "torus", torus(27.0, 10.0, 0.0))
    rows, columns = np.nonzero(np.linalg.norm(normals, axis=-1) > 0)
    normals[rows[:20], columns[:20]] = np.nan
    savemat(tmp_path / "torus" / "Normal_gt.mat", {"Normal_gt": normals})
    capture = diligent_capture(tmp_path / "torus")
    assert isinstance(capture.scene.geometry, MeshArrays)
    assert np.isfinite(capture.scene.geometry.data.positions).all()
    assert all(not (v.weight[rows[:20], columns[:20]] > 0).any() for v in capture.views)
    (message,) = capture.warnings
    assert "fitted as the height field" in message and "next to the 20 without a unit" in message


def test_a_torus_folder_fits_its_reflectance(tmp_path):
    """`layerfit fit` on the tilted torus's folder (a height field, lights normalised by their
    intensities, downscaled by 2) recovers the Lambertian reflectance it was rendered with."""
    import json

    from cli_run import run_cli

    write_folder(tmp_path / "torus", torus(27.0, 10.0, 70.0))
    (tmp_path / "fit.toml").write_text(
        f'capture = "{(tmp_path / "torus").as_posix()}"\n'
        '[material]\ntype = "oren_nayar"\nreflectance = [0.5, 0.5, 0.5]\nsigma = 0.0\n'
        '[fit]\nfree = ["oren_nayar.reflectance"]\ndownscale = 2\nuncertainty_spp = 16\n'
        '[[fit.phases]]\nsolver = "adam"\nsteps = 100\nspp = 8\nlr = 0.1\n'
    )
    out = run_cli("fit", tmp_path / "fit.toml", "--out", tmp_path / "run")
    assert out.returncode == 0, out.stderr
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    (note,) = summary["capture_warnings"]  # what the loader made of the folder, kept
    assert "fitted as the height field" in note
    assert "fitted as the height field" in (tmp_path / "run" / "report.html").read_text()
    np.testing.assert_allclose(
        summary["values"]["oren_nayar.reflectance"], [0.6, 0.35, 0.2], atol=0.02
    )


@pytest.mark.parametrize("form", ["renamed", "png"])
def test_normals_under_another_name_or_as_png(tmp_path, form):
    """The .mat's one H x W x 3 array under another name, or DiLiGenT's Normal_gt.png
    ((n + 1) / 2, 16 bits) when there is no .mat: the same height field."""
    import OpenImageIO as oiio
    from scipy.io import savemat

    normals = write_folder(tmp_path / "torus", torus(27.0, 10.0, 0.0))
    reference = diligent_capture(tmp_path / "torus").scene.geometry.data
    (tmp_path / "torus" / "Normal_gt.mat").unlink()
    if form == "renamed":
        savemat(tmp_path / "torus" / "Normal_gt.mat", {"N": normals, "other": np.zeros(3)})
    else:
        path = str(tmp_path / "torus" / "Normal_gt.png")
        out = oiio.ImageOutput.create(path)
        out.open(path, oiio.ImageSpec(W, H, 3, "uint16"))
        out.write_image(np.round((normals + 1) / 2 * 65535).astype(np.uint16))
        out.close()
    data = diligent_capture(tmp_path / "torus").scene.geometry.data
    assert data.positions.shape == reference.positions.shape
    np.testing.assert_allclose(data.normals, reference.normals, atol=1e-3)
    np.testing.assert_allclose(data.positions, reference.positions, atol=0.05)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda n: n * [1, -1, 1], r"only \d+% of the normals point out of the object"),
        (lambda n: n[..., ::-1], r"only \d+% of the normals point out|face away"),
        (lambda n: n * [1, 1, -1], r"\d+% of the mask's normals face away from the camera"),
    ],
    ids=["y flipped", "channels swapped", "z flipped"],
)
def test_normals_in_another_convention_are_refused(tmp_path, change, message):
    """A normal map with an axis flipped or its channels swapped (silently a wrong height field
    before: held-out error 0.15-0.99 on the ball against 0.06-0.08) is refused."""
    from scipy.io import savemat

    normals = write_folder(tmp_path / "torus", torus(27.0, 10.0, 0.0))
    savemat(tmp_path / "torus" / "Normal_gt.mat", {"Normal_gt": change(normals)})
    with pytest.raises(CaptureError, match=message):
        diligent_capture(tmp_path / "torus")


def test_an_object_too_thin_for_a_height_field_is_refused(tmp_path):
    """A torus whose tube is under four pixels wide has (almost) no pixel with all eight
    neighbours inside: nothing to fit (an empty mesh crashed the renderer before; a thin one
    fitted nothing, silently)."""
    write_folder(tmp_path / "torus", torus(27.0, 1.8, 0.0))
    with pytest.raises(CaptureError, match=r"mask.png: .*too thin for a height field: \d+ pixels"):
        diligent_capture(tmp_path / "torus")


def test_a_normal_png_of_another_size_is_named(tmp_path):
    import OpenImageIO as oiio

    write_folder(tmp_path / "torus", torus(27.0, 10.0, 0.0))
    (tmp_path / "torus" / "Normal_gt.mat").unlink()
    path = str(tmp_path / "torus" / "Normal_gt.png")
    out = oiio.ImageOutput.create(path)
    out.open(path, oiio.ImageSpec(W - 3, H - 2, 3, "uint16"))
    out.write_image(np.full((H - 2, W - 3, 3), 32768, np.uint16))
    out.close()
    with pytest.raises(CaptureError, match=rf"Normal_gt.png: {W - 3}x{H - 2}, mask.png {W}x{H}"):
        diligent_capture(tmp_path / "torus")


def test_a_downscaled_folder_builds_its_height_field_at_its_resolution(tmp_path):
    """At downscale 2 the height field has a vertex per 2 x 2 block (a quarter of them) and
    renders at that resolution still match the (area-averaged) photographs."""
    from fit.render import load_scene, render
    from fit.render.scene import scene_dict

    write_folder(tmp_path / "torus", torus(27.0, 10.0, 0.0))
    full = diligent_capture(tmp_path / "torus").scene.geometry.data
    capture = diligent_capture(tmp_path / "torus", 2)
    data = capture.scene.geometry.data
    assert 0.15 < len(data.positions) / len(full.positions) < 0.3
    np.testing.assert_allclose(  # the same surface, in the same (full-resolution) pixels
        [data.positions[:, :2].min(0), data.positions[:, :2].max(0)],
        [full.positions[:, :2].min(0), full.positions[:, :2].max(0)],
        atol=2.0,
    )
    for i, view in enumerate(capture.views):
        image = render(load_scene(scene_dict(capture.scene_of(i), BSDF, 0, 64)), 64)
        inside = view.weight > 0.999
        diff = (image - view.image)[inside]
        error = np.sqrt(np.mean(diff**2)) / np.sqrt(np.mean(view.image[inside] ** 2))
        assert error < 0.02, (i, error)


def test_an_unreadable_mat_falls_back_to_the_png(tmp_path):
    """A Normal_gt.mat that cannot be read (here: not a MAT file) beside a usable Normal_gt.png:
    the PNG is read, with a warning naming the .mat's problem."""
    import OpenImageIO as oiio

    normals = write_folder(tmp_path / "torus", torus(27.0, 10.0, 0.0))
    path = str(tmp_path / "torus" / "Normal_gt.png")
    out = oiio.ImageOutput.create(path)
    out.open(path, oiio.ImageSpec(W, H, 3, "uint16"))
    out.write_image(np.round((normals + 1) / 2 * 65535).astype(np.uint16))
    out.close()
    (tmp_path / "torus" / "Normal_gt.mat").write_text("not a mat file")
    capture = diligent_capture(tmp_path / "torus")
    assert isinstance(capture.scene.geometry, MeshArrays)
    assert any(
        "not a MATLAB file" in w and "read Normal_gt.png instead" in w for w in capture.warnings
    )
