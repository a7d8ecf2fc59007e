"""Strict config models (pydantic v2) whose errors name the file, the dotted key and the fix.

```python
class Phase(StrictModel):
    steps: PositiveInt
    \"\"\"Iterations of this phase.\"\"\"

phase = parse_model(Phase, {"steps": 0}, "fit.toml", "fit.phases[1]")
# CaptureError: fit.toml: fit.phases[1].steps: got 0; should be greater than or equal to 1
```

Numbers are strict (no booleans or strings; an int is a valid float) and finite. Paths in a model
resolve against the folder of the file given to `parse_model` (its validation context).
"""

from __future__ import annotations

from pathlib import Path
from types import UnionType
from typing import Annotated, Any, TypeVar, Union, get_args, get_origin

import pydantic
from pydantic import (
    AfterValidator,
    ConfigDict,
    Discriminator,
    Field,
    Strict,
    Tag,
    ValidationError,
    ValidationInfo,
)

from .errors import CaptureError

__all__ = [
    "ExistingPath",
    "FieldError",
    "FiniteFloat",
    "NonNegativeFloat",
    "NonNegativeInt",
    "NonNegativeVec3",
    "PositiveFloat",
    "PositiveInt",
    "PositiveVec3",
    "StrictModel",
    "Vec3",
    "by_shape",
    "config_folder",
    "parse_model",
    "tagged",
]

M = TypeVar("M", bound=pydantic.BaseModel)


class StrictModel(pydantic.BaseModel):
    """A config table: unknown keys are errors, instances are immutable, and each field's
    docstring (the line below it) is its description."""

    model_config = ConfigDict(
        extra="forbid", frozen=True, use_attribute_docstrings=True, strict=False
    )


class FieldError(ValueError):
    """Raise in a model validator to blame one key of the table: `FieldError("ortho_width",
    "missing; add it")` reports `<table>.ortho_width: missing; add it`."""

    def __init__(self, key: str, message: str):
        super().__init__(message)
        self.key = key


# Types --------------------------------------------------------------------------------------------

#: The largest magnitude of a number in a scene, capture or config: 1e12 (metres, watts, radiance
#: or a factor) is past anything photographed, and past it the products of geometry (a norm, a
#: cross product) overflow, or Mitsuba's float32 holds infinities.
LARGEST = 1e12
FiniteFloat = Annotated[float, Strict(), Field(allow_inf_nan=False, ge=-LARGEST, le=LARGEST)]
PositiveFloat = Annotated[FiniteFloat, Field(gt=0)]
NonNegativeFloat = Annotated[FiniteFloat, Field(ge=0)]
PositiveInt = Annotated[int, Strict(), Field(ge=1)]
NonNegativeInt = Annotated[int, Strict(), Field(ge=0)]
Vec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]
PositiveVec3 = tuple[PositiveFloat, PositiveFloat, PositiveFloat]
NonNegativeVec3 = tuple[NonNegativeFloat, NonNegativeFloat, NonNegativeFloat]


def config_folder(info: ValidationInfo) -> Path:
    """In a validator: the folder of the file given to `parse_model` (else the working folder)."""
    file = (info.context or {}).get("file")
    return Path(file).parent if file else Path.cwd()


def _existing(path: Path, info: ValidationInfo) -> Path:
    folder = config_folder(info)
    resolved = (folder / path).resolve()
    if not resolved.exists():
        raise ValueError(f"'{path}' does not exist (relative to {folder}); check the path")
    return resolved


ExistingPath = Annotated[Path, AfterValidator(_existing)]
"""A file or folder that exists; a relative path resolves against the config file's folder."""


def tagged(*models: type[pydantic.BaseModel], key: str = "type", default: str | None = None):
    """A union of tables told apart by `key` (each model declares it as a `Literal`); tables
    without `key` are `default`'s."""
    tags = [get_args(m.model_fields[key].annotation)[0] for m in models]

    def tag(value):
        return value.get(key, default) if isinstance(value, dict) else getattr(value, key, None)

    members = tuple(Annotated[m, Tag(t)] for m, t in zip(models, tags, strict=True))
    return Annotated[
        Union[members],  # noqa: UP007 (a tuple of members)
        Discriminator(
            tag,
            custom_error_type="tag",
            custom_error_message=f"{key} should be one of {', '.join(tags)}",  # read back below
        ),
    ]


_SHAPES = {
    "number": "a number",
    "text": "a string",
    "boolean": "true or false",
    "array": "an array",
    "table": "a table",
}


def _shape(value) -> str:
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, int | float):
        return "number"
    if isinstance(value, str):
        return "text"
    if isinstance(value, list | tuple):
        return "array"
    return "table" if isinstance(value, dict | pydantic.BaseModel) else "other"


def by_shape(**types):
    """A value of one of several TOML shapes (number, text, boolean, array, table), each validated
    as its own type: `by_shape(number=NonNegativeFloat, array=NonNegativeVec3)`."""
    members = tuple(Annotated[t, Tag(shape)] for shape, t in types.items())
    expected = " or ".join(_SHAPES[shape] for shape in types)
    return Annotated[
        Union[members],  # noqa: UP007 (a tuple of members)
        Discriminator(
            _shape, custom_error_type="shape", custom_error_message=f"should be {expected}"
        ),
    ]


# Errors -------------------------------------------------------------------------------------------


