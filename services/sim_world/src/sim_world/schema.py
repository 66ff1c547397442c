"""The JSON Schema of world files: ``python -m sim_world.schema [PATH]`` (``make schemas``)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import msgspec

from .world import WorldSpec

__all__ = ["SCHEMA_PATH", "render"]

SCHEMA_PATH = Path(__file__).resolve().parents[2] / "world.schema.json"


def render() -> str:
    schema = msgspec.json.schema(WorldSpec)
    schema["$id"] = "https://rap.dev/schemas/sim_world.world.schema.json"
    schema["title"] = "RAP sim_world world file"
    return json.dumps(schema, indent=2, sort_keys=True) + "\n"


if __name__ == "__main__":
    path = Path(sys.argv[1]) if len(sys.argv) > 1 else SCHEMA_PATH
    path.write_text(render(), encoding="utf-8")
    sys.stdout.write(f"wrote {path}\n")
