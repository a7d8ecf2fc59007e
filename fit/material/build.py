"""A `[material]` table (TOML) -> a `Material`: the Mitsuba BSDF dict and the table of every
declared parameter and option of what was built. Only what the table requires is built.

```toml
[material]
type = "layered"              # or a single plugin: "glaze", "oren_nayar"
bump = 0.0004                 # metres; 0 or absent: no bump is built

[[material.layers]]           # bottom to top
name = "clay"
type = "oren_nayar"
reflectance = [0.62, 0.5, 0.4]   # linear RGB, or a texture file (8-bit: sRGB-decoded)
sigma = 0.35

[[material.layers]]
name = "glaze"
type = "glaze"
enabled = true                # false: the layer, its mask and its parameters are not built
roughness = 0.02
[material.layers.mask]        # every layer but the bottom one: texture x sigmoid((fbm - t) / s)
scale = 8
threshold = 0.3
softness = 0.03
texture = "textures/glaze.png"   # optional painted mask (linear)
```
A disabled layer, a zero noise amount or a zero bump leaves no plugin, parameter or texture behind;
a stack left with one layer is that layer. Plugins and their parameters and options are declared in
`materials.params` (`LAYER_PLUGINS`, `FBM`, `LAYERED`); everything here is derived from them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

from materials.params import FBM, LAYER_PLUGINS, LAYERED, MASK_TEXTURE, ParamSpec, PluginDecl

from ..errors import ConfigError
from .keys import key, parse_key

log = logging.getLogger(__name__)

#: Names a layer may not take: the stack's keys (its `layers` list, a layer's `<name>_mask`, the
#: plugin's `type` and `id`) and the design keys' own words. A layer named `layers` or `type`, or
#: `glaze_mask` beside `glaze`, overwrote a key of the stack: its render and exports failed.
RESERVED = ("bump", "mask", "lights", "environment", "gain", "layers", "type", "id")


@dataclass(frozen=True)
class Param:
    """One declared parameter of a built material.

    - `key`: its design key (`glaze.roughness`); `spec`: its declaration.
    - `value`: a float, an RGB list, or None when it is a texture file (`texture`).
    - `traverse`: its key in `mi.traverse` of the loaded material (`glaze.roughness`,
      `pigment.value`, `lime.mask.texture.data`).
    """

    key: str
    spec: ParamSpec
    value: float | list[float] | None
    traverse: str
    texture: Path | None = None


@dataclass(frozen=True)
class Material:
    """A built material: the Mitsuba dict and what it is made of.

    - `bsdf`: the Mitsuba BSDF dict (every declared parameter set explicitly).
    - `params`: every declared parameter of what was built, by key, bottom layer first.
    - `options`: every option of what was built (integers, choices), by key (`glaze.fresnel`,
      `lime.mask.scale`).
    - `layers`: the built layers bottom to top as (name, plugin type); one entry, named after
      its type, for a single plugin.
    """

    bsdf: dict
    params: dict[str, Param]
    options: dict[str, object]
    layers: tuple[tuple[str, str], ...]
    stacked: bool = field(default=False)

    def needs_uvs(self) -> list[str]:
        """What in this material is looked up in UV space (masks, textures, the glaze's noise,
        a parameter given as a texture file): the keys, or nothing (it renders on a mesh
        without texture coordinates)."""
        return [
            k
            for k, p in self.params.items()
            if ".mask." in k
            or k.endswith(("pigment_noise", "normal_noise", ".texture"))
            or p.texture is not None
        ]

    def values(self) -> dict:
        """Each parameter's value by key (texture files left out)."""
        return {k: p.value for k, p in self.params.items() if p.value is not None}

    def table(self, texture_name=lambda key, path: str(path)) -> dict:
        """The complete `[material]` table of what was built: every layer's every declared
        parameter and option (unbuilt optional ones as 0). `texture_name(key, path)` gives the
        text the texture file of parameter `key` is written as (default: the path; two keys may
        share one file)."""

        def plugin(owner: str, decl: PluginDecl, mask: bool = False) -> dict:
            out: dict = {}
            for name in decl.params:
                p = self.params.get(key(owner, name, mask))
                if p is None:  # an optional parameter that is off
                    out[name] = 0.0
                else:
                    out[name] = texture_name(p.key, p.texture) if p.value is None else p.value
            for name, option in decl.options.items():
                out[name] = self.options.get(key(owner, name, mask), option.default)
            return out

        (owner, kind), *_ = self.layers
        if not self.stacked and owner == kind:
            return {"type": kind, **plugin(owner, LAYER_PLUGINS[kind])}
        layers = []  # a stack (of one, when the others are disabled: its keys keep its name)
        for i, (name, kind) in enumerate(self.layers):
            layer = {"name": name, "type": kind, **plugin(name, LAYER_PLUGINS[kind])}
            if i > 0:
                mask = plugin(name, FBM, mask=True)
                texture = self.params.get(key(name, "texture", True))
                if texture is not None:
                    mask["texture"] = texture_name(texture.key, texture.texture)
                layer["mask"] = mask
            layers.append(layer)
        bump = self.params.get("bump")
        return {"type": "layered", "bump": bump.value if bump else 0.0, "layers": layers}

    def with_values(self, values: dict) -> Material:
        """This material with some parameters set to `values` (by key; keys that are not scalar
        or RGB parameters of this material, such as gains or texels, are left out)."""
        table = self.table()
        for text, value in values.items():
            param = self.params.get(text)
            if param is None or param.value is None:
                continue
            k = parse_key(text)
            if not self.stacked and k.owner == table.get("type"):
                where = table
            elif not k.owner:
                where = table
            else:
                layer = next(t for t in table["layers"] if t["name"] == k.owner)
                where = layer["mask"] if k.mask else layer
            where[k.name] = [float(x) for x in value] if isinstance(value, list) else float(value)
        built = build_material(table, "<fitted material>")
        assert built is not None
        return built

    def with_textures(self, files: dict[str, Path]) -> Material:
        """This material with the texture parameters named in `files` (by key) read from those
        files (a fit's fitted texels)."""
        unknown = sorted(set(files) - set(self.texture_files()))
        if unknown:
            raise KeyError(f"no texture parameter {', '.join(unknown)}")
        table = self.table(lambda key, path: str(Path(files.get(key, path)).resolve()))
        built = build_material(table, "<fitted material>")
        assert built is not None
        return built

    def texture_files(self) -> dict[str, Path]:
        """The texture files the material reads, by parameter key."""
        return {k: p.texture for k, p in self.params.items() if p.texture is not None}


