"""A peer target (scene.json + linear EXR views) with a rough diffuse base, rendered by layerfit's
EON glaze in another peer target's scene: what a renderer with OpenPBR's diffuse lobe (Blender,
MaterialX) gives for `diffuse_roughness` > 0, which the shared Cycles targets do not have.

    .venv/bin/python scripts/eon_peer_target.py SOURCE_SCENE_JSON OUT_FOLDER \
        [--roughness 0.6] [--base-color 0.55 0.33 0.12] [--spp 1024]

The source's mesh, cameras, lights and glaze (specular roughness, ior) are kept; its views are
rendered again with `diffuse = "eon"`, `sigma` = the roughness, exact Fresnel, the paper's
coupling. README, "Other renderers' targets", fits the result with both diffuse lobes.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", type=Path, help="a peer target's scene.json")
    parser.add_argument("out", type=Path, help="the new target's folder (must not exist)")
    parser.add_argument("--roughness", type=float, default=0.6, help="diffuse_roughness")
    parser.add_argument("--base-color", type=float, nargs=3, default=(0.55, 0.33, 0.12))
    parser.add_argument("--spp", type=int, default=1024)
    args = parser.parse_args()
    if args.out.exists():
        parser.error(f"{args.out} exists; give a new folder")

    from fit.variant import select_variant

    select_variant()
    import materials

    materials.register()
    from captures import load_peer_scene
    from captures.images import write_image
    from fit.render import load_scene, render, scene_dict

    doc = json.loads(args.source.read_text())
    doc["material"]["diffuse_roughness"] = args.roughness
    doc["material"]["base_color"] = list(args.base_color)
    doc["generator"] = f"layerfit (EON glaze, scripts/eon_peer_target.py), {args.spp} spp"
    tmp = args.out.with_name(f".{args.out.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    shutil.copy(args.source.parent / doc["mesh"], tmp / doc["mesh"])
    (tmp / "scene.json").write_text(json.dumps(doc, indent=1))
    scene = load_peer_scene(tmp / "scene.json")
    material = doc["material"]
    bsdf = {
        "type": "glaze",
        "pigment": {"type": "rgb", "value": list(args.base_color)},
        "sigma": args.roughness,
        "roughness": material["specular_roughness"] ** 2,  # Cycles' r: alpha = r^2
        "ior": material["ior"],
        "coupling": "paper",
        "fresnel": "exact",
        "diffuse": "eon",
    }
    for view, path in enumerate(scene.meta["images"]):
        image = render(load_scene(scene_dict(scene, bsdf, view, args.spp)), args.spp, 100 + view)
        write_image(tmp / Path(path).name, image)
    tmp.rename(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
