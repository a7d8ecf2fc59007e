"""The native preset: a material as a TOML file, complete and lossless.

```toml
schema = 1                      # this module's PRESET_SCHEMA; newer files are refused
[provenance]                    # where the values come from (free-form but typed)
capture = "captures/samples/cup"
created = "2026-11-29T12:00:00+00:00"
loss = 0.0123
software = { layerfit = "0.1.0", mitsuba = "3.9.1", drjit = "1.5.0" }
std = { "glaze.roughness" = 0.0011 }   # per-parameter standard deviation, when known
[material]                      # every layer's every parameter and option, as in configs
type = "glaze"
...
```
Textures (painted or fitted masks, texture-valued colours) are files beside the preset, named
`<preset stem>.<key>.<ext>` and referenced by relative path. A config's `material = "x.toml"`
reads a preset wherever a `[material]` table is accepted.
"""

from __future__ import annotations

import datetime
import logging
import shutil
import tomllib
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

import numpy as np
import tomli_w

from captures.errors import listing
from captures.files import atomic_path, write_text
from captures.model import toml_kind

from ..errors import ConfigError
from .build import Material, build_material

log = logging.getLogger(__name__)

#: The preset format's version. Bump it when a preset's meaning changes, and upgrade older ones
#: in `_upgrade` (or refuse them there with the reason).
PRESET_SCHEMA = 1
_TOP_KEYS = ("schema", "provenance", "material")
_PROVENANCE_KEYS = ("capture", "config", "created", "loss", "software", "std", "note")


@dataclass(frozen=True)
class Preset:
    """A loaded preset: the built material and its provenance table."""

    material: Material
    provenance: dict = field(default_factory=dict)
    path: Path | None = None