class _Builder:
    """Collects the parameter table while building the dict (file: for errors and paths)."""

    def __init__(self, file: Path):
        self.file = Path(file)
        self.params: dict[str, Param] = {}
        self.options: dict[str, object] = {}

    def error(self, where: str, problem: str) -> ConfigError:
        return ConfigError(f"{self.file}: {where}: {problem}")

    def texture(
        self, value, where: str, raw: bool, spec: ParamSpec | None = None
    ) -> tuple[dict, Path]:
        """A bitmap texture of the file `value` names, its values within `spec`'s bounds."""
        if not isinstance(value, str):
            raise self.error(where, "must be a texture file name")
        path = (self.file.parent / value).resolve()
        if not path.is_file():
            raise self.error(
                where, f"{value!r} is not a file (paths are relative to the config); check the path"
            )
        from captures.images import image_problem

        problem = image_problem(path)
        if problem is not None:
            raise self.error(where, problem)
        if spec is not None:
            self.texel_range(spec, path, value, where)
        return {"type": "bitmap", "filename": str(path), "raw": raw}, path

    def texel_range(self, spec: ParamSpec, path: Path, value: str, where: str) -> None:
        """Refuse a texture whose texels leave the parameter's bounds (a float image can hold
        any value: a pigment of 3 or -1 rendered without a word; 8-bit files stay in [0, 1])."""
        from captures.images import read_image

        pixels = read_image(path)
        if pixels.shape[-1] in (2, 4):  # the alpha channel is not the parameter's
            pixels = pixels[..., :-1]
        low, high = float(pixels.min()), float(pixels.max())
        if low < spec.lower or high > spec.upper:
            raise self.error(
                where,
                f"{value!r} holds values from {low:.4g} to {high:.4g}, outside {spec.key}'s "
                f"bounds [{spec.lower}, {spec.upper}] ({spec.doc}); rescale the image",
            )

    def param(self, spec: ParamSpec, value, where: str, design: str, traverse: str):
        """A declared parameter's value as Mitsuba wants it, recorded in the table."""
        if spec.kind == "rgb":
            if isinstance(value, str):  # 8-bit files are sRGB-decoded
                out, path = self.texture(value, where, raw=False, spec=spec)
                self.params[design] = Param(design, spec, None, f"{traverse}.data", path)
                return out
            if isinstance(value, int | float) and not isinstance(value, bool):
                value = [value] * 3
            if not isinstance(value, list | tuple) or len(value) != 3:
                raise self.error(where, "must be 3 numbers (linear RGB) or a texture file")
            if any(isinstance(x, bool) or not isinstance(x, int | float) for x in value):
                raise self.error(where, f"must be 3 numbers (linear RGB), got {value!r}")
            self.check(spec, value, where)
            rgb = [float(x) for x in value]
            self.params[design] = Param(design, spec, rgb, f"{traverse}.value")
            return {"type": "rgb", "value": rgb}
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(where, f"must be a number, got {value!r}")
        self.check(spec, value, where)
        self.params[design] = Param(design, spec, float(value), traverse)
        return float(value)

    def check(self, spec: ParamSpec, value, where: str) -> None:
        items = value if isinstance(value, list | tuple) else [value]
        if any(isinstance(x, bool) or not isinstance(x, int | float) for x in items):
            raise self.error(where, f"must be a number, got {value!r}")
        try:
            spec.check(value, f"{self.file}: {where.rsplit('.', 1)[0]}")
        except ValueError as err:
            raise ConfigError(str(err)) from None

    def option(self, decl: PluginDecl, name: str, value, where: str, design: str):
        try:
            value = decl.options[name].check(value, f"{self.file}: {where.rsplit('.', 1)[0]}")
        except ValueError as err:
            raise ConfigError(str(err)) from None
        self.options[design] = value
        return value

    def plugin(
        self, decl: PluginDecl, table: dict, where: str, owner: str, prefix: str, mask=False
    ) -> dict:
        """One plugin's dict; `owner` (and `mask`) name its keys, `prefix` its traverse keys."""
        known = {*decl.params, *decl.options}
        unknown = sorted(set(table) - known)
        if unknown:
            raise self.error(
                f"{where}.{unknown[0]}",
                f"unknown key for {decl.name}; known: {', '.join(sorted(known))}",
            )
        on = {n for n in decl.params if not (n in decl.optional and table.get(n, 0.0) in (0, 0.0))}
        out: dict = {"type": decl.name}
        for name in decl.params:
            if name in on:
                spec = decl.params[name]
                value = table.get(name, spec.default)
                design = key(owner, name, mask)
                out[name] = self.param(spec, value, f"{where}.{name}", design, prefix + name)
            elif name in table:
                self.check(decl.params[name], table[name], f"{where}.{name}")
        for name, option in decl.options.items():
            value = table.get(name, option.default)
            design = key(owner, name, mask)
            if decl.applies(name, on):
                out[name] = self.option(decl, name, value, f"{where}.{name}", design)
            else:  # checked, not built (a noise's scale without the noise)
                self.option(decl, name, value, f"{where}.{name}", design)
                del self.options[design]
        return out

    def mask(self, table, where: str, layer: str) -> dict:
        if not isinstance(table, dict):
            raise self.error(f"[{where}]", "must be a table (scale, threshold, softness, ...)")
        table = dict(table)
        texture = table.pop("texture", None)
        out = self.plugin(FBM, table, where, layer, f"{layer}.mask.", mask=True)
        if texture is not None:
            out["texture"], path = self.texture(
                texture, f"{where}.texture", raw=True, spec=MASK_TEXTURE
            )
            design = key(layer, "texture", True)  # a painted mask is linear
            self.params[design] = Param(
                design, MASK_TEXTURE, None, f"{layer}.mask.texture.data", path
            )
        return out