def _unwrap(tp):
    """(the type under Annotated and Optional, {tag: member} when it is a tagged union)."""
    while True:
        if get_origin(tp) is Annotated:
            tp = get_args(tp)[0]
            continue
        args = [a for a in get_args(tp) if a is not type(None)]
        if get_origin(tp) in (Union, UnionType) and len(args) == 1:
            tp = args[0]
            continue
        break
    tags = {}
    if get_origin(tp) in (Union, UnionType):
        for member in get_args(tp):
            for meta in getattr(member, "__metadata__", ()):
                if isinstance(meta, Tag):
                    tags[meta.tag] = member
    return tp, tags


def _walk(model: type, loc: tuple) -> tuple[list[str], type, Any]:
    """The dotted parts of `loc` (union tags dropped), the model holding its last key, and the
    type at its end."""
    parts, owner, tp = [], model, model
    for part in loc:
        tp, tags = _unwrap(tp)
        if part in tags:
            tp = tags[part]
        elif isinstance(part, str) and get_origin(tp) in (Union, UnionType):  # a member's label
            tp = next((m for m in get_args(tp) if getattr(m, "__name__", None) == part), None)
        elif isinstance(part, int):
            parts.append(f"[{part}]")
            args = [a for a in get_args(tp) if a is not Ellipsis]
            fixed = get_origin(tp) is tuple and len(args) > 1
            tp = args[part] if fixed and part < len(args) else (args or [None])[0]
        elif isinstance(tp, type) and issubclass(tp, pydantic.BaseModel):
            parts.append(part)
            owner, field = tp, tp.model_fields.get(part)
            tp = field.annotation if field else None
        else:
            parts.append(str(part))
            tp = get_args(tp)[-1] if get_origin(tp) is dict else None
    return parts, owner, tp


def _join(where: str, parts: list[str]) -> str:
    out = where
    for part in parts:
        out += part if part.startswith("[") or not out else f".{part}"
    return out


def _show(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _describe(model: type, error: dict, where: str) -> tuple[str, str]:
    """(dotted location, "problem; fix") of one pydantic error."""
    kind, value, ctx = error["type"], error["input"], error.get("ctx") or {}
    parts, owner, _ = _walk(model, error["loc"])
    if kind == "extra_forbidden":
        return _join(where, parts), f"unknown key; known: {', '.join(owner.model_fields)}"
    if kind == "missing" and parts and parts[-1].startswith("["):  # a short fixed-length array
        parent, _, tp = _walk(model, error["loc"][:-1])
        n = len(get_args(_unwrap(tp)[0]))
        return _join(where, parent), f"got {_show(value)}; should have {n} items"
    if kind == "missing":
        return _join(where, parts), "missing; add it"
    if kind == "tag":
        key, _, choices = error["msg"].partition(" should be one of ")
        if not isinstance(value, dict):
            return _join(where, parts), f"got {_show(value)}; should be a table"
        got = f"got {_show(value[key])}" if key in value else "missing"
        return _join(where, [*parts, key]), f"{got}; choose one of {choices}"
    if kind in ("value_error", "assertion_error"):
        cause = ctx.get("error")
        if isinstance(cause, FieldError):
            parts = [*parts, cause.key]
        return _join(where, parts), str(cause) if cause is not None else error["msg"]
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        return _join(where, parts), f"got {_show(value)}; should be a table"
    if kind == "literal_error":
        choices = ctx["expected"].replace("'", "").replace(" or ", ", ")
        return _join(where, parts), f"got {_show(value)}; choose one of {choices}"
    msg = error["msg"].replace("Input should", "should").replace(" after validation", "")
    msg = msg.replace("a valid tuple", "an array").replace("a valid list", "an array")
    if kind == "path_type":  # "Input is not a valid path for <class 'pathlib.Path'>"
        msg = "should be a file name (a string)"
    for prefix in ("Tuple ", "List ", "Dictionary "):
        msg = msg.removeprefix(prefix)
    return _join(where, parts), f"got {_show(value)}; {msg}"


def parse_model(model: type[M], data: Any, file: Path | str, where: str = "") -> M:
    """`data` (a table from TOML) validated as `model`, or a one-line `CaptureError`
    `"{file}: {where}.{key}: {problem}; {fix}"` of its first error (unknown keys first: a misspelt
    key is the likelier mistake). Relative paths resolve against `file`'s folder."""
    try:
        return model.model_validate(data, context={"file": Path(file)})
    except ValidationError as err:
        errors = err.errors(include_url=False)
        first = next((e for e in errors if e["type"] == "extra_forbidden"), errors[0])
        location, text = _describe(model, first, where)
        raise CaptureError(
            f"{file}: {location}: {text}" if location else f"{file}: {text}"
        ) from None


def toml_kind(doc: dict) -> str:
    """What kind of layerfit file a TOML document is, from its top-level keys ("a fit config",
    "a batch spec", "a preset", "a capture manifest", "a render config"; "" when none), for the
    message when one kind is given where another belongs."""
    if "fit" in doc or isinstance(doc.get("capture"), str):
        return "a fit config"
    if "configs" in doc:
        return "a batch spec"
    if "schema" in doc:
        return "a preset"
    if "views" in doc or "truth" in doc:
        return "a capture manifest"
    if "material" in doc or "render" in doc:
        return "a render config"
    return ""


def expect_kind(doc: dict, path, wanted: str, fix: str, error: type[Exception]) -> None:
    """Raise `error` ("PATH: is a fit config, not WANTED; FIX") when `doc` is plainly another
    kind of layerfit file than `wanted` (see `toml_kind`)."""
    kind = toml_kind(doc)
    if kind not in (wanted, ""):
        raise error(f"{path}: is {kind}, not {wanted}; {fix}")
