"""The built-ins with state: ``when``, ``latch``, ``update``, ``timeout`` and
``x.aggregate(over: W, using: f)``. Each is a :class:`~.nodes.StatefulNode` that the
runner updates once per tick, before the stream that contains it is computed; the
real-time ones read the tick's timestamp from the shared :class:`~.nodes.TickTime`.
A node's ``export()``/``restore()`` carry its state over a hot swap.
"""

from __future__ import annotations

import math
from collections import deque
from typing import cast

from trust_checker.engine.nodes import ExprNode, StatefulNode, TickTime
from trust_checker.lang import ast
from trust_checker.operators import Fault
from trust_checker.values import BOTTOM, INT_MAX, INT_MIN, NOVAL, console

__all__ = ["AggregateNode", "LatchNode", "TimeoutNode", "UpdateNode", "WhenNode"]


class WhenNode(StatefulNode):
    __slots__ = ("_fe",)

    def __init__(self, node: ast.Expr, e: ExprNode) -> None:
        super().__init__(node, (e,), always=True)
        self._fe = e.held
        self.cur_v = self.held_v = False

    def update(self) -> None:
        if self.held_v is False:
            v = self._fe()
            if v is not NOVAL and v is not BOTTOM:
                self.cur_v = self.held_v = True


class LatchNode(StatefulNode):
    __slots__ = ("_fx", "_fy")

    def __init__(self, node: ast.Expr, x: ExprNode, y: ExprNode) -> None:
        super().__init__(node, (x, y), always=False)
        self._fx, self._fy = x.held, y.cur

    def update(self) -> None:
        if self._fy() is NOVAL:
            self.cur_v = NOVAL
        else:
            self._set(self._fx())


class UpdateNode(StatefulNode):
    __slots__ = ("_fa", "_fb", "_switched")

    def __init__(self, node: ast.Expr, a: ExprNode, b: ExprNode) -> None:
        super().__init__(node, (a, b), always=False)
        self._fa, self._fb = a.held, b.held
        self._switched = False

    def update(self) -> None:
        if not self._switched:
            v = self._fb()
            if v is not NOVAL and v is not BOTTOM:
                self._switched = True
        self._set(self._fb() if self._switched else self._fa())

    def export(self) -> object:
        return (self.cur_v, self.held_v, self._switched)

    def restore(self, state: object) -> None:
        self.cur_v, self.held_v, self._switched = state  # type: ignore[misc]


class TimeoutNode(StatefulNode):
    __slots__ = ("_clock", "_fx", "_limit", "_since", "_where")

    def __init__(self, node: ast.Expr, x: ExprNode, limit_ns: int, clock: TickTime, where: str):
        super().__init__(node, (x,), always=True)
        self._fx, self._limit, self._clock, self._where = x.cur, limit_ns, clock, where
        self._since: int | None = None

    def update(self) -> None:
        now = self._clock.ts
        if now is None:
            raise Fault(
                "timeout(...) needs tick timestamps, and this tick has none "
                "(pass ts_ns to SpecRunner.step)",
                self._where,
            )
        v = self._fx()
        if self._since is None or (v is not NOVAL and v is not BOTTOM):
            self._since = now
        self.cur_v = self.held_v = now - self._since > self._limit

    def export(self) -> object:
        return (self.cur_v, self.held_v, self._since)

    def restore(self, state: object) -> None:
        self.cur_v, self.held_v, self._since = state  # type: ignore[misc]


class AggregateNode(StatefulNode):
    """``x.aggregate(over: W, using: f)`` over the data values x took at ticks whose
    timestamp is within ``(now - W, now]``; bounded by ``cap`` samples."""

    __slots__ = (
        "_cap",
        "_clock",
        "_floats",
        "_fx",
        "_isum",
        "_mono",
        "_q",
        "_using",
        "_where",
        "_window",
    )

    def __init__(
        self, node: ast.Aggregate, x: ExprNode, clock: TickTime, cap: int, where: str
    ) -> None:
        super().__init__(node, (x,), always=True)
        self._fx, self._clock, self._cap, self._where = x.cur, clock, cap, where
        self._window, self._using = node.window_ns, node.using
        self._q: deque[tuple[int, object]] = deque()
        self._mono: deque[tuple[int, object]] = deque()
        self._isum = 0
        self._floats = 0

    def update(self) -> None:
        now = self._clock.ts
        if now is None:
            raise Fault(
                f"x.aggregate(using: {self._using}) needs tick timestamps, and this tick "
                "has none (pass ts_ns to SpecRunner.step)",
                self._where,
            )
        v = self._fx()
        using = self._using
        if v is not NOVAL and v is not BOTTOM:
            if using != "count" and (type(v) is not int and type(v) is not float):
                raise Fault(f"aggregate {using} needs numbers, got {console(v)}", self._where)
            if len(self._q) >= self._cap:
                raise Fault(
                    f"aggregate window holds more than {self._cap} samples "
                    "(raise Limits.window_samples or shorten the window)",
                    self._where,
                )
            self._q.append((now, v))
            if type(v) is int:
                self._isum += v
            else:
                self._floats += 1
            if using in ("min", "max"):
                mono = self._mono
                if using == "min":
                    while mono and mono[-1][1] >= v:  # type: ignore[operator]
                        mono.pop()
                else:
                    while mono and mono[-1][1] <= v:  # type: ignore[operator]
                        mono.pop()
                mono.append((now, v))
        edge = now - self._window
        q = self._q
        while q and q[0][0] <= edge:
            _, old = q.popleft()
            if type(old) is int:
                self._isum -= old
            else:
                self._floats -= 1
        while self._mono and self._mono[0][0] <= edge:
            self._mono.popleft()
        self.cur_v = self.held_v = self._fold()

    def _fold(self) -> object:
        n = len(self._q)
        if self._using == "count":
            return n
        if self._using in ("min", "max"):
            return self._mono[0][1] if self._mono else BOTTOM
        if self._floats:
            total: object = math.fsum(v for _, v in self._q)  # type: ignore[misc]
        else:
            if not INT_MIN <= self._isum <= INT_MAX:
                raise Fault(
                    f"Int overflow: the window's sum {self._isum} does not fit in 64 bits",
                    self._where,
                )
            total = self._isum
        if self._using == "sum":
            return total
        return total / n if n else BOTTOM  # type: ignore[operator]

    def export(self) -> object:
        return (self.cur_v, self.held_v, list(self._q), list(self._mono))

    def restore(self, state: object) -> None:
        self.cur_v, self.held_v, q, mono = cast(
            tuple[object, object, list[tuple[int, object]], list[tuple[int, object]]], state
        )
        self._q.clear()
        self._mono.clear()
        self._isum = self._floats = 0
        for t, v in q:
            self._q.append((t, v))
            if type(v) is int:
                self._isum += v
            else:
                self._floats += 1
        self._mono.extend(mono)
