"""Peer targets (a scene.json and its views): truth, materials, cameras, lights, bad input."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from image_files import _oiio_write

from captures import CaptureError
from captures.images import read_linear, write_image
from captures.importers import peer_capture


def test_peer_capture_truth(shared_data):
    capture = peer_capture(shared_data / "peer-cycles" / "sphere-blue" / "scene.json")
    assert capture.truth["glaze.roughness"] == pytest.approx(0.25**2)
    assert len(capture.views) == 3 and all(v.weight.mean() == 1 for v in capture.views)


def test_a_peer_targets_folder_opens_as_its_scene_json(shared_data, tmp_path):
    """`layerfit fit`'s capture may name the peer target's folder, as it may a manifest's; the
    folder was refused as holding "no capture.toml, scene.json" while it held a scene.json."""
    from captures import open_capture

    folder = shared_data / "peer-cycles" / "sphere-blue"
    capture = open_capture(folder)
    assert len(capture.views) == 3 and capture.truth == open_capture(folder / "scene.json").truth
    (tmp_path / "scene.json").mkdir()  # a folder by that name: one line, not a traceback
    with pytest.raises(CaptureError, match=r"scene\.json: cannot read"):
        open_capture(tmp_path / "scene.json")


def _peer_folder(folder: Path, image_name: str, material: dict) -> Path:
    """A one-view peer target: scene.json, a tetrahedron mesh and the view's file name."""
    import json

    folder.mkdir()
    (folder / "mesh.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
    )
    doc = {
        "mesh": "mesh.obj",
        "views": [
            {
                "image": image_name,
                "origin": [3, -3, 2],
                "target": [0, 0, 0],
                "up": [0, 0, 1],
                "fov_x_deg": 40,
                "width": 8,
                "height": 6,
            }
        ],
        "lights": [],
        "environment_radiance_rgb": [0.05, 0.05, 0.05],
        "material": material,
    }
    path = folder / "scene.json"
    path.write_text(json.dumps(doc))
    return path


def test_a_peer_target_in_png_is_decoded_as_srgb(tmp_path):
    """A peer's views given as 16-bit PNG (a display output) are sRGB-decoded, with a warning;
    read as stored they were 2x too bright in the mid-tones."""
    from captures.images import srgb_decode

    path = _peer_folder(tmp_path / "peer", "view_00.png", {"base_color": [0.5, 0.4, 0.3]})
    write_image(tmp_path / "peer" / "view_00.png", np.full((6, 8, 3), 0.2, np.float32))
    encoded = read_linear(tmp_path / "peer" / "view_00.png", "linear")[0]  # the file's codes
    capture = peer_capture(path)
    np.testing.assert_allclose(capture.views[0].image, srgb_decode(encoded), rtol=1e-5)
    assert any("read as sRGB-encoded" in w for w in capture.warnings)


