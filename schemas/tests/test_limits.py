"""Explicit decoder limits: size, nesting, bad UTF-8; every failure is a reason."""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import pytest
from hypothesis import given
from hypothesis import strategies as st
from rap_schemas import LaserScan, pack_ranges
from rap_schemas.limits import MAX_DEPTH, DecodeRejected, SafeDecoder, check_depth, decode_failure
from rap_schemas.yamlconf import YamlError, parse_yaml, read_text_file


def nested_msgpack(depth: int) -> bytes:
    return b"\x91" * depth + b"\xc0"


@pytest.mark.parametrize("depth", [MAX_DEPTH + 1, 1000, 100_000])
def test_deep_untyped_msgpack_is_a_rejection(depth: int) -> None:
    with pytest.raises(DecodeRejected, match="nest"):
        SafeDecoder(max_depth=MAX_DEPTH).decode(nested_msgpack(depth))


def test_depth_at_the_limit_is_accepted() -> None:
    value = SafeDecoder(max_depth=MAX_DEPTH).decode(nested_msgpack(MAX_DEPTH))
    assert check_depth(value) is value


def test_deep_json_is_a_rejection() -> None:
    decode = SafeDecoder(protocol="json", max_depth=MAX_DEPTH).decode
    with pytest.raises(DecodeRejected, match="nest"):
        decode(b"[" * 5000 + b"]" * 5000)


def test_size_limit() -> None:
    with pytest.raises(DecodeRejected, match="over the limit of 10"):
        SafeDecoder(max_bytes=10).decode(b"\xc0" * 11)


def test_bad_utf8_in_a_string_is_worded() -> None:
    payload = b"\xa2\xff\xfe"  # a 2-byte msgpack str that is not UTF-8
    with pytest.raises(DecodeRejected, match="not valid UTF-8"):
        SafeDecoder(str).decode(payload)


def test_typed_message_rejects_nan_via_schema() -> None:
    decode = SafeDecoder(LaserScan).decode
    bad = msgspec.msgpack.encode(
        {
            "stamp": 1,
            "frame_id": "f",
            "angle_min": 0.0,
            "angle_increment": 0.1,
            "range_min": 0.1,
            "range_max": 5.0,
            "ranges": pack_ranges([math.nan]),
        }
    )
    with pytest.raises(DecodeRejected, match=r"ranges\[0\] is nan"):
        decode(bad)


@given(st.binary(max_size=200))
def test_any_bytes_decode_or_are_rejected(data: bytes) -> None:
    for decoder in (SafeDecoder(max_depth=MAX_DEPTH), SafeDecoder(LaserScan)):
        reason = "decoded"
        try:
            decoder.decode(data)
        except DecodeRejected as exc:
            reason = exc.reason
        assert reason


def test_decode_failure_words_recursion() -> None:
    assert "nested too deeply" in decode_failure(RecursionError())


def test_yaml_nesting_is_bounded_with_a_position() -> None:
    with pytest.raises(YamlError, match=r"^x\.yaml:1:\d+: .*more than 64 levels"):
        parse_yaml("a: " + "[" * 500 + "]" * 500, "x.yaml")


def test_yaml_alias_bombs_are_bounded() -> None:
    lines = ["a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    for prev, name in zip("abcde", "bcdef", strict=True):
        lines.append(f"{name}: &{name} [" + ", ".join([f"*{prev}"] * 10) + "]")
    lines.append("g: [" + ", ".join(["*f"] * 10) + "]")
    with pytest.raises(YamlError, match="expands to more than"):
        parse_yaml("\n".join(lines), "bomb.yaml")


def test_binary_file_is_located(tmp_path: Path) -> None:
    path = tmp_path / "spec.dsrv"
    path.write_bytes(b"input a: Int\n\x89PNG")
    with pytest.raises(YamlError, match=r"spec\.dsrv:2:1: the spec is not UTF-8 text"):
        read_text_file(path, what="spec")


def test_missing_and_directory(tmp_path: Path) -> None:
    with pytest.raises(YamlError, match="cannot read the plan"):
        read_text_file(tmp_path / "nope.yaml", what="plan")
    with pytest.raises(YamlError, match="is a directory"):
        read_text_file(tmp_path, what="plan")
