"""The parameter table, the key grammar and the native preset (no rendering)."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from bundled import CUP, ROOT, SPHERE, cup_material, cup_table

from captures import InputError
from fit.config import load_fit_config, load_render_config
from fit.errors import ConfigError
from fit.material import (
    PRESET_SCHEMA,
    build_material,
    load_preset,
    parse_key,
    provenance,
    resolve,
    save_preset,
)


@pytest.mark.parametrize(
    "text, parts",
    [
        ("glaze.roughness", ("glaze", "roughness", False)),
        ("lime.mask.threshold", ("lime", "threshold", True)),
        ("bump", ("", "bump", False)),
        ("lights.scale", ("lights", "scale", False)),
    ],
)
def test_key_grammar_round_trips(text, parts):
    key = parse_key(text)
    assert (key.owner, key.name, key.mask) == parts and str(key) == text


@pytest.mark.parametrize("text", ["", "glaze.", "a.b.c", "glaze.mask", "1x.roughness", "a.b.c.d"])
def test_bad_keys_say_what_a_key_looks_like(text):
    with pytest.raises(KeyError, match=r"keys look like glaze\.roughness"):
        parse_key(text)


def test_table_lists_every_declared_parameter_of_what_was_built():
    material = cup_material()
    # every layer's declared parameters, the masks' (texture included) and the bump
    for name in ("clay.reflectance", "clay.sigma", "glaze.ior", "glaze.sigma", "stain.sigma"):
        assert name in material.params
    for layer in ("glaze", "lime", "stain"):
        for name in ("threshold", "softness", "texture"):
            assert f"{layer}.mask.{name}" in material.params
    assert material.params["bump"].value == pytest.approx(2e-4)
    assert material.params["glaze.roughness"].traverse == "glaze.roughness"
    assert material.params["glaze.pigment"].traverse == "glaze.pigment.value"
    assert material.params["lime.mask.texture"].traverse == "lime.mask.texture.data"
    assert material.params["lime.mask.texture"].texture.name == "lime.exr"
    assert material.options["lime.mask.scale"] == 24 and material.options["glaze.fresnel"]
    # a parameter the config leaves out is in the table at its declared default, and in the dict
    assert material.params["glaze.sigma"].value == 0.0 and material.bsdf["glaze"]["sigma"] == 0.0


def test_disabling_a_layer_keeps_the_others_keys():
    table = cup_table()
    for layer in table["layers"][1:]:
        layer["enabled"] = False
    material = build_material(table, CUP)
    assert material.bsdf["type"] == "oren_nayar"  # a stack of one is that layer
    assert [f.key for f in resolve(material, ["clay.sigma"])] == ["clay.sigma"]
    assert [f.traverse for f in resolve(material, ["clay.sigma"])] == ["sigma"]
    with pytest.raises(KeyError, match="no layer 'glaze' is built"):
        resolve(material, ["glaze.roughness"])
    with pytest.raises(KeyError, match="the bump comes from the masks of a stack of two or more"):
        resolve(material, ["bump"])
    # the stack with its bump at 0 (not built): it said "no layer '' is built"
    table = cup_table()
    flat = build_material({**table, "bump": 0.0}, CUP)
    with pytest.raises(KeyError, match=r"bump is 0 in \[material\], so it is not built; give"):
        resolve(flat, ["bump"])


def test_preset_round_trips_exactly_with_textures(tmp_path):
    material = cup_material()
    fitted = np.random.default_rng(0).uniform(0, 1, (8, 8, 1)).astype(np.float32)
    path = save_preset(
        material,
        tmp_path / "cup.toml",
        provenance("captures/samples/cup", loss=0.5, std={"glaze.ior": 0.01}),
        textures={"lime.mask.texture": fitted},
    )
    text = path.read_text()
    preset = load_preset(path)
    assert preset.provenance["std"] == {"glaze.ior": 0.01} and preset.provenance["loss"] == 0.5
    assert preset.material.values() == material.values()
    assert preset.material.options == material.options
    # textures beside it, by relative path: the painted ones copied, the fitted one written
    files = preset.material.texture_files()
    assert files["lime.mask.texture"] == tmp_path / "cup.lime.mask.texture.exr"
    assert (
        files["glaze.mask.texture"].read_bytes() == (CUP.parent / "textures/glaze.exr").read_bytes()
    )
    assert 'texture = "cup.glaze.mask.texture.exr"' in text
    from captures.images import read_image

    np.testing.assert_array_equal(read_image(files["lime.mask.texture"])[..., :1], fitted)
    # saving what was loaded writes the same file again
    again = save_preset(preset.material, tmp_path / "again" / "cup.toml", preset.provenance)
    assert again.read_text() == text


def test_single_plugin_preset_and_with_values(tmp_path):
    material = load_render_config(SPHERE).material
    fitted = material.with_values({"glaze.roughness": 0.3, "glaze.pigment": [0.1, 0.2, 0.3]})
    assert fitted.values()["glaze.roughness"] == 0.3 and fitted.bsdf["roughness"] == 0.3
    assert fitted.values()["glaze.ior"] == material.values()["glaze.ior"]
    preset = load_preset(save_preset(fitted, tmp_path / "p.toml"))
    assert preset.material.values() == fitted.values() and preset.material.bsdf == fitted.bsdf


def test_configs_accept_a_preset(tmp_path, shared_data):
    material = load_render_config(SPHERE).material
    save_preset(material, tmp_path / "glaze.toml")
    text = (ROOT / "configs" / "peer-sphere.toml").read_text()
    text = text.replace('"../../shared/data', f'"{shared_data}')
    start = text.index("[material]")
    end = text.index("[fit]")
    config = tmp_path / "fit.toml"
    config.write_text(text[:start] + 'material = "glaze.toml"\n' + text[end:])
    assert load_fit_config(config).material.values() == material.values()


@pytest.mark.parametrize(
    "edit, message",
    [
        (("schema = 1", "schema = 99"), "schema = 99 was written by a newer layerfit"),
        (("schema = 1", "schema = 0"), "schema = 0 is not a preset version"),
        (("schema = 1", 'schema = "1"'), "a preset starts with schema = 1"),
        (("schema = 1", "schema = 1\ncolour = 1"), "unknown key colour at the top level"),
        (("ior = 1.52", "ior = 9.0"), "ior = 9.0 is outside its bounds"),
        (("ior = 1.52", "iorr = 1.5"), "material.iorr: unknown key for glaze"),
        (("[provenance]", "[provenance]\nwho = 1"), "unknown key provenance.who"),
    ],
)
def test_bad_presets_are_one_line_errors(tmp_path, edit, message):
    material = load_render_config(SPHERE).material
    path = save_preset(material, tmp_path / "p.toml", provenance(loss=1.0))
    text = path.read_text()
    assert edit[0] in text
    path.write_text(text.replace(edit[0], edit[1], 1))
    with pytest.raises(InputError) as err:
        load_preset(path)
    assert message in str(err.value) and "p.toml" in str(err.value)
    assert "\n" not in str(err.value)


def test_a_preset_missing_keys_loads_with_a_warning_naming_them(tmp_path, caplog):
    """A preset layerfit writes lists every parameter and option; one that leaves some out (a
    hand edit, a line deleted) takes their defaults, and says which (it was silent)."""
    glaze = load_render_config(SPHERE).material
    for name, material in (("glaze", glaze), ("cup", cup_material())):
        path = save_preset(material, tmp_path / f"{name}.toml")
        with caplog.at_level("WARNING"):
            load_preset(path)
        assert not caplog.records, caplog.text  # complete: no word
        text = path.read_text()
        if name == "glaze":
            path.write_text(text.replace("ior = ", "# ior = ", 1))
            expected = ["material.ior"]
        else:  # the second layer's mask's softness, and the stack's bump
            doc = tomllib.loads(text)
            layer = doc["material"]["layers"][1]
            del layer["mask"]["softness"], doc["material"]["bump"]
            import tomli_w

            path.write_text(tomli_w.dumps(doc))
            expected = ["material.bump", f"material.{layer['name']}.mask.softness"]
        with caplog.at_level("WARNING"):
            loaded = load_preset(path)
        message = caplog.records[-1].getMessage()
        assert f"{name}.toml" in message and "default" in message
        assert all(key in message for key in expected), message
        assert loaded.material.values().keys() == material.values().keys() - {"bump"}  # off
        caplog.clear()
    # a stack with one layer left enabled, named as its type, is built as that layer (a flat
    # table): compared as one, complete
    doc = tomllib.loads(save_preset(cup_material(), tmp_path / "one.toml").read_text())
    for layer in doc["material"]["layers"]:
        layer["enabled"] = layer["name"] == "glaze"
    import tomli_w

    (tmp_path / "one.toml").write_text(tomli_w.dumps(doc))
    with caplog.at_level("WARNING"):
        one = load_preset(tmp_path / "one.toml").material
    assert "layers" not in one.table(), one.table()
    # complete; its bump (the masks' height) has no mask left to come from, and says so
    (record,) = caplog.records
    assert "one.toml: material.bump = 0.0002 is ignored" in record.getMessage()
    assert "only 'glaze' is enabled" in record.getMessage()


def test_preset_with_a_missing_texture_names_it(tmp_path):
    save_preset(cup_material(), tmp_path / "cup.toml")
    (tmp_path / "cup.lime.mask.texture.exr").unlink()
    with pytest.raises(
        InputError, match=r"cup\.toml: material\.lime\.mask\.texture: .* not a file"
    ):
        load_preset(tmp_path / "cup.toml")


def test_preset_schema_is_written():
    assert PRESET_SCHEMA == 1


def test_a_stack_of_one_layer_checks_its_bump_and_warns_it_is_ignored(caplog):
    """The bump is the masks' height field; a stack left with one layer has no mask, so its
    bump does nothing. It was dropped without a word (and without its range checked)."""

    def stack(bump, second=False):
        return {
            "type": "layered",
            "bump": bump,
            "layers": [
                {"name": "clay", "type": "oren_nayar"},
                {"name": "glaze", "type": "glaze", "enabled": second, "mask": {"threshold": 0.5}},
            ],
        }

    with caplog.at_level("WARNING"):
        one = build_material(stack(0.0003), "cup.toml")
    assert "bump" not in one.params
    (record,) = caplog.records
    assert "cup.toml: material.bump = 0.0003 is ignored" in record.getMessage()
    assert "only 'clay' is enabled" in record.getMessage()
    caplog.clear()
    with caplog.at_level("WARNING"):
        build_material(stack(0.0), "cup.toml")  # off: nothing to say
        two = build_material(stack(0.0003, second=True), "cup.toml")
    assert not caplog.records, caplog.text
    assert two.params["bump"].value == pytest.approx(0.0003)
    for bad in (-1.0, 0.5, "thick"):  # outside [0, 0.01], or not a number: refused by name
        with pytest.raises(ConfigError, match=r"cup\.toml: material"):
            build_material(stack(bad), "cup.toml")


@pytest.mark.parametrize("name", ["layers", "type", "id", "glaze_mask", "bump"])
def test_a_layer_named_as_a_key_of_the_stack_is_refused(name):
    """A layer named `layers`, `type` or `id`, or `glaze_mask` beside `glaze`, overwrote a key
    of the stack's dict: its render and every export failed with an internal error."""
    table = {
        "type": "layered",
        "layers": [
            {"name": "clay", "type": "oren_nayar"},
            {"name": "glaze", "type": "glaze", "mask": {"threshold": 0.5}},
            {"name": name, "type": "oren_nayar", "mask": {"threshold": 0.5}},
        ],
    }
    with pytest.raises(ConfigError, match=rf"cup\.toml: material\.layers\[2\]\.name: '{name}'"):
        build_material(table, "cup.toml")