def test_a_peer_material_table_may_lack_keys(tmp_path):
    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5, 0.4, 0.3]})
    write_image(tmp_path / "peer" / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
    capture = peer_capture(path)
    assert capture.truth == {"glaze.pigment": [0.5, 0.4, 0.3]}
    (warning,) = capture.warnings
    assert "no specular_roughness, ior, diffuse_roughness" in warning
    np.testing.assert_allclose(capture.views[0].image, 0.2, rtol=1e-3)  # EXR: linear as stored


def test_a_peer_diffuse_roughness_is_the_eon_sigma(tmp_path):
    """Cycles' diffuse roughness is EON's r in [0, 1]: the truth of the glaze's sigma with
    `diffuse = "eon"` (recorded in `truth_options`); 0 (Lambert) is sigma 0 in either lobe."""
    material = {"base_color": [0.5, 0.4, 0.3], "specular_roughness": 0.2, "ior": 1.5}
    lambert = _peer_folder(tmp_path / "a", "view_00.exr", {**material, "diffuse_roughness": 0.0})
    rough = _peer_folder(tmp_path / "b", "view_00.exr", {**material, "diffuse_roughness": 0.5})
    for folder in ("a", "b"):
        write_image(tmp_path / folder / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
    capture = peer_capture(lambert)
    assert capture.truth["glaze.sigma"] == 0.0 and capture.truth_options == {}
    capture = peer_capture(rough)
    assert capture.truth["glaze.sigma"] == 0.5 and capture.truth["glaze.ior"] == 1.5
    assert capture.truth_options == {"glaze.diffuse": "eon"}


def test_an_8_bit_peer_view_masks_only_the_object(tmp_path):
    """In an 8-bit view the constant background varies by its rounding: the object's mask must
    not take it for the object (IoU 0.30-0.34 on a peer sphere before)."""
    path = _peer_folder(tmp_path / "peer", "view_00.png", {"base_color": [0.5, 0.4, 0.3]})
    image = np.full((6, 8, 3), 0.05, np.float32)  # the environment below, as rounded to 8 bits
    image[2:4, 3:5] = 0.4  # the object
    import json

    doc = json.loads(path.read_text())
    doc["environment_radiance_rgb"] = [0.0503, 0.0497, 0.05]  # not exactly a code value
    path.write_text(json.dumps(doc))
    import OpenImageIO as oiio

    from captures.images import srgb_encode

    out = oiio.ImageOutput.create(str(tmp_path / "peer" / "view_00.png"))
    out.open(str(tmp_path / "peer" / "view_00.png"), oiio.ImageSpec(8, 6, 3, "uint8"))
    out.write_image(np.round(srgb_encode(image) * 255).astype(np.uint8))
    out.close()
    mask = peer_capture(path).views[0].mask
    assert mask.sum() == 4 and mask[2:4, 3:5].all()


@pytest.mark.parametrize(
    "material, message",
    [
        ({"base_color": 0.3}, r"material.base_color = 0.3; give 3 numbers in \[0, 1\]"),
        ({"base_color": "blue"}, r"material.base_color = 'blue'; give 3 numbers"),
        ({"ior": True}, r"material.ior = True; give a number in \[1, 10\]"),
        ({"diffuse_roughness": -0.2}, r"material.diffuse_roughness = -0.2; give a number"),
        ([1, 2], r"material is list; give a table of its values"),
    ],
)
def test_a_peer_material_table_with_bad_values_is_named(tmp_path, material, message):
    path = _peer_folder(tmp_path / "peer", "view_00.exr", material)
    write_image(tmp_path / "peer" / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
    with pytest.raises(CaptureError, match=message):
        peer_capture(path)


def _view(doc):
    return doc["views"][0]


def _light(doc):
    doc["lights"] = [
        {
            "type": "rectangle",
            "center": [3.0, -2.0, 3.0],
            "u_axis": [1.0, 0.0, 0.0],
            "v_axis": [0.0, 1.0, 0.0],
            "emit_direction": [0.0, 0.0, -1.0],
            "size": [1.0, 1.0],
            "radiance_rgb": [10.0, 10.0, 10.0],
        }
    ]
    return doc["lights"][0]


@pytest.mark.parametrize(
    "part, change, message",
    [
        ("view", {"fov_x_deg": 200}, r"views\[0\]\.fov_x_deg: got 200; should be less"),
        ("view", {"origin": [0, 0, 0]}, r"views\[0\]\.target: equals origin"),
        ("view", {"origin": [float("nan"), 0, 0]}, r"views\[0\]\.origin\[0\]: got nan"),
        ("view", {"up": [3, -3, 2]}, r"views\[0\]\.up: .* along the viewing"),
        ("view", {"width": 0}, r"views\[0\]\.width: got 0"),
        ("view", {"image": 5}, r"views\[0\]\.image is 5; give the view's image"),
        ("view", {"type": "ORTHO"}, r'views\[0\]\.type = "ORTHO" changes the picture'),
        ("view", {"shift_x": 0.1}, r"views\[0\]\.shift_x = 0.1 changes the picture"),
        ("light", {"shape": "DISK"}, r'lights\[0\]\.shape = "DISK" changes the picture'),
        ("light", {"type": "point"}, r"lights\[0\]\.type = 'point'; .* capture.toml"),
        ("doc", {"environment_map": "env.exr"}, r'environment_map = "env.exr" changes the'),
        ("view", {"image": ""}, r'views\[0\]\.image is ""; give'),
        ("view", {"origin": [0.1, 0.1, 0.1]}, r"views\[0\]\.origin .* inside the object"),
        ("light", {"radiance_rgb": [-1, 1, 1]}, r"lights\[0\]\.radiance_rgb\[0\]: got -1"),
        ("light", {"size": [0, 1]}, r"lights\[0\]\.size\[0\]: got 0"),
        ("light", {"radiance_rgb": None}, r"lights\[0\] has no field 'radiance_rgb'"),
        ("doc", {"environment_radiance_rgb": [-1, 0, 0]}, r"environment_radiance_rgb\[0\]: got -1"),
        ("doc", {"views": []}, r"views must be a list of one or more"),
        ("doc", {"environment_radiance_rgb": "bright"}, r"environment_radiance_rgb: expected 3"),
        ("doc", {"environment_radiance_rgb": [0, 0, 0]}, r"the scene has no light; add lights"),
    ],
)
def test_a_peer_scene_passes_a_manifests_checks_named_by_its_fields(
    tmp_path, part, change, message
):
    """A peer scene.json's cameras, lights and environment were read without a manifest's checks:
    a field of view outside (0, 180) or a camera on its target was an internal error from the
    renderer, a NaN origin or a camera inside the object rendered nothing, a negative radiance
    or a light of no size was taken. Now each is one line naming the JSON's field."""
    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5, 0.4, 0.3]})
    write_image(tmp_path / "peer" / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
    doc = json.loads(path.read_text())
    table = {"view": _view, "light": _light, "doc": lambda d: d}[part](doc)
    table.update(change)
    for key in [k for k, v in change.items() if v is None]:  # a field left out
        del table[key]
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match=r"peer/scene\.json: " + message):
        peer_capture(path)


