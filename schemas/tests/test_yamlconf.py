"""YAML -> Struct with positions: msgspec's errors land on the right line, mapping entries
are named, duplicate keys are refused."""

from __future__ import annotations

from typing import Literal

import msgspec
import pytest
from rap_schemas.yamlconf import (
    YamlError,
    load_yaml,
    parse_location,
    parse_yaml,
    render_location,
)


class Leaf(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    size: int
    colour: Literal["red", "green"] = "red"


class Tree(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    groups: dict[str, dict[str, Leaf]] = {}
    items: list[Leaf] = []


class MyError(YamlError):
    pass


NESTED = """\
groups:
  a:
    x: {size: 1}
    y: {size: 2}
  b:
    x: {size: 3}
    y: {size: three}
"""


def test_an_entry_msgspec_does_not_name_is_found_and_named() -> None:
    with pytest.raises(YamlError) as exc:
        load_yaml(NESTED, Tree, "t.yaml")
    assert str(exc.value) == (
        "t.yaml:7:15: Expected `int`, got `str` - at `$.groups.b.y.size` (found 'three')"
    )
    assert (exc.value.line, exc.value.column) == (7, 15)


def test_strict_false_coerces_strings_like_msgspec_does() -> None:
    tree = load_yaml(NESTED.replace("three", "'4'"), Tree, strict=False)
    assert tree.groups["b"]["y"] == Leaf(size=4)


def test_literal_values_and_unknown_fields_come_with_the_fix() -> None:
    with pytest.raises(YamlError, match=r"^t.yaml:2:23: Invalid enum value 'blue'.*green, red"):
        load_yaml("items:\n  - {size: 1, colour: blue}\n", Tree, "t.yaml")
    with pytest.raises(YamlError, match=r"^t.yaml:3:5: .*`sise`.*did you mean `size`"):
        load_yaml("items:\n  - size: 1\n    sise: 2\n", Tree, "t.yaml")


def test_a_bad_mapping_key_is_pointed_at() -> None:
    with pytest.raises(YamlError, match=r"^t.yaml:3:3: Expected `str`, got `int` - at key 1"):
        load_yaml("groups:\n  a: {}\n  1: {}\n", Tree, "t.yaml")


def test_duplicate_keys_are_refused_at_any_depth_but_merges_are_fine() -> None:
    with pytest.raises(YamlError, match=r"^t.yaml:4:5: key 'size' appears twice .*line 3"):
        parse_yaml("items:\n  - colour: red\n    size: 1\n    size: 2\n", "t.yaml")
    text = "base: &b {size: 1}\nitems:\n  - <<: *b\n    colour: green\n"
    doc = parse_yaml(text, "t.yaml")
    assert doc.data["items"] == [{"size": 1, "colour": "green"}]
    assert doc.where(("items", 0, "size")) == "t.yaml:1:17"  # where the merged value is


def test_the_callers_error_class_is_raised() -> None:
    with pytest.raises(MyError, match=r"^t\.yaml: the tree file is empty"):
        parse_yaml("", "t.yaml", what="tree file", error=MyError)
    with pytest.raises(MyError, match=r"^t\.yaml:1:9: Expected `object`"):
        load_yaml("groups: [1]\n", Tree, "t.yaml", error=MyError)
    doc = parse_yaml("items: []\n", "t.yaml", error=MyError)
    err = doc.error(("items",), "no items")
    assert isinstance(err, MyError)
    assert str(err) == "t.yaml:1:8: no items"


def test_unsafe_tags_are_not_valid_yaml() -> None:
    with pytest.raises(YamlError, match="not valid YAML"):
        parse_yaml("a: !!python/object:os.system {}\n", "t.yaml")


@pytest.mark.parametrize(
    ("loc", "text"),
    [((), "$"), (("a", 0, "b"), "$.a[0].b"), (("a.b", 2), "$['a.b'][2]")],
)
def test_locations_render(loc: tuple[object, ...], text: str) -> None:
    assert render_location(loc) == text


def test_msgspec_paths_parse() -> None:
    assert parse_location("$.robots[0].name") == ["robots", 0, "name"]
    assert parse_location("$.a[...].b") == ["a"]
    assert parse_location("$") == []
