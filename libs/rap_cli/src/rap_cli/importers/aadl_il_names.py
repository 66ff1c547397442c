"""Names the importers share: the MAPLE-K stage or role a component's name says, a
design's name made a valid model name, and AADL's base data types as field types.

(Used by the AADL-IL and RoboChart importers alike; its place would be a shared module of
:mod:`rap_cli.importers`.)
"""

from __future__ import annotations

import re
from typing import Any

from rap_schemas.maplek import Stage

__all__ = ["DATA_TYPES", "STAGE_WORDS", "clean_name", "description", "stage_or_role"]

DATA_TYPES = {
    "Boolean": "bool",
    "Integer": "int",
    "Natural": "int",
    "Integer_8": "int8",
    "Integer_16": "int16",
    "Integer_32": "int32",
    "Integer_64": "int64",
    "Unsigned_8": "uint8",
    "Unsigned_16": "uint16",
    "Unsigned_32": "uint32",
    "Unsigned_64": "uint64",
    "Float": "float",
    "Float_32": "float32",
    "Float_64": "float64",
    "String": "str",
    "Character": "str",
}
"""AADL-IL ``_dataType`` (AADL Base_Types) -> a field type of the model."""

_NOT_NAME = re.compile(r"[^A-Za-z0-9_.\-~+:@=%,]+")
STAGE_WORDS = {
    # the words a component name says its MAPLE-K stage with (every importer)
    "monitor": Stage.MONITOR,
    "analyse": Stage.ANALYSE,
    "analysis": Stage.ANALYSE,
    "analyze": Stage.ANALYSE,
    "plan": Stage.PLAN,
    "planner": Stage.PLAN,
    "legitimate": Stage.LEGITIMATE,
    "legitimation": Stage.LEGITIMATE,
    "execute": Stage.EXECUTE,
    "executor": Stage.EXECUTE,
}


def stage_or_role(name: str) -> tuple[Stage | None, str | None]:
    """The MAPLE-K stage a component's name says (``Monitor``, ``Analysis``,
    ``Adaptation_Plan``: the whole name or its last ``_`` part), or role ``knowledge``
    for a knowledge component; ``(None, None)`` for any other name."""
    for word in (name.lower(), name.rsplit("_", 1)[-1].lower()):
        if word in STAGE_WORDS:
            return STAGE_WORDS[word], None
        if word == "knowledge":
            return None, "knowledge"
    return None, None


def clean_name(text: str) -> str:
    """``text`` as a model name: runs of characters a name may not hold become ``_``,
    leading and trailing ``_`` added that way are dropped."""
    cleaned = _NOT_NAME.sub("_", text)
    if cleaned != text:
        cleaned = cleaned.strip("_")
    return cleaned or "_"


def description(obj: dict[str, Any]) -> str:
    """An AADL-IL ``_description`` as a doc; RPIO's placeholder ``tbd`` is no doc."""
    text = obj.get("_description")
    return text if isinstance(text, str) and text.strip().lower() not in ("", "tbd") else ""