def test_a_peer_views_size_may_be_a_whole_float(tmp_path):
    """A script's computed resolution (160.0) is a whole number of pixels; 160.5 is not."""
    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5, 0.4, 0.3]})
    write_image(tmp_path / "peer" / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
    doc = json.loads(path.read_text())
    _view(doc).update(width=8.0, height=6.0)
    path.write_text(json.dumps(doc))
    assert peer_capture(path).views[0].image.shape == (6, 8, 3)
    _view(doc).update(width=8.5)
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match=r"views\[0\]\.width: got 8\.5"):
        peer_capture(path)


def test_a_peer_model_other_than_the_glaze_is_a_warning(tmp_path, shared_data):
    """The shared targets' `material.model` is the glaze (no warning, whatever the spacing); a
    target made with another BSDF (GGX here) says that its scores compare two models."""
    from captures.importers import PEER_MODEL

    shared = json.loads((shared_data / "peer-cycles" / "torus-amber" / "scene.json").read_text())
    assert "".join(shared["material"]["model"].split()) == "".join(PEER_MODEL.split())
    material = {"base_color": [0.5, 0.4, 0.3], "specular_roughness": 0.2, "ior": 1.5}
    material["diffuse_roughness"] = 0.0
    for name, model, warned in (
        ("same", PEER_MODEL.replace(", ", ","), False),
        ("ggx", PEER_MODEL.replace("beckmann", "ggx"), True),
    ):
        path = _peer_folder(tmp_path / name, "view_00.exr", {**material, "model": model})
        write_image(tmp_path / name / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
        warnings = peer_capture(path).warnings
        assert any("is not the glaze's model" in w for w in warnings) == warned, warnings


def test_a_peer_target_is_checked_as_a_manifest_is(tmp_path):
    """What a manifest refuses or warns of, a peer target does too: two views named alike
    (their gains collided: an internal error after the whole fit), a view with no valid pixel
    (fitted as a perfect match, relative RMSE 0), NaN pixels; a light that is not one-sided is
    refused; fields this version does not read, and no environment, are warned."""
    import json

    path = _peer_folder(tmp_path / "peer", "a/view.exr", {"base_color": [0.5, 0.4, 0.3]})
    doc = json.loads(path.read_text())
    doc["views"].append({**doc["views"][0], "image": "b/view.exr"})
    for name in ("a", "b"):
        (tmp_path / "peer" / name).mkdir()
        write_image(tmp_path / "peer" / name / "view.exr", np.full((6, 8, 3), 0.2, np.float32))
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match=r"views\[1\]\.image: view.exr has the name of views\["):
        peer_capture(path)

    doc["views"] = doc["views"][:1]
    doc["views"][0]["image"] = "black.exr"
    path.write_text(json.dumps(doc))
    write_image(tmp_path / "peer" / "black.exr", np.zeros((6, 8, 3), np.float32))
    with pytest.raises(CaptureError, match=r"views\[0\]\.image: black.exr has no valid pixel"):
        peer_capture(path)

    nan = np.full((6, 8, 3), 0.2, np.float32)
    nan[0, 0] = np.nan
    write_image(tmp_path / "peer" / "black.exr", nan)
    doc["views"][0]["exposure"] = 1.0  # another exporter's field
    doc["lights"] = [
        {
            "type": "rectangle",
            "center": [0, 0, 3],
            "emit_direction": [0, 0, -1],
            "u_axis": [1, 0, 0],
            "v_axis": [0, -1, 0],
            "size": [1, 1],
            "radiance_rgb": [5, 5, 5],
            "one_sided": False,
        }
    ]
    del doc["environment_radiance_rgb"]
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match=r"lights\[0\]\.one_sided = False: layerfit's rect"):
        peer_capture(path)
    doc["lights"][0]["one_sided"] = True
    path.write_text(json.dumps(doc))
    warnings = peer_capture(path).warnings
    assert any("black.exr: 1 NaN/Inf pixels get weight 0" in w for w in warnings)
    assert any("views[0] has field(s) 'exposure' this version does not read" in w for w in warnings)
    assert any(
        "no environment_radiance_rgb: the environment is taken as black" in w for w in warnings
    )


