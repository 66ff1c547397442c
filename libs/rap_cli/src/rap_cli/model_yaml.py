"""Write a system model as the YAML a user reads and edits (``rap import -o``).

Fields left at their defaults are left out, so an imported model shows what the design
said and nothing else; reading the file back (``rap check``) gives the same model.
"""

from __future__ import annotations

from typing import Any

import msgspec
import yaml
from rap_schemas import DeploymentPlan

__all__ = ["model_to_data", "model_to_yaml"]


def model_to_data(plan: DeploymentPlan) -> dict[str, Any]:
    """``plan`` as plain data, without the fields that hold their defaults."""
    data = _prune(plan)
    assert isinstance(data, dict)
    return data


def _prune(value: Any) -> Any:
    if isinstance(value, msgspec.Struct):
        out: dict[str, Any] = {}
        for f in msgspec.structs.fields(value):
            item = getattr(value, f.name)
            if f.default is not msgspec.NODEFAULT and item == f.default:
                continue
            if f.default_factory is not msgspec.NODEFAULT and item == f.default_factory():
                continue
            out[f.encode_name] = _prune(item)
        return out
    if isinstance(value, dict):
        return {k: _prune(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_prune(v) for v in value]
    return msgspec.to_builtins(value)


class _Dumper(yaml.SafeDumper):
    """Block style for mappings and lists of mappings, flow style for short scalar
    lists; multi-line strings as literal blocks."""


def _str(dumper: yaml.SafeDumper, data: str) -> yaml.Node:
    style = "|" if "\n" in data else None
    return dumper.represent_scalar("tag:yaml.org,2002:str", data, style=style)


def _list(dumper: yaml.SafeDumper, data: list[Any]) -> yaml.Node:
    flow = all(isinstance(v, str | int | float | bool) for v in data) and len(data) <= 12
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


_Dumper.add_representer(str, _str)
_Dumper.add_representer(list, _list)


def model_to_yaml(plan: DeploymentPlan, header: str = "") -> str:
    """The model as YAML text, after ``header`` (each of its lines made a comment)."""
    lines = [f"# {line}".rstrip() for line in header.splitlines()]
    body = yaml.dump(
        model_to_data(plan),
        Dumper=_Dumper,
        sort_keys=False,
        allow_unicode=True,
        width=100,
        default_flow_style=False,
    )
    return "\n".join(lines) + ("\n" if lines else "") + body
