"""``rap model show --json``: the normalized model in one documented shape
(``schemas/json/rap.ModelView.schema.json``)."""

from __future__ import annotations

from typing import Any

import msgspec
from rap_schemas.model import connections
from rap_schemas.view import (
    ComponentView,
    ConnectionView,
    DiagnosticView,
    FieldView,
    MessageView,
    ModelView,
    NodeView,
    PortView,
)

from .model_io import CheckedModel

__all__ = ["model_view"]


def model_view(checked: CheckedModel) -> dict[str, Any]:
    """The view of ``checked`` as plain JSON data (empty sections when the model did not
    fit its schema; its findings are in ``diagnostics`` either way)."""
    plan = checked.plan
    view = ModelView(
        diagnostics=[
            DiagnosticView(file=d.file, line=d.line, severity=d.severity, message=d.message)
            for d in checked.diagnostics
        ]
    )
    if plan is not None:
        view = ModelView(
            components=[
                ComponentView(
                    name=name,
                    kind="component",
                    origin=c.origin or "rap",
                    stage=c.stage.value if c.stage is not None else None,
                    role=c.role,
                    ports=[
                        PortView(name=p, direction=port.direction, kind=port.kind, type=port.type)
                        for p, port in c.ports.items()
                    ],
                )
                for name, c in plan.components.items()
            ],
            messages=[
                MessageView(
                    name=name,
                    fields=[FieldView(name=f, type=spec.type) for f, spec in m.fields.items()],
                    enum=m.enum,
                )
                for name, m in plan.messages.items()
            ],
            nodes=[NodeView(name=n, address=c.address) for n, c in plan.compute_nodes.items()],
            bindings={n: c.node for n, c in plan.components.items() if c.node is not None},
            connections=[
                ConnectionView(from_=".".join(c.source), to=".".join(c.target))
                for c in connections(plan)
            ],
            diagnostics=view.diagnostics,
        )
    data: dict[str, Any] = msgspec.to_builtins(view)
    return data
