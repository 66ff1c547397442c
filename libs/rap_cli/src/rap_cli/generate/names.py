"""Python names for the model's names (which may be any key chunk)."""

from __future__ import annotations

import keyword
import re

__all__ = ["class_name", "identifier", "package_name", "unique"]

_NOT_WORD = re.compile(r"[^0-9A-Za-z_]+")


def identifier(name: str, *, prefix: str = "x") -> str:
    """A lower-case Python identifier for ``name`` (``controlSoftware`` ->
    ``control_software``, ``tb1/scan`` -> ``tb1_scan``)."""
    snake = re.sub(r"(?<=[a-z0-9])([A-Z])", r"_\1", name)
    text = _NOT_WORD.sub("_", snake).strip("_").lower() or prefix
    if text[0].isdigit():
        text = f"{prefix}_{text}"
    if keyword.iskeyword(text) or keyword.issoftkeyword(text):
        text += "_"
    return text


def class_name(name: str) -> str:
    """A Python class name for a message or enumeration name (kept when it is one)."""
    if name.isidentifier() and not keyword.iskeyword(name):
        return name[0].upper() + name[1:]
    parts = [p for p in _NOT_WORD.split(name) if p]
    text = "".join(p[0].upper() + p[1:] for p in parts) or "Message"
    return f"M{text}" if text[0].isdigit() else text


def package_name(name: str) -> str:
    """A Python package name for a project or system name."""
    return identifier(name, prefix="pkg")


def unique(names: dict[str, str]) -> dict[str, str]:
    """``names`` (model name -> Python name) with clashes suffixed ``_2``, ``_3`` ..."""
    seen: set[str] = set()
    out: dict[str, str] = {}
    for key, value in names.items():
        candidate, n = value, 1
        while candidate in seen:
            n += 1
            candidate = f"{value}_{n}"
        seen.add(candidate)
        out[key] = candidate
    return out
