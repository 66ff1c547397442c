"""JSON Schema export of every wire message, the envelope, the system model (the
deployment plan grown) and the view ``rap model show --json`` prints (``make schemas``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import msgspec

from .catalog import MESSAGES
from .envelope import Envelope
from .knowledge import KbReply, KbRequest
from .plan import DeploymentPlan
from .view import ModelView

__all__ = ["PLAN_SCHEMA", "render", "write"]

PLAN_SCHEMA = "rap.DeploymentPlan.schema.json"
"""The export's file for deployment plans (a file format, not a versioned wire message)."""


def _file_name(type_name: str) -> str:
    # "rap.LaserScan/1" -> "rap.LaserScan.v1.schema.json"; "rap.X" -> "rap.X.schema.json"
    name, _, version = type_name.partition("/")
    return f"{name}.v{version}.schema.json" if version else f"{name}.schema.json"


def render() -> dict[str, str]:
    """File name -> JSON text, deterministic (sorted keys, trailing newline)."""
    out: dict[str, str] = {}
    entries: list[tuple[str, Any]] = [
        ("rap.Envelope/1", Envelope),
        ("rap.KbRequest/1", KbRequest),
        ("rap.KbReply/1", KbReply),
        ("rap.DeploymentPlan", DeploymentPlan),
        ("rap.ModelView", ModelView),
    ]
    entries += [(m.TYPE, m) for m in MESSAGES]
    for type_name, cls in entries:
        schema = msgspec.json.schema(cls)
        schema["$id"] = f"https://rap.dev/schemas/{_file_name(type_name)}"
        schema["title"] = type_name
        out[_file_name(type_name)] = json.dumps(schema, indent=2, sort_keys=True) + "\n"
    return out


def write(directory: Path) -> list[Path]:
    """Write the export into ``directory`` and delete stale schema files there."""
    directory.mkdir(parents=True, exist_ok=True)
    files = render()
    written = []
    for stale in directory.glob("*.schema.json"):
        if stale.name not in files:
            stale.unlink()
    for name, text in files.items():
        path = directory / name
        path.write_text(text, encoding="utf-8")
        written.append(path)
    return written
