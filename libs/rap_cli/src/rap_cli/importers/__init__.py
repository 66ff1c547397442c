"""Importers: from a design (AADL, AADL-IL, RoboChart) to RAP's system model.

Every importer returns an :class:`Imported`: the model it built (a
:class:`rap_schemas.DeploymentPlan`), what it found wrong with the design (located
diagnostics), and where in the design each part of the model came from (``where``), so
that the model's own cross-checks (:func:`rap_schemas.model.model_findings`), run later
by the ``rap`` command, point at the design's lines too.

An importer never raises on a bad design: what it cannot read or resolve is a
diagnostic, and what it reads but the model has no place for is a ``note``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from rap_schemas import DeploymentPlan
from rap_schemas.yamlconf import Location

from ..diagnostics import Diagnostic, Loc

__all__ = ["Imported"]


@dataclass(slots=True)
class Imported:
    """What an import yields.

    ``plan`` is None only when nothing at all could be read (then ``readable`` is False
    and ``diagnostics`` says why). ``where`` maps a location in the model (a path such as
    ``("components", "m", "ports", "scan")``) to the construct of the design it came
    from; :meth:`locate` finds the nearest one for any path."""

    plan: DeploymentPlan | None
    diagnostics: list[Diagnostic] = field(default_factory=list)
    where: dict[tuple[object, ...], Loc] = field(default_factory=dict)
    sources: list[str] = field(default_factory=list)
    readable: bool = True

    def locate(self, loc: Location) -> Loc | None:
        """Where the part of the model at ``loc`` (or its nearest enclosing part that
        has a place) is in the design; None when nothing of it has one."""
        path = tuple(loc)
        while True:
            found = self.where.get(path)
            if found is not None:
                return found
            if not path:
                return None
            path = path[:-1]
