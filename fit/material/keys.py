"""The one grammar of parameter keys, used by configs, free lists, truths, presets and exports.

```
glaze.roughness        <layer>.<param>         (a single plugin: <type>.<param>)
lime.mask.threshold    <layer>.mask.<param>    (the layer's mask: threshold, softness, texture)
bump                   <param> of the stack itself
lights.scale           an emitter group's scale (lights, environment)
gain.view_01           a view's RGB gain (fit results only)
```
"""

from __future__ import annotations

from dataclasses import dataclass

#: Scene-side owners of fittable values (their scales); not layers of the material.
EMITTER_OWNERS = ("lights", "environment")


@dataclass(frozen=True)
class Key:
    """A parsed key: `owner` is the layer (or plugin type, or emitter group; "" for the stack
    itself), `mask` whether it names the layer's mask, `name` the parameter or option."""

    owner: str
    name: str
    mask: bool = False

    def __str__(self) -> str:
        parts = [self.owner] if self.owner else []
        return ".".join([*parts, *(["mask"] if self.mask else []), self.name])

    @property
    def emitter(self) -> bool:
        return self.owner in EMITTER_OWNERS


def parse_key(text: str) -> Key:
    """A `Key` from its text, or a `KeyError` saying what a key looks like."""
    parts = text.split(".") if isinstance(text, str) else []
    if parts and all(p.isidentifier() for p in parts):
        if len(parts) == 1:
            return Key("", parts[0])
        if len(parts) == 2 and parts[1] != "mask":
            return Key(parts[0], parts[1])
        if len(parts) == 3 and parts[1] == "mask":
            return Key(parts[0], parts[2], mask=True)
    raise KeyError(
        f"{text!r} is not a parameter key; keys look like glaze.roughness, lime.mask.threshold, "
        "bump or lights.scale"
    )


def key(owner: str, name: str, mask: bool = False) -> str:
    """The text of a key."""
    return str(Key(owner, name, mask))
