from __future__ import annotations

import json

from sim_world.schema import SCHEMA_PATH, render


def test_the_committed_world_schema_matches_the_structs() -> None:
    assert SCHEMA_PATH.read_text(encoding="utf-8") == render(), (
        "the world Structs changed: run `make schemas` and commit "
        "services/sim_world/world.schema.json"
    )
    schema = json.loads(render())
    assert "robots" in schema["$defs"]["WorldSpec"]["required"]
