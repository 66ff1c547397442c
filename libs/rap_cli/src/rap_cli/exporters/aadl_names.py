"""AADL identifiers for the names of a RAP model, and AADL literals.

A RAP name may hold characters an AADL identifier cannot (``tb1/scan`` is a topic, but
a component may be ``robot-1``); :class:`Names` gives each name one identifier, unique in
its scope and never a reserved word, and the exporter writes ``RAP::Name`` wherever the
identifier differs from the name, so that the import gives the name back.
"""

from __future__ import annotations

import re

__all__ = ["RESERVED", "Names", "aadl_string", "common", "ident", "props_block", "real", "strings"]

RESERVED = frozenset(
    """
    aadlboolean aadlinteger aadlreal aadlstring abstract access all and annex applies
    binding bus calls classifier compute connections constant data delta device end
    enumeration event extends false features feature flow flows group implementation in
    inherit initial inverse is list memory mode modes none not of or out package parameter
    path port private process processor properties property prototypes provides public
    range record reference refined refines renames requires self set sink source
    subcomponents subprogram system thread to true type units virtual with
    """.split()
)
"""AADL v2's reserved words (case-insensitive)."""

_BAD = re.compile(r"[^A-Za-z0-9_]+")


def ident(name: str) -> str:
    """An AADL identifier for ``name``: letters, digits and single underscores, starting
    with a letter, not ending with ``_``, not a reserved word."""
    text = _BAD.sub("_", name)
    text = re.sub(r"_+", "_", text).strip("_")
    if not text or not text[0].isalpha():
        text = f"n_{text}" if text else "n"
    if text.lower() in RESERVED:
        text = f"{text}_1"
    return text


class Names:
    """One scope of AADL identifiers (case-insensitive, as AADL's are)."""

    def __init__(self, taken: tuple[str, ...] = ()) -> None:
        self._by_name: dict[str, str] = {}
        self._used: set[str] = {t.lower() for t in taken}

    def __call__(self, name: str) -> str:
        """The identifier of ``name`` in this scope (the same one each time)."""
        found = self._by_name.get(name)
        if found is not None:
            return found
        base = ident(name)
        candidate, n = base, 1
        while candidate.lower() in self._used:
            n += 1
            candidate = f"{base}_{n}"
        self._used.add(candidate.lower())
        self._by_name[name] = candidate
        return candidate


def aadl_string(text: str) -> str:
    """``text`` as an AADL string literal (one line; ``"`` doubled)."""
    return '"' + " ".join(text.split("\n")).replace('"', '""') + '"'


def props_block(items: list[str], indent: str) -> list[str]:
    """A ``properties`` section of ``items`` (nothing when there are none)."""
    if not items:
        return []
    return [f"{indent}properties", *(f"{indent}  {p};" for p in items)]


def strings(values: list[str]) -> str:
    """An AADL list of string literals."""
    return "(" + ", ".join(aadl_string(v) for v in values) + ")"


def real(value: float) -> str:
    """An AADL real literal (always with a ``.`` or an exponent)."""
    text = repr(float(value))
    return text if "e" in text or "." in text else f"{text}.0"


def common(name: str, ident_: str, doc: str, properties: dict[str, str]) -> list[str]:
    """The ``RAP::Name``, ``RAP::Doc`` and ``RAP::Design_Properties`` of a part."""
    out = []
    if ident_ != name:
        out.append(f"RAP::Name => {aadl_string(name)}")
    if doc:
        out.append(f"RAP::Doc => {aadl_string(doc)}")
    if properties:
        out.append(
            f"RAP::Design_Properties => {strings([f'{k} => {v}' for k, v in properties.items()])}"
        )
    return out
