"""The payload codec: three input forms told apart by shape, two output forms."""

from __future__ import annotations

import math

import msgspec
import pytest
from trust_checker.io.codec import (
    MAX_PAYLOAD,
    CodecError,
    decode_payload,
    encode_value,
    payload_form,
)
from trust_checker.values import BOTTOM, NOVAL, UNIT, MapV, StructV, TupleV


@pytest.mark.parametrize(
    ("payload", "value"),
    [
        # plain
        (b"42", 42),
        (b"1.5", 1.5),
        (b"true", True),
        (b'"hello"', "hello"),
        (b"null", UNIT),
        (b"[1, 2]", (1, 2)),
        (b'{"a": 1, "b": "x"}', MapV(a=1, b="x")),
        (b'"Deferred"', "Deferred"),  # only "Unit" and "Unknown" are bare tags
        (b'{"value": 1, "other": 2}', MapV(value=1, other=2)),  # not only value/deferred
        # tagged
        (b'{"Int": 42}', 42),
        (b'{"Float": 2}', 2.0),
        (b'{"Bool": false}', False),
        (b'{"Str": "Unit"}', "Unit"),
        (b'"Unit"', UNIT),
        (b'"Unknown"', BOTTOM),
        (b'{"List": [{"Int": 1}, "Unknown"]}', (1, BOTTOM)),
        (b'{"Tuple": [{"Int": 1}, {"Bool": true}]}', TupleV((1, True))),
        (b'{"Struct": {"a": {"Int": 1}}}', StructV(a=1)),
        # wrapped (read as plain inside)
        (b'{"value": 7}', 7),
        (b'{"value": {"Int": 1}}', MapV(Int=1)),
        (b'{"value": "Unknown"}', "Unknown"),
        (b'{"value": null}', UNIT),
        (b'{"value": null, "deferred": true}', BOTTOM),
        (b'{"value": 3, "deferred": false}', 3),
    ],
)
def test_decode(payload: bytes, value: object) -> None:
    got = decode_payload(payload)
    assert got == value
    assert type(got) is type(value)


def test_forms_are_told_apart_by_shape() -> None:
    assert payload_form({"Int": 1}) == "tagged"
    assert payload_form("Unknown") == "tagged"
    assert payload_form({"value": 1}) == "wrapped"
    assert payload_form({"value": 1, "deferred": True}) == "wrapped"
    assert payload_form({"deferred": True}) == "plain"
    assert payload_form({"Int": 1, "x": 2}) == "plain"
    assert payload_form("Int") == "plain"
    assert payload_form(3) == "plain"


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"", "empty payload"),
        (b"   ", "empty payload"),
        (b"{not json", "payload: undecodable: JSON is malformed"),
        (b'{"Int": "x"}', "tagged value rejected"),
        (b'{"Int": 1.5}', "tagged value rejected"),
        (b'{"Int": 9223372036854775808}', "64 bits"),
        (b"9223372036854775808", "64 bits"),
        (b'{"value": 1, "deferred": "yes"}', '"deferred" must be true or false'),
    ],
)
def test_bad_payloads_say_why(payload: bytes, reason: str) -> None:
    with pytest.raises(CodecError, match=reason):
        decode_payload(payload)


def test_oversized_payload_is_rejected() -> None:
    with pytest.raises(CodecError, match="larger than"):
        decode_payload(b" " * (MAX_PAYLOAD + 1))


def test_str_payload_is_accepted() -> None:
    assert decode_payload('{"Int": 3}') == 3


@pytest.mark.parametrize(
    ("value", "plain", "tagged"),
    [
        (7, {"value": 7}, {"Int": 7}),
        (2.5, {"value": 2.5}, {"Float": 2.5}),
        (True, {"value": True}, {"Bool": True}),
        ("a", {"value": "a"}, {"Str": "a"}),
        (UNIT, {"value": None}, "Unit"),
        (BOTTOM, {"value": None, "deferred": True}, "Unknown"),
        ((1, 2), {"value": [1, 2]}, {"List": [{"Int": 1}, {"Int": 2}]}),
        (MapV(k=1), {"value": {"k": 1}}, {"Map": {"k": {"Int": 1}}}),
        (math.inf, {"value": None}, {"Float": None}),
    ],
)
def test_encode(value: object, plain: object, tagged: object) -> None:
    assert msgspec.json.decode(encode_value(value)) == plain
    assert msgspec.json.decode(encode_value(value, tagged=True)) == tagged


@pytest.mark.parametrize("value", [7, -3, 2.5, True, "x", UNIT, BOTTOM, (1, "a"), MapV(k=(1,))])
@pytest.mark.parametrize("tagged", [False, True])
def test_outputs_feed_another_checker(value: object, tagged: bool) -> None:
    got = decode_payload(encode_value(value, tagged=tagged))
    assert got == value
    assert type(got) is type(value)


def test_noval_is_never_encoded() -> None:
    with pytest.raises(ValueError, match="NoVal"):
        encode_value(NOVAL)
