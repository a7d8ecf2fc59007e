"""What the commands share: starting Mitsuba, a silent progress display for calls from Python,
stopping on Ctrl-C with a line saying what was kept, and reading a render config or a preset."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from pathlib import Path

from captures.errors import InputError

from ..errors import Stopped


def start(variant: str | None) -> None:
    """Select the Mitsuba variant and register the plugins (`fit.variant.VariantError` for an
    unknown one, `BackendError` where the backend cannot load). A Ctrl-C meanwhile waits until
    they are done (`interrupts.deferred`), and one a library swallowed earlier is honoured
    here."""
    from .. import interrupts
    from ..variant import select_variant

    with interrupts.deferred():
        select_variant(variant)
        import materials

        materials.register()
    if interrupts.asked():
        raise KeyboardInterrupt


class Quiet:
    """A progress display that shows nothing: the methods of `rich.progress.Progress` the
    commands call, for calls from Python (the command line passes rich's)."""

    def add_task(self, description: str, total: float | None = None, **fields) -> int:
        return 0

    def update(self, task: int, **fields) -> None:
        pass

    def advance(self, task: int, advance: float = 1) -> None:
        pass

    def stop(self) -> None:
        pass


@contextlib.contextmanager
def stopping(what: Callable[[], str]) -> Iterator[None]:
    """Ctrl-C (or SIGTERM) inside becomes `Stopped(what())`: what the command left."""
    try:
        yield
    except KeyboardInterrupt:
        raise Stopped(what()) from None


def check_capture_cameras(scene, path: Path) -> None:
    """Refuse cameras whose views a capture cannot hold (what its loader refuses: synth wrote
    them, and inspect and fit then refused the capture): under `MIN_SIDE` pixels a side, or not
    seeing the object."""
    from captures.capture import MIN_SIDE, check_cameras_see

    for i, camera in enumerate(scene.cameras):
        if min(camera.width, camera.height) < MIN_SIDE:
            raise InputError(
                f"{path}: scene.cameras[{i}] is {camera.width}x{camera.height}: a capture's views "
                f"need at least {MIN_SIDE} pixels a side; give a larger width and height"
            )
    check_cameras_see(scene, lambda i: f"{path}: scene.cameras[{i}]")


def scene_and_material(config: Path, scene: Path | None):
    """(scene, material, spp) of a render config or a preset, the scene replaced by `scene`'s."""
    from captures import CaptureError, parse_scene
    from captures.model import toml_kind

    from ..config import load_render_config
    from ..material import check_uvs, load_preset, read_toml

    doc = read_toml(config)
    kind = toml_kind(doc)
    if kind in ("a fit config", "a batch spec", "a capture manifest"):
        raise CaptureError(
            f"{config}: is {kind}; give a render config (a material and a [scene]) or a preset "
            "with --scene SCENE.toml"
        )
    if "schema" in doc:  # a preset: the material only
        if scene is None:
            raise CaptureError(f"{config}: is a preset (a material); give --scene SCENE.toml")
        material, spp = load_preset(config).material, 64
    else:
        cfg = load_render_config(config)
        material, spp = cfg.material, cfg.spp
        if scene is None:
            check_uvs(cfg.scene, material)
            return cfg.scene, material, spp
    try:
        table = read_toml(scene)
        if "scene" not in table:
            raise CaptureError(f"{scene}: no [scene] table; give a TOML file with one")
        if toml_kind(table) == "a capture manifest":  # its cameras are its views'
            raise CaptureError(
                f"{scene}: is a capture manifest (its cameras are in its [[views]]); give a "
                "TOML file with a [scene] and its [[scene.cameras]] (configs/glazed-sphere-"
                "views.toml is one)"
            )
        the_scene = parse_scene(table["scene"], scene)
        check_uvs(the_scene, material)
        return the_scene, material, spp
    except InputError as err:  # name the option the file came from
        raise CaptureError(f"--scene {err}") from None


def render_inputs(config: Path, scene_file: Path | None, scene, material) -> list[Path]:
    """Every file a render reads: the config, the scene file, textures, mesh, environment."""
    from captures.scene import EnvMap, ObjFile

    files = [config, *material.texture_files().values()]
    if scene_file is not None:
        files.append(scene_file)
    if isinstance(scene.geometry, ObjFile):
        files.append(scene.geometry.path)
    if isinstance(scene.environment, EnvMap):
        files.append(scene.environment.path)
    return files
