"""Dynamic specs: ``eval(s)`` (alias ``dynamic(s)``) and ``defer(s)``, the expression
held in a Str stream, parsed with the checker's own parser (never Python's) and compiled
on the fly against the spec's streams (docs/trust_checker.md, "Dynamic specs").
"""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

from trust_checker import operators as op
from trust_checker.engine.compiler import Compiler
from trust_checker.engine.nodes import ExprNode, StatefulNode
from trust_checker.errors import SpecError
from trust_checker.lang import ast
from trust_checker.lang.parser import parse_expr
from trust_checker.operators import Fault, Mismatch
from trust_checker.values import BOTTOM, NOVAL, console

__all__ = ["EvalNode"]


class EvalNode(StatefulNode):
    """``eval(s)`` / ``dynamic(s)`` and ``defer(s)``: the expression held in the Str stream
    ``s``, parsed with the checker's own parser and compiled by ``compiler()`` (whose
    ``lookup`` enforces the scope). ``eval`` re-parses whenever the text changes; ``defer``
    keeps the first expression that parses."""

    __slots__ = ("_compiler", "_conform", "_expr", "_fixed", "_src", "_text", "_updates", "_where")

    def __init__(
        self,
        node: ast.Eval,
        source: ExprNode,
        compiler: Callable[[], Compiler],
        where: str,
    ) -> None:
        super().__init__(node, (source,), always=False)
        self._src = source.held
        self._compiler = compiler
        self._where = where
        self._conform = None if node.ascription is None else op.conformer(node.ascription)
        self._text: str | None = None
        self._expr: ExprNode | None = None
        self._updates: list[StatefulNode] = []
        self._fixed = False

    @property
    def kind(self) -> str:
        return self.ast.kind  # type: ignore[union-attr]

    def update(self) -> None:
        s = self._src()
        if s is NOVAL:
            self.cur_v = NOVAL
            return
        if not self._fixed:
            if s is BOTTOM:
                self._set(BOTTOM)
                return
            if type(s) is not str:
                raise Fault(
                    f"{self.kind}(s) needs a Str holding an expression, got {console(s)}",
                    self._where,
                )
            if s != self._text:
                self._load(s)
        if self._expr is None:
            self._set(BOTTOM)
            return
        for u in self._updates:
            u.update()
        v = self._expr.cur()
        if self._conform is not None and v is not NOVAL:
            try:
                v = self._conform(v)
            except Mismatch as m:
                raise Fault(
                    f"{self.kind} of {self._text!r} gave a value of the wrong type: {m} "
                    "(fix the expression or the ascription)",
                    self._where,
                ) from None
        self._set(v)

    def _load(self, text: str) -> None:
        self._text = text
        self._expr = None
        self._updates = []
        try:
            tree = parse_expr(text, f"<{self.kind} at {self._where}>")
            c = self._compiler()
            expr = c.compile(tree)
        except SpecError as e:
            raise Fault(
                f"cannot parse the {self.kind} expression {text!r}: {e}", self._where
            ) from None
        except Fault as f:
            raise Fault(
                f"cannot use the {self.kind} expression {text!r}: {f.message}"
                + (f" ({f.where})" if f.where else ""),
                self._where,
            ) from None
        self._expr, self._updates = expr, c.stateful
        self._fixed = self.kind == "defer"

    def export(self) -> object:
        inner = [u.export() for u in self._updates]
        return (self.cur_v, self.held_v, self._text, self._fixed, inner)

    def restore(self, state: object) -> None:
        self.cur_v, self.held_v, text, fixed, inner = cast(
            tuple[object, object, str | None, bool, list[object]], state
        )
        if text is None:
            return
        try:
            self._load(text)
        except Fault:
            return
        self._fixed = fixed
        if len(inner) == len(self._updates):
            for u, st in zip(self._updates, inner, strict=True):
                u.restore(st)
