"""Property-based fuzzing (hypothesis) of the loaders of render and fit configs, capture manifests
and presets: TOML documents built from the real schema's keys with random values and types, and
random bytes. Whatever the input, the outcome is a loaded object or a one-line `InputError` naming
the file, never another exception. 50 examples per loader by default, 1000 with `-m slow`."""

from __future__ import annotations

import atexit
import copy
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import tomli_w
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.configuration import set_hypothesis_home_dir

from captures import InputError, open_capture
from captures.images import write_image
from fit.config import load_fit_config, load_render_config
from fit.material import load_preset

ROOT = Path(__file__).resolve().parents[1]
# hypothesis's caches (unicode data, constants) go to a temporary folder, not .hypothesis/ here
_HOME = tempfile.mkdtemp(prefix="layerfit-hypothesis-")
set_hypothesis_home_dir(_HOME)
atexit.register(shutil.rmtree, _HOME, True)

#: Keys of the real schemas (configs, scenes, cameras, lights, materials, fits, manifests,
#: presets) and values that mean something to them: mutations draw from these.
KEYS = [
    *("scene", "material", "render", "capture", "fit", "views", "truth", "schema"),
    *("provenance", "geometry", "cameras", "lights", "environment", "integrator", "max_depth"),
    *("type", "origin", "target", "up", "fov_x_deg", "width", "height", "aperture_radius"),
    *("focus_distance", "ortho_width", "center", "size", "power", "radiance", "temperature"),
    *("color", "u_axis", "v_axis", "emit_direction", "position", "direction", "file", "scale"),
    *("pigment", "roughness", "ior", "sigma", "coupling", "fresnel", "reflectance", "layers"),
    *("bump", "mask", "name", "enabled", "threshold", "softness", "texture", "free", "seed"),
    *("gains", "loss", "loss_scale", "uncertainty_spp", "downscale", "holdout", "phases"),
    *("solver", "steps", "spp", "lr", "average", "jacobian_spp", "image", "exposure_ev"),
    *("gain", "encoding", "white_balance", "dilate", "glaze.roughness", "glaze.pigment"),
]
WORDS = [
    *("sphere", "cup", "obj", "m.obj", "none.obj", "../m.obj", "glaze", "layered", "oren_nayar"),
    *("perspective", "orthographic", "rectangle", "point", "directional", "constant", "envmap"),
    *("sky.exr", "tex.png", "view_00.exr", "../view_00.exr", "linear", "srgb", "raw", "camera"),
    *("adam", "lm", "bfgs", "l2", "huber", "schlick", "exact", "paper", "glaze.roughness", ""),
    *("prb", "path", "clay", "cap", "/", "\\", "nan"),
]
SCALARS = st.one_of(
    st.integers(-(2**63), 2**63 - 1),
    st.sampled_from([0, 1, -1, 2, 3, 8, 16, 10**9]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-300, 1e300, 0.5, 1.5, 65504.0]),
    st.booleans(),
    st.text(max_size=12),
    st.sampled_from(WORDS),
)
VALUES = st.recursive(
    SCALARS,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4), st.dictionaries(st.sampled_from(KEYS), inner, max_size=3)
    ),
    max_leaves=8,
)


def _slots(doc) -> list[tuple[object, object]]:
    """Every (container, key or index) of a nested document."""
    out = []
    items = doc.items() if isinstance(doc, dict) else enumerate(doc)
    for key, value in items:
        out.append((doc, key))
        if isinstance(value, dict | list):
            out += _slots(value)
    return out


@st.composite
def mutated(draw, base: dict) -> dict:
    """`base` with 1-4 random edits: a value replaced (any type), a key or item deleted, or a
    key of the schema added with a random value."""
    doc = copy.deepcopy(base)
    for _ in range(draw(st.integers(1, 4))):
        slots = _slots(doc)
        if not slots:
            break
        container, key = draw(st.sampled_from(slots))
        action = draw(st.sampled_from(["set", "set", "delete", "add"]))
        if action == "set":
            container[key] = draw(VALUES)
        elif action == "delete":
            del container[key]
        else:
            target = container[key] if isinstance(container[key], dict) else container
            if isinstance(target, dict):
                target[draw(st.sampled_from(KEYS))] = draw(VALUES)
    return doc


def documents(base: dict):
    """TOML text: `base` mutated (mostly), or random text or bytes."""
    edited = mutated(base).map(_dump)
    return st.one_of(edited, edited, edited, edited, st.binary(max_size=64), st.text(max_size=64))


def _dump(doc: dict) -> str | None:
    try:
        return tomli_w.dumps(doc)
    except (TypeError, ValueError):  # a shape TOML cannot hold
        return None


