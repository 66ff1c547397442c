from __future__ import annotations

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st
from rap_sdk.keyexpr import KeyExprError, intersects, validate

chunks = st.sampled_from(["a", "b", "c", "*", "**"])


def canonical(expr: str) -> bool:
    try:
        validate(expr)
    except KeyExprError:
        return False
    return True


exprs = st.lists(chunks, min_size=1, max_size=5).map("/".join).filter(canonical)


@settings(max_examples=400)
@given(exprs, exprs)
def test_intersection_agrees_with_zenoh(a: str, b: str) -> None:
    assert intersects(a, b) == zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b))


@pytest.mark.parametrize(
    ("a", "b", "hit"),
    [
        ("rap/s/data/scan", "rap/s/data/scan", True),
        ("rap/s/data/*", "rap/s/data/scan", True),
        ("rap/s/data/*", "rap/s/data/tb1/scan", False),
        ("rap/s/**", "rap/s", True),
        ("rap/**/scan", "rap/s/data/tb1/scan", True),
        ("rap/s/event/**", "rap/s/data/x", False),
    ],
)
def test_examples(a: str, b: str, hit: bool) -> None:
    assert intersects(a, b) is hit


@pytest.mark.parametrize("bad", ["", "a//b", "/a", "a/", "a/b*", "a/$*", "a/**/**", "a/**/*"])
def test_invalid_expressions_are_refused(bad: str) -> None:
    with pytest.raises(KeyExprError):
        validate(bad)