def build_material(
    table: dict, file: Path | str = "<material>", where: str = "material"
) -> Material | None:
    """The `Material` of a `[material]` table, or None when every part of it is disabled."""
    b = _Builder(Path(file))
    if not isinstance(table, dict):
        raise b.error(f"[{where}]", "must be a table")
    table = dict(table)
    enabled = _enabled(b, table, where)
    kind = table.pop("type", None)
    choices = [*LAYER_PLUGINS, "layered"]
    if not isinstance(kind, str) or kind not in choices:
        raise b.error(f"{where}.type", f"got {kind!r}; choose one of {', '.join(choices)}")
    if not enabled:
        return None
    if kind != "layered":
        bsdf = b.plugin(LAYER_PLUGINS[kind], table, where, kind, "")
        return Material(bsdf, b.params, b.options, ((kind, kind),))

    layers = table.pop("layers", None)
    bump = table.pop("bump", 0.0)
    if table:
        unknown = ", ".join(table)
        raise b.error(f"[{where}]", f"has unknown key(s) {unknown}; known: type, bump, layers")
    if not isinstance(layers, list) or not layers:
        raise b.error(f"[{where}]", f"needs [[{where}.layers]] (bottom to top)")
    built: list[tuple[str, str, dict, dict | None]] = []
    seen: list[str] = []  # every layer's name, disabled ones too
    for i, entry in enumerate(layers):
        at = f"{where}.layers[{i}]"
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str):
            raise b.error(f"[[{where}.layers]] number {i}", "needs a name")
        layer = dict(entry)
        name, mask = layer.pop("name"), layer.pop("mask", None)
        if not name.isidentifier() or name in RESERVED or name.endswith("_mask"):
            raise b.error(
                f"{at}.name",
                f"{name!r} must be an identifier, not a reserved word ({', '.join(RESERVED)}) "
                "nor end in _mask (the stack's own keys)",
            )
        if name in seen:
            raise b.error(f"{at}.name", f"{name!r} is used twice")
        seen.append(name)
        if i == 0 and mask is not None:
            raise b.error(
                f"{where}.{name}.mask",
                "the bottom layer takes no mask (it shows wherever the layers above do not); "
                "remove the table, or put the layer above another",
            )
        if not _enabled(b, layer, f"{where}.{name}"):
            continue
        layer_kind = layer.pop("type", None)
        if not isinstance(layer_kind, str) or layer_kind not in LAYER_PLUGINS:
            choices = ", ".join(LAYER_PLUGINS)
            raise b.error(f"{where}.{name}.type", f"got {layer_kind!r}; choose one of {choices}")
        bsdf = b.plugin(LAYER_PLUGINS[layer_kind], layer, f"{where}.{name}", name, f"{name}.")
        if built and mask is None:
            raise b.error(f"layer {name!r}", f"needs a [{where}.layers.mask] table")
        if not built and mask is not None:  # the bottom, the layers below it disabled: its
            # mask is not built, but checked (a missing texture file passed without a word)
            _Builder(b.file).mask(mask, f"{where}.{name}.mask", name)
        mask_dict = b.mask(mask, f"{where}.{name}.mask", name) if built else None
        built.append((name, layer_kind, bsdf, mask_dict))
    if not built:
        return None
    if len(built) == 1:  # a stack of one is that layer, keyed by its name
        ((name, layer_kind, bsdf, _),) = built
        b.check(LAYERED.params["bump"], bump, f"{where}.bump")
        if bump != 0:
            log.warning(
                f"{b.file}: {where}.bump = {bump:g} is ignored: the bump comes from the masks of "
                f"the layers above the first, and only {name!r} is enabled"
            )
        params = {k: _retraverse(p, f"{name}.") for k, p in b.params.items()}
        return Material(bsdf, params, b.options, ((name, layer_kind),), stacked=False)
    out: dict = {"type": "layered", "layers": ",".join(name for name, *_ in built)}
    for name, _, bsdf, mask in built:
        out[name] = bsdf
        if mask is not None:
            out[f"{name}_mask"] = mask
    if bump != 0:
        out["bump"] = b.param(LAYERED.params["bump"], bump, f"{where}.bump", "bump", "bump")
    else:
        b.check(LAYERED.params["bump"], bump, f"{where}.bump")
    layer_kinds = tuple((name, kind) for name, kind, *_ in built)
    return Material(out, b.params, b.options, layer_kinds, stacked=True)


