from __future__ import annotations

import msgspec
import pytest
from rap_schemas import Envelope
from rap_sdk import Opener, RejectedSample, Sealer


class FixedClock:
    def __init__(self) -> None:
        self.now = 1_700_000_000_000_000_000

    def time_ns(self) -> int:
        self.now += 1000
        return self.now


def sealed(sealer: Sealer, key: str = "rap/s/data/x") -> bytes:
    payload, _ = sealer.seal(key, "rap.Empty/1", msgspec.msgpack.encode(None))
    return payload


def test_seal_stamps_uid_ts_and_per_key_seq() -> None:
    clock = FixedClock()
    s = Sealer("mon", clock)
    envs = [s.seal(k, "rap.Empty/1", b"\xc0")[1] for k in ("rap/a", "rap/a", "rap/b", "rap/a")]
    assert [e.seq for e in envs] == [0, 1, 0, 2]
    assert len({e.uid for e in envs}) == 4
    assert all(len(e.uid) == 16 and e.uid[6] >> 4 == 7 for e in envs)  # UUIDv7
    assert [e.ts for e in envs] == sorted(e.ts for e in envs)
    assert all(e.source == "mon" for e in envs)


def test_cycle_cause_and_ctx_are_carried() -> None:
    payload, _ = Sealer("p").seal(
        "rap/s/event/e", "rap.Empty/1", b"\xc0", cycle=b"c" * 16, cause=b"k" * 16, ctx={"mask": 7}
    )
    back = msgspec.msgpack.decode(payload, type=Envelope)
    assert (back.cycle, back.cause, back.ctx) == (b"c" * 16, b"k" * 16, {"mask": 7})


def test_duplicates_dropped_gaps_and_reordering_counted() -> None:
    s = Sealer("src", FixedClock())
    p = [sealed(s) for _ in range(6)]
    o = Opener(FixedClock())
    order = [0, 1, 1, 3, 2, 5, 3]  # dup of 1, 2 late, 4 never, dup of 3
    got = [o.open("rap/s/data/x", p[i]) for i in order]
    assert [e.seq if e else None for e in got] == [0, 1, None, 3, 2, 5, None]
    assert o.stats.duplicates == 2
    assert o.stats.reordered == 1
    assert o.stats.missing == 1  # seq 4


def test_a_restarted_sender_is_not_taken_for_duplicates() -> None:
    clock = FixedClock()
    first = Sealer("src", clock)
    o = Opener(clock)
    for _ in range(3):
        assert o.open("rap/s/data/x", sealed(first)) is not None
    again = Sealer("src", clock)  # same node id, new process: seq starts at 0
    assert o.open("rap/s/data/x", sealed(again)) is not None
    assert o.stats.restarts == 1
    assert o.stats.duplicates == 0


def test_sequences_are_tracked_per_key() -> None:
    clock = FixedClock()
    s = Sealer("src", clock)
    o = Opener(clock)
    for key in ("rap/a", "rap/b", "rap/a", "rap/b"):
        assert o.open(key, sealed(s, key)) is not None
    assert o.stats.missing == 0


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"\xc1", "undecodable envelope"),
        (b"\xff\x00garbage", "invalid envelope: Expected `object`"),
        (msgspec.msgpack.encode({"uid": b"x"}), "invalid envelope: Object missing required"),
        (
            msgspec.msgpack.encode(
                {"uid": b"1" * 16, "ts": "now", "source": "a", "seq": 0, "type": "t", "body": None}
            ),
            r"\$\.ts",
        ),
        (
            msgspec.msgpack.encode(
                {"uid": b"1", "ts": 1, "source": "a", "seq": 0, "type": "t", "body": None}
            ),
            "uid must be 16 bytes",
        ),
    ],
)
def test_bad_envelopes_are_rejected_with_a_reason(payload: bytes, reason: str) -> None:
    with pytest.raises(RejectedSample, match=reason):
        Opener().open("rap/s/data/x", payload)


def test_an_envelope_from_the_future_is_rejected_and_cannot_block_its_sender() -> None:
    clock = FixedClock()
    real = Sealer("monitor", clock)
    o = Opener(clock)
    assert o.open("rap/s/data/x", sealed(real)) is not None
    forged = msgspec.msgpack.encode(
        Envelope(
            uid=b"f" * 16,
            ts=clock.now + 10 * 365 * 86_400 * 10**9,  # ten years ahead
            source="monitor",
            seq=2**62,
            type="rap.Empty/1",
            body=msgspec.Raw(b"\x80"),
        )
    )
    with pytest.raises(RejectedSample, match="in the future"):
        o.open("rap/s/data/x", forged)
    assert o.stats.future == 1
    for _ in range(3):  # the real sender's next samples still arrive
        assert o.open("rap/s/data/x", sealed(real)) is not None


def test_a_very_old_sample_is_dropped_not_taken_for_a_restart() -> None:
    clock = FixedClock()
    s = Sealer("src", clock)
    p = [sealed(s) for _ in range(100)]
    o = Opener(clock)
    for payload in p:
        assert o.open("rap/s/data/x", payload) is not None
    assert o.open("rap/s/data/x", p[10]) is None  # a stale copy: older ts, far back
    assert o.open("rap/s/data/x", p[50]) is None  # and a replay within the window
    assert (o.stats.stale, o.stats.duplicates, o.stats.restarts) == (1, 1, 0)
    assert o.stats.missing == 0


def test_samples_from_before_a_late_join_do_not_make_missing_negative() -> None:
    clock = FixedClock()
    s = Sealer("src", clock)
    p = [sealed(s) for _ in range(6)]
    o = Opener(clock)
    assert o.open("rap/s/data/x", p[5]) is not None  # joined late, at seq 5
    assert o.open("rap/s/data/x", p[3]) is not None  # an earlier one arrives after
    assert o.open("rap/s/data/x", p[3]) is None
    assert (o.stats.missing, o.stats.reordered, o.stats.duplicates) == (0, 1, 1)


def test_a_message_sealed_in_one_pass_is_an_envelope_on_the_wire() -> None:
    from rap_schemas import SpinCommand, SpinPlan

    plan = SpinPlan(commands=[SpinCommand(omega=1.0, duration=0.5)], period=8.0)
    payload, sent = Sealer("planner", FixedClock()).seal_message(
        "rap/s/event/new-plan", plan, cycle=b"c" * 16, cause=b"k" * 16, ctx={"mask": 3}
    )
    env = msgspec.msgpack.decode(payload, type=Envelope)
    assert (env.uid, env.ts, env.source, env.seq, env.type) == (
        sent.uid,
        sent.ts,
        "planner",
        0,
        SpinPlan.TYPE,
    )
    assert (env.cycle, env.cause, env.ctx) == (b"c" * 16, b"k" * 16, {"mask": 3})
    assert msgspec.msgpack.decode(env.body, type=SpinPlan) == plan
    empty, _ = Sealer("x").seal_message("rap/s/event/e", None)
    back = msgspec.msgpack.decode(empty, type=Envelope)
    assert (back.type, msgspec.msgpack.decode(back.body)) == ("rap.Empty/1", {})
