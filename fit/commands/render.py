"""`layerfit render`: a render config's scene with its material (or a preset's material in
another scene), a linear EXR and the image asked for per view."""

from __future__ import annotations

from pathlib import Path

from captures.errors import InputError

from .common import Quiet, render_inputs, scene_and_material, start, stopping

#: Image types `render --out` writes.
IMAGE_SUFFIXES = (".png", ".exr", ".tif", ".tiff", ".jpg", ".jpeg")


def render(
    config: Path,
    scene: Path | None = None,
    out: Path = Path("out/render.png"),
    spp: int | None = None,
    seed: int = 0,
    force: bool = False,
    variant: str | None = None,
    progress=None,
    wrote=lambda path: None,
) -> list[Path]:
    """Render `config` (a render config, or a preset with `scene`, a TOML file holding a
    `[scene]`) into `out` (`out_NN` per view when there are several): a linear EXR beside each
    image. Existing images are replaced only with `force`. `progress`: a
    `rich.progress.Progress` (default: none shown); `wrote(path)` as each file is written.
    Returns the files written."""
    from captures.files import check_output

    progress = progress or Quiet()
    the_scene, material, config_spp = scene_and_material(config, scene)
    views = len(the_scene.cameras)
    paths = []
    if out.is_dir():
        raise InputError(f"--out {out}: is a folder; give an image file name (e.g. a.png)")
    base = out.name[: -len(out.suffix)] if out.suffix else out.name  # only the last suffix
    for view in range(views):
        name = base if views == 1 else f"{base}_{view:02d}"
        # the linear EXR, and the image asked for (b.EXR is that EXR: written once)
        suffixes = (out.suffix,) if out.suffix.lower() == ".exr" else (".exr", out.suffix)
        paths.append(list(dict.fromkeys(out.with_name(name + s) for s in suffixes)))
    inputs = render_inputs(config, scene, the_scene, material)
    for path in (p for files in paths for p in files):
        check_output(path, "--out", force=force, inputs=inputs, suffixes=IMAGE_SUFFIXES)
    start(variant)

    from captures.images import write_image

    from ..render import load_scene, scene_dict
    from ..render import render as render_image

    spp = spp or config_spp
    written: list[Path] = []
    n_files = sum(map(len, paths))
    with stopping(lambda: f"wrote {len(written)} of {n_files} images"):
        for view in range(views):
            task = progress.add_task(f"view {view}", total=spp)
            loaded = load_scene(scene_dict(the_scene, material.bsdf, view, spp))
            update = lambda n, t=task: progress.update(t, completed=n)  # noqa: E731
            image = render_image(loaded, spp, seed, update)
            for path in paths[view]:
                write_image(path, image)
                written.append(path)
                wrote(path)
    return written
