"""The strict config models: one-line errors naming the file, the dotted key and the fix."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import pydantic
import pytest
from pydantic import model_validator

from captures import CaptureError
from captures.model import (
    ExistingPath,
    FieldError,
    NonNegativeFloat,
    PositiveFloat,
    StrictModel,
    Vec3,
    by_shape,
    parse_model,
    tagged,
)


class Item(StrictModel):
    name: str
    """The item's name."""
    weight: PositiveFloat = 1.0
    """Its weight in kilograms."""


class Disc(StrictModel):
    type: Literal["disc"] = "disc"
    """A flat disc."""
    radius: PositiveFloat
    """Its radius."""


class Ring(StrictModel):
    type: Literal["ring"]
    """A ring."""
    inner: PositiveFloat
    """Inner radius."""
    outer: PositiveFloat
    """Outer radius."""

    @model_validator(mode="after")
    def _ordered(self):
        if self.inner >= self.outer:
            raise FieldError("outer", "must exceed inner; swap them")
        return self


class Box(StrictModel):
    label: Literal["a", "b"] = "a"
    """The box's label."""
    items: tuple[Item, ...] = ()
    """What it holds."""
    size: Vec3 = (1.0, 1.0, 1.0)
    """Its size in metres."""
    shape: tagged(Disc, Ring, default="disc") | None = None
    """Its footprint."""
    tint: by_shape(number=NonNegativeFloat, array=Vec3) = 1.0
    """A grey level or an RGB colour."""
    manual: ExistingPath | None = None
    """Its manual, relative to the config."""
    note: Item | str = ""
    """An item or a text."""


def problem(data, where="box") -> str:
    with pytest.raises(CaptureError) as err:
        parse_model(Box, data, Path("c.toml"), where)
    message = str(err.value)
    assert "\n" not in message and "pydantic" not in message
    return message


def test_valid_tables_parse_into_frozen_models(tmp_path):
    (tmp_path / "manual.txt").write_text("")
    data = {
        "items": [{"name": "x", "weight": 2}],
        "shape": {"radius": 1},
        "tint": [1, 0.5, 0],
        "manual": "manual.txt",
    }
    box = parse_model(Box, data, tmp_path / "c.toml")
    assert box.items[0].weight == 2.0 and isinstance(box.shape, Disc)
    assert box.tint == (1.0, 0.5, 0.0) and box.manual == (tmp_path / "manual.txt").resolve()
    with pytest.raises(pydantic.ValidationError):
        box.label = "b"
    assert Box.model_fields["items"].description == "What it holds."


def test_unknown_key_lists_the_known_ones():
    message = problem({"items": [{"name": "x", "wieght": 2}]})
    assert message == "c.toml: box.items[0].wieght: unknown key; known: name, weight"


def test_unknown_key_comes_before_other_errors():
    assert "box.items[0].colour: unknown key" in problem({"items": [{"weight": -1, "colour": 1}]})


def test_missing_key():
    assert problem({"items": [{"name": "x"}, {}]}) == "c.toml: box.items[1].name: missing; add it"


def test_wrong_type_in_a_nested_list():
    message = problem({"items": [{"name": "x"}, {"name": "y", "weight": "heavy"}]})
    assert message == "c.toml: box.items[1].weight: got 'heavy'; should be a valid number"


@pytest.mark.parametrize(
    "data, message",
    [
        ({"size": [1, 2]}, "c.toml: size: got [1, 2]; should have 3 items"),
        ({"size": [1, True, 1]}, "c.toml: size[1]: got True; should be a valid number"),
        ({"size": [1, float("inf"), 1]}, "size[1]: got inf; should be a finite number"),
        (
            {"items": [{"name": "x", "weight": 0}]},
            "items[0].weight: got 0; should be greater than 0",
        ),
        ({"label": "c"}, "c.toml: label: got 'c'; choose one of a, b"),
        ({"items": 3}, "c.toml: items: got 3; should be an array"),
        ({"items": [3]}, "c.toml: items[0]: got 3; should be a table"),
        ({"shape": {"type": "cube"}}, "shape.type: got 'cube'; choose one of disc, ring"),
        ({"shape": {"radius": -1}}, "c.toml: shape.radius: got -1; should be greater than 0"),
        ({"shape": {"type": "ring", "inner": 2, "outer": 1}}, "shape.outer: must exceed inner"),
        ({"tint": "red"}, "c.toml: tint: got 'red'; should be a number or an array"),
        ({"note": 5}, "c.toml: note: got 5; should be a table"),
        ({"note": {"name": "x", "weight": -1}}, "c.toml: note.weight: got -1; should be greater"),
        ({"manual": "none.txt"}, "c.toml: manual: 'none.txt' does not exist (relative to"),
    ],
)
def test_errors_name_the_dotted_key(data, message):
    assert message in problem(data, where="")


def test_a_table_that_is_not_a_table():
    assert problem([1, 2]) == "c.toml: box: got [1, 2]; should be a table"