def software_versions() -> dict:
    """The versions of what made a result (layerfit and the renderer stack)."""
    out = {}
    for name in ("layerfit", "mitsuba", "drjit", "jax", "optimistix"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return out


def provenance(capture=None, config=None, loss=None, std=None, note=None) -> dict:
    """A provenance table: now, the software versions, and what is given (None left out)."""
    out = {
        "capture": None if capture is None else str(capture),
        "config": None if config is None else str(config),
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "loss": None if loss is None else float(loss),
        "software": software_versions(),
        "std": std,
        "note": note,
    }
    return {k: v for k, v in out.items() if v is not None}


def save_preset(
    material: Material,
    path: str | Path,
    provenance: dict | None = None,
    textures: dict[str, np.ndarray] | None = None,
) -> Path:
    """Write `material` as a preset at `path`, its texture files beside it.

    `textures` replaces texture parameters by fitted texels (key -> (H, W, C) array, written as
    EXR). Every file appears whole or not at all; the TOML last, so a preset never names a
    texture that is not there yet.
    """
    from captures.images import write_image

    path = Path(path)
    if path.suffix != ".toml":
        raise ConfigError(f"{path}: a preset is a .toml file")
    if path.is_dir():
        raise ConfigError(f"{path}: is a folder; give the preset's file name")
    textures = textures or {}
    written: dict[str, str] = {}  # by key: two masks may share one file, fitted apart
    for key, source in material.texture_files().items():
        fitted = textures.get(key)
        suffix = ".exr" if fitted is not None else source.suffix.lower()
        target = path.with_name(f"{path.stem}.{key}{suffix}")
        if fitted is not None:
            write_image(target, np.asarray(fitted, np.float32))
        elif target.resolve() != source.resolve():
            with atomic_path(target) as tmp:
                shutil.copyfile(source, tmp)
        written[key] = target.name
    unknown = sorted(set(textures) - set(material.texture_files()))
    if unknown:
        raise ConfigError(f"{path}: no texture parameter {', '.join(unknown)} to write")
    doc = {
        "schema": PRESET_SCHEMA,
        "provenance": _clean(provenance or {}),
        "material": _clean(material.table(lambda key, path: written[key])),
    }
    return write_text(path, tomli_w.dumps(doc))


def _clean(value):
    """TOML-ready: tuples to lists, numpy scalars to Python, None dropped."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items() if v is not None}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _not_a_preset(doc: dict, schema) -> str:
    """Why a TOML document without an integer `schema` is not a preset: what it looks like."""
    kind = toml_kind(doc)
    if kind not in ("a preset", ""):
        return f"is {kind}, not a preset; give a preset (e.g. a run's preset.toml)"
    if schema is None:
        return "has no schema key: not a preset; a preset starts with schema = 1"
    return f"schema = {schema!r} is not a preset version; a preset starts with schema = 1"


def load_preset(path: str | Path) -> Preset:
    """A preset from its file; a `ConfigError` naming the file and key for anything wrong."""
    path = Path(path)
    doc = read_toml(path)
    schema = doc.get("schema")
    if isinstance(schema, bool) or not isinstance(schema, int):
        raise ConfigError(f"{path}: {_not_a_preset(doc, schema)}")
    doc = _upgrade(doc, path)
    unknown = sorted(set(doc) - set(_TOP_KEYS))
    if unknown:
        raise ConfigError(
            f"{path}: unknown key {unknown[0]} at the top level; known: {', '.join(_TOP_KEYS)}"
        )
    prov = doc.get("provenance", {})
    if not isinstance(prov, dict):
        raise ConfigError(f"{path}: [provenance] must be a table")
    bad = sorted(set(prov) - set(_PROVENANCE_KEYS))
    if bad:
        known = ", ".join(_PROVENANCE_KEYS)
        raise ConfigError(f"{path}: unknown key provenance.{bad[0]}; known: {known}")
    if "material" not in doc:
        raise ConfigError(f"{path}: missing [material]")
    material = build_material(doc["material"], path)
    if material is None:
        raise ConfigError(f"{path}: every layer of [material] is disabled")
    given, full, where = doc["material"], material.table(), "material"
    if "layers" in given and "layers" not in full:  # a stack of one built as its layer
        name = material.layers[0][0]
        layers = given["layers"] if isinstance(given["layers"], list) else []
        given = next((x for x in layers if isinstance(x, dict) and x.get("name") == name), {})
        where = f"material.{name}"
    missing = _missing(given, full, where)
    if missing:
        log.warning(
            f"{path}: {listing(missing, 4)} not given: their defaults taken (a preset lists "
            "every parameter and option: this one was edited, or written by an older layerfit)"
        )
    return Preset(material, prov, path)


def _missing(given, full, where: str) -> list[str]:
    """The dotted keys of the complete table `full` (`Material.table`) that `given` leaves out;
    a stack's layers matched by name (a disabled layer is not built, so not compared)."""
    if not isinstance(given, dict):
        return []
    out = []
    for name, value in full.items():
        if name not in given:
            out.append(f"{where}.{name}")
        elif name == "layers" and isinstance(given[name], list):
            layers = {g.get("name"): g for g in given[name] if isinstance(g, dict)}
            for layer in value:
                out += _missing(layers.get(layer["name"]), layer, f"{where}.{layer['name']}")
        elif isinstance(value, dict):
            out += _missing(given[name], value, f"{where}.{name}")
    return out


def _upgrade(doc: dict, path: Path) -> dict:
    """A preset of an older schema in today's form, or a refusal that says why."""
    schema = doc["schema"]
    if schema > PRESET_SCHEMA:
        raise ConfigError(
            f"{path}: schema = {schema} was written by a newer layerfit (this one reads up to "
            f"{PRESET_SCHEMA}); upgrade layerfit"
        )
    if schema < 1:
        raise ConfigError(f"{path}: schema = {schema} is not a preset version (1 is the first)")
    return doc


def read_toml(path: Path) -> dict:
    """A TOML document, or a one-line `ConfigError` naming the file."""
    try:
        return tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file; check the path") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a folder, not a TOML file; give the file") from None
    except UnicodeDecodeError as err:
        raise ConfigError(
            f"{path}: not UTF-8 text ({err.reason} at byte {err.start}); save it as UTF-8"
        ) from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not valid TOML ({err}); fix the syntax") from None
    except OSError as err:
        raise ConfigError(f"{path}: cannot read ({err.strerror}); check the path") from None


def load_material(value, file: Path, where: str = "material") -> Material:
    """A config's material: a `[material]` table, or the name of a preset file (relative to the
    config)."""
    if isinstance(value, str):
        preset = (Path(file).parent / value).resolve()
        if not preset.exists():
            raise ConfigError(
                f"{file}: {where} = {value!r}: no such preset file ({preset}); give the path of "
                "a preset, relative to the config, or a [material] table"
            )
        if not preset.is_file():
            raise ConfigError(
                f"{file}: {where} = {value!r} is a folder; give the path of a preset file "
                "(e.g. a run's preset.toml)"
            )
        return load_preset(preset).material
    material = build_material(value, file, where)
    if material is None:
        raise ConfigError(f"{file}: every layer of [{where}] is disabled: nothing to render")
    return material
