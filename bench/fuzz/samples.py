"""Valid messages of each wire type the loop reads: what a mutation starts from.

``valid_body(type_name, rng, ...)`` is a valid message of that wire type (as plain
msgpack data: dicts, lists, bytes, numbers), varied by ``rng``. Knowledge requests
(``KbRequest``) and trust spec updates have their own makers. A wire type with no maker
here gets an empty map (reported: the target then only tests the type check).
"""

from __future__ import annotations

import hashlib
import math
import random
import time
from collections.abc import Callable
from typing import Any

import msgspec
from lidar_occlusion.scans import occluded_scan
from rap_schemas import (
    Empty,
    KbGet,
    KbHistory,
    KbList,
    KbPut,
    KbRecord,
    KnowledgeAccess,
    LaserScan,
    LidarMask,
    ModelGet,
    ModelList,
    ModelPin,
    ModelPut,
    PlanProposal,
    SpinCommand,
    SpinPlan,
    Stage,
    StageTrace,
    TrustOutput,
    TrustSpecUpdate,
    Verdict,
    pack_flags,
)
from rap_sdk.knowledge import HybridClock

__all__ = ["KNOWN_TYPES", "kb_request", "plain", "spec_update", "valid_body"]

_encode = msgspec.msgpack.Encoder().encode
_decode = msgspec.msgpack.decode
WRITER = "fuzzer"
_clock = HybridClock(WRITER)


def plain(msg: Any) -> Any:
    """A message as plain msgpack data (bytes stay bytes)."""
    return _decode(_encode(msg))


def _uid(rng: random.Random) -> bytes:
    return rng.randbytes(16)


def _scan(rng: random.Random) -> LaserScan:
    if rng.random() < 0.3:
        return occluded_scan(None)
    return occluded_scan(rng.uniform(-math.pi, math.pi), rng.uniform(0.1, 1.5))


def _mask(rng: random.Random) -> LidarMask:
    n = 360
    start, width = rng.randrange(n), rng.randrange(0, 90)
    occ = pack_flags([(i - start) % n < width for i in range(n)])
    return LidarMask(angle_min=-math.pi, angle_increment=2 * math.pi / n, occluded=occ)


def _spin(rng: random.Random) -> SpinPlan:
    cmds = [
        SpinCommand(omega=rng.choice([-1.0, 1.0]) * 0.5, duration=rng.uniform(0.1, 3.0))
        for _ in range(rng.randrange(0, 4))
    ]
    return SpinPlan(commands=cmds, period=8.0)


def _proposal(rng: random.Random) -> PlanProposal[SpinPlan]:
    return PlanProposal(
        plan_uid=_uid(rng),
        plan_type=SpinPlan.TYPE,
        plan=_spin(rng),
        proposer=rng.choice(["planner", WRITER]),
        created=time.time_ns(),
    )


def _verdict(rng: random.Random) -> Verdict[SpinPlan]:
    approved = rng.random() < 0.5
    prop = _proposal(rng)
    return Verdict(
        plan_uid=prop.plan_uid,
        approved=approved,
        legitimator=rng.choice(["legitimate", WRITER]),
        ts=time.time_ns(),
        reason="" if approved else "fuzz",
        proposal=prop if approved else None,
    )


def _trace(rng: random.Random, nodes: list[str]) -> StageTrace:
    return StageTrace(
        node=rng.choice(nodes),
        handler="fuzz",
        phase=rng.choice(["start", "end"]),
        trigger=_uid(rng),
        trigger_key="rap/demo/event/new-data",
        cycle=_uid(rng),
        ts=time.time_ns(),
        stage=rng.choice([*Stage, None]),
        sent=[],
    )


def _access(rng: random.Random, nodes: list[str], kb_keys: list[str]) -> KnowledgeAccess:
    return KnowledgeAccess(
        node=rng.choice(nodes),
        op=rng.choice(["read", "write", "delete"]),
        key=rng.choice(kb_keys) if kb_keys else "fuzz",
        version=_clock.next(),
        ts=time.time_ns(),
        cycle=_uid(rng) if rng.random() < 0.8 else None,
    )


def _trust_output(rng: random.Random) -> TrustOutput:
    return TrustOutput(
        stream="fuzz", tick=rng.randrange(1 << 20), ts=time.time_ns(), value=rng.random() < 0.5
    )


