"""The shape ``rap model show --json`` prints: a system model normalized, whatever it
was read from (a RAP model or an imported design), with the findings of its checks.

A component's ``kind`` is ``component`` for everything that runs; ``origin`` names the
construct it came from (``rap`` for a component of a RAP model)."""

from __future__ import annotations

from typing import Literal

import msgspec

__all__ = [
    "ComponentView",
    "ConnectionView",
    "DiagnosticView",
    "FieldView",
    "MessageView",
    "ModelView",
    "NodeView",
    "PortView",
]


class _View(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    pass


class PortView(_View, frozen=True, kw_only=True):
    name: str
    direction: Literal["in", "out", "in-out"]
    kind: Literal["event", "data", "event-data"]
    type: str | None


class ComponentView(_View, frozen=True, kw_only=True, omit_defaults=True):
    name: str
    kind: Literal["component"]
    origin: str
    stage: str | None
    role: str | None = None
    ports: list[PortView]


class FieldView(_View, frozen=True, kw_only=True):
    name: str
    type: str


class MessageView(_View, frozen=True, kw_only=True, omit_defaults=True):
    name: str
    fields: list[FieldView]
    enum: list[str] | None = None


class NodeView(_View, frozen=True, kw_only=True):
    name: str
    address: str | None


class ConnectionView(_View, frozen=True, kw_only=True):
    from_: str = msgspec.field(name="from")
    to: str


class DiagnosticView(_View, frozen=True, kw_only=True):
    file: str
    line: int
    severity: Literal["error", "warning", "note"]
    message: str


class ModelView(_View, frozen=True, kw_only=True):
    components: list[ComponentView] = []
    messages: list[MessageView] = []
    nodes: list[NodeView] = []
    bindings: dict[str, str] = {}
    connections: list[ConnectionView] = []
    diagnostics: list[DiagnosticView] = []