def test_a_peer_truth_outside_the_bounds_is_fitted_not_scored(tmp_path, caplog):
    """A Cycles glaze of roughness 0.04 (alpha 0.0016, below the glaze's 0.002) could not be
    fitted at all: its truth was refused as a manifest's is ("choose a value inside them",
    which a peer's user cannot). The fit runs; that key is warned and not scored."""
    import logging

    from fit.commands.prepare import check_truth
    from fit.material import build_material, resolve

    material = {"base_color": [0.5, 0.4, 0.3], "specular_roughness": 0.04, "ior": 1.5}
    path = _peer_folder(tmp_path / "peer", "view_00.exr", material)
    write_image(tmp_path / "peer" / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
    capture = peer_capture(path)
    glaze = build_material({"type": "glaze"})
    free = resolve(glaze, ["glaze.roughness", "glaze.ior"])
    with caplog.at_level(logging.WARNING):
        check_truth(capture, free, path, glaze)
    assert "truth.glaze.roughness = 0.0016" in caplog.text and "not scored" in caplog.text
    assert "glaze.roughness" not in capture.truth and capture.truth["glaze.ior"] == 1.5


def test_another_exporters_peer_scene_is_read_or_named(tmp_path):
    """What another exporter writes: a Windows path (`renders\\view.exr`,
    refused as "no such image file"), a material with inputs this version does not read (a
    coat: silently scored as if absent; now a warning), a vertical field of view only, a render
    at another size (the error named neither the field nor the fix), UTF-16 text (a decode
    error)."""
    from captures.peer import load_peer_scene

    path = _peer_folder(tmp_path / "peer", "renders\\view_00.exr", {"base_color": [0.5] * 3})
    (tmp_path / "peer" / "renders").mkdir()
    write_image(tmp_path / "peer" / "renders" / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
    doc = json.loads(path.read_text())
    doc["material"]["coat_weight"] = 0.5
    path.write_text(json.dumps(doc))
    capture = peer_capture(path)
    assert capture.views[0].image.shape == (6, 8, 3)
    assert any("material has field(s) 'coat_weight'" in w for w in capture.warnings)
    _view(doc).update(width=16, height=12)
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match=r"views\[0\]: view_00.exr is 8x6 but width and height"):
        peer_capture(path)
    _view(doc).update(width=8, height=6, fov_y_deg=30)
    del _view(doc)["fov_x_deg"]
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match=r"views\[0\] has fov_y_deg but no fov_x_deg"):
        load_peer_scene(path)
    path.write_text(json.dumps(doc), encoding="utf-16")
    with pytest.raises(CaptureError, match="is UTF-16 text; save it as UTF-8"):
        load_peer_scene(path)


def test_a_peer_view_on_a_transparent_film_is_refused(tmp_path):
    """A Cycles render with Film > Transparent (background RGB 0, alpha 0): its background is
    not the declared environment; it was read with an "alpha ignored" warning and then a poor
    silhouette overlap blamed on the mesh's axes. Opaque RGBA reads."""
    import OpenImageIO as oiio

    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5] * 3})
    rgba = np.zeros((6, 8, 4), np.float32)
    rgba[2:4, 3:5] = 0.2, 0.2, 0.2, 1.0
    _oiio_write(tmp_path / "peer" / "view_00.exr", rgba, oiio.FLOAT)
    with pytest.raises(CaptureError, match=r"views\[0\]: view_00.exr has alpha 0 on 92%"):
        peer_capture(path)
    rgba[..., 3], rgba[..., :3] = 1.0, np.maximum(rgba[..., :3], 0.05)
    _oiio_write(tmp_path / "peer" / "view_00.exr", rgba, oiio.FLOAT)
    assert peer_capture(path).views[0].image.shape == (6, 8, 3)