def _enabled(b: _Builder, table: dict, where: str) -> bool:
    enabled = table.pop("enabled", True)
    if not isinstance(enabled, bool):
        raise b.error(f"{where}.enabled", "must be true or false")
    return enabled


def _retraverse(p: Param, prefix: str) -> Param:
    """A parameter of a stack's only layer, now the whole material: traverse keys lose the
    layer's prefix (its design key keeps the layer's name)."""
    from dataclasses import replace

    return replace(p, traverse=p.traverse.removeprefix(prefix))


def material_dict(table: dict, file: Path | str = "<material>", where: str = "material"):
    """The Mitsuba BSDF dict of a `[material]` table, or None when it is disabled."""
    material = build_material(table, file, where)
    return None if material is None else material.bsdf


def check_uvs(scene, material: Material) -> None:
    """Refuse a mesh without texture coordinates under a material that needs them."""
    from captures.errors import listing
    from captures.scene import ObjFile

    geometry = scene.geometry
    if isinstance(geometry, ObjFile) and not geometry.uvs:
        needs = material.needs_uvs()
        if needs:
            shown = listing(needs)
            raise ConfigError(
                f"{geometry.path}: the OBJ has faces without texture coordinates, and the "
                f"material looks up {shown} in UV space; unwrap the mesh (e.g. Blender: UV > "
                "Smart UV Project) and export with UVs, or fit a material without masks, noise or "
                "textures"
            )
