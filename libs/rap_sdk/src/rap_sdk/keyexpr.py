"""Zenoh key-expression intersection for ``*`` and ``**`` chunks, in pure Python.

Used for in-process delivery (which never touches Zenoh) and by MemoryFabric. Checked
against ``zenoh.KeyExpr.intersects`` by a property test.
"""

from __future__ import annotations

import itertools
from functools import cache, lru_cache

__all__ = ["KeyExprError", "intersects", "validate"]


class KeyExprError(ValueError):
    """A malformed key expression."""


def validate(expr: str) -> str:
    """Return ``expr`` if it is a key expression RAP accepts, else raise with the fix."""
    if not expr:
        raise KeyExprError("empty key expression; use e.g. 'rap/<system>/data/<topic>'")
    for chunk in expr.split("/"):
        if not chunk:
            raise KeyExprError(
                f"key expression {expr!r} has an empty chunk (a '//' or an edge '/'); remove it"
            )
        if chunk in ("*", "**"):
            continue
        if any(c in chunk for c in "*$#?"):
            raise KeyExprError(
                f"key expression {expr!r}: chunk {chunk!r} uses '*', '$', "
                "'#' or '?' inside a chunk; wildcards must be whole chunks"
            )
    chunks = expr.split("/")
    for first, second in itertools.pairwise(chunks):
        if first == "**" and second in ("*", "**"):
            fix = "a single '**'" if second == "**" else "'*/**'"
            raise KeyExprError(
                f"key expression {expr!r} is not canonical: write {fix} instead of '**/{second}'"
            )
    return expr


@lru_cache(maxsize=8192)
def intersects(a: str, b: str) -> bool:
    """True when some concrete key matches both expressions."""
    return _intersects(tuple(a.split("/")), tuple(b.split("/")))


def _intersects(a: tuple[str, ...], b: tuple[str, ...]) -> bool:
    @cache
    def go(i: int, j: int) -> bool:
        if i == len(a) and j == len(b):
            return True
        if i == len(a):
            return all(c == "**" for c in b[j:])
        if j == len(b):
            return all(c == "**" for c in a[i:])
        x, y = a[i], b[j]
        if x == "**":
            return go(i + 1, j) or go(i, j + 1)
        if y == "**":
            return go(i, j + 1) or go(i + 1, j)
        if x == y or x == "*" or y == "*":
            return go(i + 1, j + 1)
        return False

    return go(0, 0)
