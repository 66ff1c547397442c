"""``python -m sim_world.schema [PATH]``: write the JSON Schema of world files (``make
schemas``); PATH defaults to world.schema.json beside the sim_world package's
pyproject.toml (services/sim_world/world.schema.json in the repository)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import msgspec
import typer
from rap_sdk.entry import fail, run_cli

from .world import WorldSpec

__all__ = ["SCHEMA_PATH", "cli", "main", "render"]

SCHEMA_PATH = Path(__file__).resolve().parents[2] / "world.schema.json"

cli = typer.Typer(add_completion=False, help=__doc__)


def render() -> str:
    schema = msgspec.json.schema(WorldSpec)
    schema["$id"] = "https://rap.dev/schemas/sim_world.world.schema.json"
    schema["title"] = "RAP sim_world world file"
    # allow_nan=False: a default of inf or nan would be written as invalid JSON
    return json.dumps(schema, indent=2, sort_keys=True, allow_nan=False) + "\n"


@cli.command()
def main(
    path: Annotated[
        Path | None,
        typer.Argument(
            help="Where to write the schema (default: world.schema.json).", show_default=False
        ),
    ] = None,
) -> None:
    """Write the JSON Schema of sim_world's world files."""
    out = SCHEMA_PATH if path is None else path
    if out.is_dir():
        raise fail(f"{out}: is a directory - give a file path, e.g. {out / 'world.schema.json'}")
    try:
        out.write_text(render(), encoding="utf-8")
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise fail(f"{out}: cannot write the schema: {reason} - give a writable path") from None
    typer.echo(f"wrote {out}")


if __name__ == "__main__":
    run_cli(cli)
