from __future__ import annotations

import json

import pytest
from sim_world.schema import SCHEMA_PATH, render


def test_the_committed_world_schema_matches_the_structs() -> None:
    assert SCHEMA_PATH.read_text(encoding="utf-8") == render(), (
        "the world Structs changed: run `make schemas` and commit "
        "services/sim_world/world.schema.json"
    )
    schema = json.loads(render())
    assert "robots" in schema["$defs"]["WorldSpec"]["required"]


def test_the_schema_is_strict_json() -> None:
    """No ``Infinity`` or ``NaN`` (Python's json writes them; other readers refuse them):
    an occlusion's open end is ``t_end: null``, not an infinite default."""

    def refuse(name: str) -> None:
        pytest.fail(f"the schema holds {name}, which is not JSON")

    schema = json.loads(SCHEMA_PATH.read_text(encoding="utf-8"), parse_constant=refuse)
    t_end = schema["$defs"]["Occlusion"]["properties"]["t_end"]
    assert t_end["default"] is None
