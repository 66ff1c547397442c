"""Specs shipped with the checker, as package data.

``maplek/*.dsrv``: the MAPLE-K loop's contract, written against the
fabric's default mapping (:mod:`trust_checker.io.fabric`). Each has one Bool output that
is true while the loop is healthy:

=====================  ===========================  =========================================
spec                   output                       false when
=====================  ===========================  =========================================
``stage_order``        ``stage_order_ok``           a stage starts before the one before it
                                                    started in its cycle (a stage skipped)
``no_overlap``         ``no_overlap_ok``            two handlers of an exclusive stage
                                                    (plan, execute) run at once
``anomaly_deadline``   ``anomaly_deadline_ok``      an anomaly waits longer than 500 ms for
                                                    the execute stage of its cycle
``unread_overwrite``   ``no_unread_overwrite_ok``   a knowledge key is written twice with no
                                                    read in between
``execute_approved``   ``execute_approved_ok``      execute starts in a cycle with no verdict,
                                                    or acts in one with no approving verdict
=====================  ===========================  =========================================

The comments in each file say what it checks, how, and what to edit (the constants in
capitals). ``docs/trust_checker.md`` ("MAPLE-K specs and veto") shows them at work.
"""

from __future__ import annotations

from importlib import resources
from typing import Final

__all__ = ["ANOMALY_DEADLINE_NS", "MAPLEK_OUTPUTS", "maplek_specs"]

ANOMALY_DEADLINE_NS: Final = 500_000_000
"""The deadline written in ``maplek/anomaly_deadline.dsrv`` (a test keeps them equal)."""

MAPLEK_OUTPUTS: Final = {
    "stage_order": "stage_order_ok",
    "no_overlap": "no_overlap_ok",
    "anomaly_deadline": "anomaly_deadline_ok",
    "unread_overwrite": "no_unread_overwrite_ok",
    "execute_approved": "execute_approved_ok",
}
"""Each shipped MAPLE-K spec's name -> its Bool output stream."""


def maplek_specs() -> dict[str, str]:
    """The shipped MAPLE-K specs: name (the file's stem) -> spec text, sorted by name."""
    folder = resources.files(__name__).joinpath("maplek")
    found = sorted(
        (entry.name.removesuffix(".dsrv"), entry.read_text(encoding="utf-8"))
        for entry in folder.iterdir()
        if entry.name.endswith(".dsrv")
    )
    return dict(found)