def kb_record(key: str, value: bytes, rng: random.Random) -> KbRecord:
    """A write-stream record of ``key`` holding ``value`` (msgpack), stamped now."""
    deleted = rng.random() < 0.05
    return KbRecord(
        key=key,
        version=_clock.next(),
        ts=time.time_ns(),
        writer=WRITER,
        value=msgspec.Raw(b"\xc0" if deleted else value),
        deleted=deleted,
    )


def valid_body(
    type_name: str,
    rng: random.Random,
    *,
    nodes: list[str],
    kb_keys: list[str],
    kb_key: str = "",
    kb_value: bytes = b"\xc0",
) -> Any:
    """A valid message of wire type ``type_name`` as plain data (None: no maker)."""
    makers: dict[str, Callable[[], Any]] = {
        Empty.TYPE: Empty,
        LaserScan.TYPE: lambda: _scan(rng),
        LidarMask.TYPE: lambda: _mask(rng),
        SpinPlan.TYPE: lambda: _spin(rng),
        PlanProposal.TYPE: lambda: _proposal(rng),
        Verdict.TYPE: lambda: _verdict(rng),
        StageTrace.TYPE: lambda: _trace(rng, nodes),
        KnowledgeAccess.TYPE: lambda: _access(rng, nodes, kb_keys),
        TrustOutput.TYPE: lambda: _trust_output(rng),
        KbRecord.TYPE: lambda: kb_record(kb_key, kb_value, rng),
    }
    maker = makers.get(type_name)
    return None if maker is None else plain(maker())


KNOWN_TYPES = frozenset(
    {
        Empty.TYPE,
        LaserScan.TYPE,
        LidarMask.TYPE,
        SpinPlan.TYPE,
        PlanProposal.TYPE,
        Verdict.TYPE,
        StageTrace.TYPE,
        KnowledgeAccess.TYPE,
        TrustOutput.TYPE,
        KbRecord.TYPE,
    }
)


def kb_request(rng: random.Random, key: str, value: bytes) -> Any:
    """A valid knowledge request about ``key`` (one of each operation, by ``rng``), as
    plain data. Model requests name a model under the fuzzer's own name."""
    model = "fuzz"
    now = time.time_ns()
    data = rng.randbytes(rng.randrange(0, 64))
    choices: list[Callable[[], Any]] = [
        lambda: KbGet(key=key, min_version=rng.choice([0, _clock.next()])),
        lambda: KbHistory(
            key=key, since=rng.choice([None, now - 10**9]), until=None, limit=rng.randrange(1, 50)
        ),
        lambda: KbList(pattern=rng.choice(["**", "*", key])),
        lambda: KbPut(record=kb_record(key, value, rng), expect=rng.choice([None, 0, 1])),
        lambda: ModelGet(name=model, version=rng.choice([None, 1]), with_data=rng.random() < 0.5),
        lambda: ModelList(name=model),
        lambda: ModelPin(name=model, version=rng.choice([None, 1]), rollback=rng.random() < 0.3),
        lambda: ModelPut(name=model, data=data, sha256=hashlib.sha256(data).hexdigest()),
    ]
    return plain(rng.choice(choices)())


def _depth(rng: random.Random) -> int:
    """Nesting of a spec text: 100..10 000, one in twenty up to 100 000 (the traffic of
    100 000 swap requests stays near 1 GB)."""
    return int(10 ** rng.uniform(2, 5 if rng.random() < 0.05 else 4))


def spec_update(rng: random.Random, running: str) -> tuple[Any, bool]:
    """A spec update as plain data, and whether its spec text is the running one (then
    only envelope-level mutations may touch it: a mutated valid spec would replace the
    checker's spec). Else the text is not a valid spec: garbage, deeply nested
    expressions, a huge text."""
    r = rng.random()
    if r < 0.02:
        return plain(TrustSpecUpdate(spec=running, path="<fuzz>")), True
    if r < 0.10:
        depth = _depth(rng)
        text = "in a: Int\nout b: Int\nb = " + "(" * depth + "a" + ")" * depth + "\n"
    elif r < 0.14:
        text = "in a: Int\nout b: Int\nb = " + "-" * _depth(rng) + "a\n"
    elif r < 0.18:
        text = "out b: Int\nb = " + " + ".join(["1"] * _depth(rng)) + "\n"
    elif r < 0.35:
        text = running[: rng.randrange(len(running))] + rng.choice(["(", "if", "@", "\u2603"])
    else:
        text = "".join(chr(rng.randrange(32, 0x2FF)) for _ in range(rng.randrange(1, 400)))
    return plain(TrustSpecUpdate(spec=text, path="<fuzz>")), False