def check(load: Callable[[Path], object], path: Path, text: str | bytes) -> None:
    """Write `text` to `path` and load it: an object, or a one-line `InputError` naming a file."""
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    try:
        load(path)
    except InputError as err:
        message = str(err)
        assert message and "\n" not in message, message
        assert path.name in message or path.parent.name in message, message


def fuzz(load, path: Path, base: dict, examples: int) -> None:
    """Run `examples` documents derived from `base` through `load`."""

    @settings(
        max_examples=examples,
        database=None,  # no .hypothesis folder in the repository
        deadline=None,
        # reproducible in the default run and in CI (a gate, not a search); elsewhere it explores
        derandomize=examples < 100 or os.environ.get("CI", "").lower() not in ("", "0", "false"),
        suppress_health_check=list(HealthCheck),
    )
    @given(documents(base))
    def run(text):
        assume(text is not None)
        check(load, path, text)

    run()


EXAMPLES = [50, pytest.param(1000, marks=pytest.mark.slow)]


@pytest.fixture(scope="module")
def project(tmp_path_factory) -> Path:
    """Files the documents may name: a capture with one image, a texture, an env map, a mesh."""
    root = tmp_path_factory.mktemp("fuzz")
    (root / "cap").mkdir()
    image = np.full((12, 16, 3), 0.2, np.float32)
    image[4:8, 6:10] = 0.6
    write_image(root / "cap" / "view_00.exr", image)
    write_image(root / "tex.png", np.full((4, 4, 3), 0.5, np.float32))
    write_image(root / "cap" / "sky.exr", np.full((4, 8, 3), 0.1, np.float32))
    obj = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n"
    (root / "m.obj").write_text(obj)
    shutil.copy(root / "m.obj", root / "cap" / "m.obj")
    return root


def render_doc() -> dict:
    import tomllib

    doc = tomllib.loads((ROOT / "configs" / "glazed-sphere.toml").read_text())
    doc["scene"]["cameras"][0].update(width=16, height=12)
    return doc


FIT_DOC = {
    "capture": "cap",
    "material": {"type": "glaze", "pigment": [0.3, 0.3, 0.3], "roughness": 0.1, "ior": 1.5},
    "fit": {
        "free": ["glaze.roughness", "glaze.pigment"],
        "seed": 0,
        "gains": True,
        "loss": "huber",
        "downscale": 1,
        "phases": [{"solver": "adam", "steps": 3, "spp": 4, "lr": 0.05}],
    },
}

LAYERED = {
    "type": "layered",
    "bump": 0.0002,
    "layers": [
        {"name": "clay", "type": "oren_nayar", "reflectance": [0.5, 0.5, 0.5], "sigma": 0.2},
        {
            "name": "glaze",
            "type": "glaze",
            "pigment": "tex.png",
            "roughness": 0.1,
            "mask": {"texture": "tex.png", "threshold": 0.3, "softness": 0.05},
        },
    ],
}


@pytest.mark.parametrize("examples", EXAMPLES)
def test_fuzz_render_config(project, examples):
    fuzz(load_render_config, project / "render.toml", render_doc(), examples)


@pytest.mark.parametrize("examples", EXAMPLES)
def test_fuzz_fit_config(project, examples):
    base = {**FIT_DOC, "material": LAYERED} if examples > 100 else FIT_DOC
    fuzz(load_fit_config, project / "fit.toml", base, examples)


@pytest.mark.parametrize("examples", EXAMPLES)
def test_fuzz_capture_manifest(project, examples):
    scene = render_doc()["scene"]
    camera = scene.pop("cameras")[0]
    scene["environment"] = {"type": "envmap", "file": "sky.exr"}
    base = {
        "capture": {"encoding": "linear", "downscale": 1, "dilate": 2},
        "scene": scene,
        "views": [{"image": "view_00.exr", "exposure_ev": 0.5, "camera": camera}],
        "truth": {"glaze.roughness": 0.0625, "glaze.pigment": [0.1, 0.2, 0.5]},
    }
    fuzz(open_capture, project / "cap" / "capture.toml", base, examples)


@pytest.mark.parametrize("examples", EXAMPLES)
def test_fuzz_preset(project, examples):
    base = {
        "schema": 1,
        "provenance": {"capture": "cap", "loss": 0.01, "std": {"glaze.roughness": 0.001}},
        "material": LAYERED,
    }
    fuzz(load_preset, project / "preset.toml", base, examples)


def test_fuzz_outcome_check_can_fail(project):
    """The property is not vacuous: a loader raising anything but `InputError` fails it."""

    def broken(path):
        raise KeyError("boom")

    with pytest.raises(KeyError):
        check(broken, project / "x.toml", "a = 1")
    with pytest.raises(AssertionError):  # an error naming no file
        check(lambda p: (_ for _ in ()).throw(InputError("bad")), project / "x.toml", "a = 1")
