"""Helpers over lark's parse tree of an AADL file, and the base of the syntax-model
builder (locations, diagnostics, notes), shared by :mod:`rap_cli.aadl.parse_properties`
and :mod:`rap_cli.aadl.parse_components`."""

from __future__ import annotations

from lark import Token, Tree

from rap_cli.aadl import syntax as s
from rap_cli.diagnostics import Diagnostic, Severity

_Branch = Tree[Token] | Token

_VALUE_RULES = {
    "list_value",
    "range_value",
    "number_value",
    "string_value",
    "bool_value",
    "name_value",
    "reference_value",
    "classifier_value",
    "record_value",
    "computed_value",
}
_TYPE_RULES = {
    "bool_type",
    "string_type",
    "int_type",
    "real_type",
    "enum_type",
    "units_type",
    "classifier_type",
    "reference_type",
    "range_type",
    "record_type",
    "type_ref",
}


# ---------------------------------------------------------------- tree helpers


def _text(node: _Branch) -> str:
    """The tokens under ``node`` joined as written without spaces (``a::b.impl``)."""
    if isinstance(node, Token):
        return str(node)
    return "".join(_text(child) for child in node.children)


def _words(node: Tree[Token]) -> str:
    """Keyword tokens as lower-case words (``thread group``, ``in out``)."""
    return " ".join(str(c).lower() for c in node.children if isinstance(c, Token))


def _owner_text(node: Tree[Token]) -> str:
    """An ``applies to`` owner of a property definition as written (``access
    connection``, ``pkg::T``), category words in lower case."""
    out = ""
    for child in node.children:
        word = str(child)
        glued = child.type in {"DCOLON", "DOT"} if isinstance(child, Token) else False
        out += word if glued or out.endswith((":", ".")) or not out else f" {word}"
    return out.lower() if ":" not in out else out


def _trees(node: Tree[Token], *names: str) -> list[Tree[Token]]:
    """The children of ``node`` that are subtrees of one of ``names``."""
    return [c for c in node.children if isinstance(c, Tree) and c.data in names]


def _tree(node: Tree[Token], name: str) -> Tree[Token] | None:
    """The first child subtree ``name`` of ``node``, or None."""
    found = _trees(node, name)
    return found[0] if found else None


def _toks(node: Tree[Token], *types: str) -> list[Token]:
    """The children of ``node`` that are tokens of one of ``types``."""
    return [c for c in node.children if isinstance(c, Token) and c.type in types]


def _has(node: Tree[Token], kind: str) -> bool:
    """Whether ``node`` has a token of ``kind`` among its children."""
    return bool(_toks(node, kind))


# ---------------------------------------------------------------- building the model


class _BuilderBase:
    """What every part of the builder needs: where a node is, and the notes (what is
    skipped) and diagnostics (what the grammar cannot check) collected so far."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.notes: list[s.Note] = []
        self.diagnostics: list[Diagnostic] = []

    def loc(self, node: _Branch) -> s.Loc:
        """Where ``node`` starts (its first token, keywords included)."""
        if isinstance(node, Token):
            return s.Loc(self.source, node.line or 0, node.column or 0)
        meta = node.meta
        return s.Loc(self.source, getattr(meta, "line", 0), getattr(meta, "column", 0))

    def report(self, node: _Branch, severity: Severity, message: str) -> None:
        """A diagnostic at ``node``."""
        loc = self.loc(node)
        self.diagnostics.append(Diagnostic(self.source, loc.line, loc.column, severity, message))

    def note(self, node: _Branch, message: str) -> None:
        """Record, at ``node``, something read but not modelled."""
        self.notes.append(s.Note(self.loc(node), message))

    def check_end(self, written: list[Token], end: list[Token], what: str) -> None:
        """``end X;`` must repeat the declared name (in any case)."""
        name, closing = "".join(written), "".join(end)
        if s.norm(name) != s.norm(closing):
            message = f"'end {closing};' does not close {what} '{name}' - write 'end {name};'"
            self.report(end[0], "error", message)

    def in_modes(self, tree: Tree[Token]) -> tuple[str, ...]:
        """The modes of ``in modes (..)``; of a mapping ``m => sm`` the owner's ``m``."""
        modes = _tree(tree, "in_modes")
        if modes is None:
            return ()
        return tuple(str(_toks(ref, "IDENT")[0]) for ref in _trees(modes, "mode_ref"))
