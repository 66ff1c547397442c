from __future__ import annotations

from pathlib import Path

import msgspec
import pytest
from hypothesis import given
from hypothesis import strategies as st
from rap_schemas import (
    MESSAGES,
    Envelope,
    Message,
    SpinCommand,
    SpinPlan,
    by_type,
)
from rap_schemas.export import render

EXPORT = Path(__file__).resolve().parents[1] / "json"


def test_committed_json_schema_matches_the_structs() -> None:
    """Fails when a Struct changed and `make schemas` was not run."""
    expected = render()
    on_disk = {p.name: p.read_text(encoding="utf-8") for p in EXPORT.glob("*.schema.json")}
    assert sorted(on_disk) == sorted(expected), "run `make schemas` and commit schemas/json"
    for name, text in expected.items():
        assert on_disk[name] == text, f"{name} drifted from its Struct: run `make schemas`"


def test_every_message_has_a_unique_versioned_name() -> None:
    names = [m.TYPE for m in MESSAGES]
    assert len(set(names)) == len(names)
    for m in MESSAGES:
        assert by_type(m.TYPE) is m
    with pytest.raises(KeyError, match=r"unknown message type 'rap\.Nope/1'"):
        by_type("rap.Nope/1")


def test_a_bad_wire_name_is_refused_at_class_creation() -> None:
    with pytest.raises(TypeError, match="is not a wire name"):

        class Bad(Message, frozen=True):
            TYPE = "LaserScan"


def test_wire_messages_accept_fields_added_by_newer_senders() -> None:
    class SpinCommandV2(msgspec.Struct, frozen=True):
        omega: float
        duration: float
        ramp: float = 0.0  # a field a newer sender added

    wire = msgspec.msgpack.encode(SpinCommandV2(omega=1.0, duration=2.0, ramp=0.5))
    assert msgspec.msgpack.decode(wire, type=SpinCommand) == SpinCommand(omega=1.0, duration=2.0)


def test_invalid_body_reports_the_path() -> None:
    wire = msgspec.msgpack.encode({"commands": [{"omega": "fast", "duration": 1.0}]})
    with pytest.raises(msgspec.ValidationError, match=r"\$\.commands\[0\]\.omega"):
        msgspec.msgpack.decode(wire, type=SpinPlan)


envelopes = st.builds(
    Envelope,
    uid=st.binary(min_size=16, max_size=16),
    ts=st.integers(min_value=0, max_value=2**63 - 1),
    source=st.text(max_size=20),
    seq=st.integers(min_value=0, max_value=2**63 - 1),
    type=st.sampled_from([m.TYPE for m in MESSAGES]),
    body=st.binary(max_size=64).map(lambda b: msgspec.Raw(msgspec.msgpack.encode(b))),
    cycle=st.none() | st.binary(min_size=16, max_size=16),
    cause=st.none() | st.binary(min_size=16, max_size=16),
    ctx=st.dictionaries(
        st.text(max_size=10), st.integers(min_value=0, max_value=2**63 - 1), max_size=4
    ),
)


@given(envelopes)
def test_envelope_round_trip(env: Envelope) -> None:
    back = msgspec.msgpack.decode(msgspec.msgpack.encode(env), type=Envelope)
    assert back == env


def test_the_model_reference_in_the_docs_is_current() -> None:
    """docs/toolkit.md's model reference is generated from the schema: fails when a
    field changed and `make schemas` was not run."""
    from rap_schemas.reference import BEGIN, END, reference

    doc = (EXPORT.parents[1] / "docs" / "toolkit.md").read_text(encoding="utf-8")
    assert BEGIN in doc, "docs/toolkit.md lost its model-reference markers"
    assert END in doc, "docs/toolkit.md lost its model-reference markers"
    section = doc.split(BEGIN, 1)[1].split(END, 1)[0]
    assert section.strip() == reference().strip(), "run `make schemas` and commit docs/toolkit.md"
    assert "### PortSpec" in section
    assert "`direction`" in section