def test_a_batchs_capture_check_reads_a_peer_scene_as_its_loader_does(tmp_path):
    """`check_capture` (a batch's check before Ray) read scene.json itself as plain UTF-8: a
    file with a byte-order mark, which the loader reads, was refused. It now calls the loader
    (no image read); a broken one is refused with its reason."""
    from captures.open import check_capture

    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5] * 3})
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    check_capture(tmp_path / "peer")  # no image on disk: not read
    path.write_text("{", encoding="utf-8")
    with pytest.raises(CaptureError, match="not valid JSON"):
        check_capture(path)


def _look_at_matrix(origin, target, up) -> list[list[float]]:
    """Blender's `matrix_world` of a camera at `origin` looking at `target`: columns x, y (up),
    z (backward) and the position."""
    back = np.subtract(origin, target, dtype=float)
    back /= np.linalg.norm(back)
    x = np.cross(up, back)
    x /= np.linalg.norm(x)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = x, np.cross(back, x), back, origin
    return matrix.tolist()


@pytest.mark.parametrize(
    "change, message",
    [
        (None, None),
        ({"origin": [3, -3, 2.5]}, r"puts the camera at \[3, -3, 2.5\], not at origin"),
        ({"target": [0.5, 0, 0]}, r"looks 5\.03 degrees away from target"),
        ({"up": [0.3, 0, 1]}, r"turns the camera \d+\.\d\d degrees about its view"),
        ("rows", r"= \[\[1, 0\], \[0, 1\]\]: expected a 4x4 matrix"),
    ],
)
def test_a_peer_views_camera_matrix_must_agree_with_its_look_at(tmp_path, change, message):
    """`blender_matrix_world` was listed as read but not read: a matrix of another camera (a
    stale export) beside the look-at values was silent. A disagreeing one is refused by what
    differs; an agreeing one reads."""
    from captures.peer import load_peer_scene

    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5] * 3})
    doc = json.loads(path.read_text())
    view = _view(doc)
    moved = {**view, **change} if isinstance(change, dict) else view
    matrix = _look_at_matrix(moved["origin"], moved["target"], moved["up"])
    view["blender_matrix_world"] = [[1, 0], [0, 1]] if change == "rows" else matrix
    path.write_text(json.dumps(doc))
    if message is None:
        load_peer_scene(path)
        return
    with pytest.raises(CaptureError, match=r"views\[0\]\.blender_matrix_world " + message):
        load_peer_scene(path)


@pytest.mark.parametrize("fov, warned", [(40, False), (0.698, True), (2.0, True)])
def test_a_field_of_view_in_radians_is_warned(tmp_path, caplog, fov, warned):
    """A field of view given in radians (Blender's `camera.data.angle`) was taken as degrees:
    0.698 saw a sliver of the object and only the silhouette's overlap warned. Where the object
    spans three times the value or more, the warning gives the value in degrees."""
    from captures.peer import load_peer_scene

    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5] * 3})
    doc = json.loads(path.read_text())
    _view(doc)["fov_x_deg"] = fov
    path.write_text(json.dumps(doc))
    with caplog.at_level(logging.WARNING):
        load_peer_scene(path)
    notes = [r.getMessage() for r in caplog.records if "in radians" in r.getMessage()]
    assert bool(notes) == warned
    if warned:
        assert f"views[0].fov_x_deg = {fov:g}" in notes[0]
        assert f"give {np.degrees(fov):.4g} (degrees)" in notes[0]


def test_a_telephoto_view_of_a_far_object_is_not_warned(tmp_path, caplog):
    """A narrow field of view that frames the object (a long lens far away) is not radians."""
    from captures.peer import load_peer_scene

    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5] * 3})
    doc = json.loads(path.read_text())
    _view(doc).update(origin=[300, -300, 200], fov_x_deg=0.5)
    path.write_text(json.dumps(doc))
    with caplog.at_level(logging.WARNING):
        load_peer_scene(path)
    assert not [r for r in caplog.records if "in radians" in r.getMessage()]
