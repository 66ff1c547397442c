from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st
from rap_schemas import keys
from rap_schemas.keys import KeyError_, Kind, ParsedKey

chunk = st.from_regex(r"[A-Za-z0-9_.\-]{1,12}", fullmatch=True)
path = st.lists(chunk, min_size=1, max_size=4).map("/".join)


@given(system=chunk, name=path)
def test_multi_chunk_families_round_trip(system: str, name: str) -> None:
    for build, kind in (
        (keys.data, Kind.DATA),
        (keys.event, Kind.EVENT),
        (keys.kb, Kind.KB),
        (keys.trust, Kind.TRUST),
    ):
        key = build(system, name)
        assert key == f"rap/{system}/{kind.value}/{name}"
        assert keys.parse(key) == ParsedKey(system, kind, name)


@given(system=chunk, node=chunk, verb=chunk)
def test_node_families_round_trip(system: str, node: str, verb: str) -> None:
    for build, kind in ((keys.trace, Kind.TRACE), (keys.log, Kind.LOG), (keys.alive, Kind.ALIVE)):
        assert keys.parse(build(system, node)) == ParsedKey(system, kind, node)
    assert keys.parse(keys.admin(system, node, verb)) == ParsedKey(system, Kind.ADMIN, node, verb)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: keys.data("my sys", "scan"), "invalid system 'my sys'"),
        (lambda: keys.data("s", "a//b"), "chunk '' is empty"),
        (lambda: keys.data("s", "scan/*"), "chunk '*'"),
        (lambda: keys.event("s", ""), "must be a non-empty string"),
        (lambda: keys.trace("s", "a/b"), "invalid node 'a/b'"),
        (lambda: keys.admin("s", "n", "sw?p"), "invalid admin verb"),
        (lambda: keys.parse("ros/s/data/x"), "not a RAP key"),
        (lambda: keys.parse("rap/s/stuff/x"), "unknown kind 'stuff'"),
        (lambda: keys.parse("rap/s/admin/n"), "must be 'rap/<system>/admin/<node>/<verb>'"),
        (lambda: keys.parse("rap/s/alive/a/b"), "invalid node 'a/b'"),
    ],
)
def test_bad_parts_are_named_with_the_fix(call: object, message: str) -> None:
    with pytest.raises(KeyError_, match=message.replace("?", r"\?").replace("*", r"\*")):
        call()  # type: ignore[operator]


def test_patterns() -> None:
    assert keys.pattern("s", Kind.EVENT) == "rap/s/event/**"
    assert keys.pattern("s", Kind.DATA, "*/scan") == "rap/s/data/*/scan"
    assert keys.system_pattern("s") == "rap/s/**"
    with pytest.raises(KeyError_):
        keys.pattern("s", Kind.DATA, "sc*n")
