"""Bad input never crashes a node: every sample is delivered, rejected or dropped as a
duplicate, and the node goes on handling good samples."""

from __future__ import annotations

import math
from typing import Any

import anyio
import msgspec
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rap_schemas import MESSAGES, Envelope, LaserScan, keys, pack_ranges
from rap_sdk import Context, MemoryFabric, Node, NodeRuntime
from rap_sdk.fabric import Sample

KEY = keys.data("t", "scan")

msgpack_values: st.SearchStrategy[Any] = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=8)
    | st.binary(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4)
    ),
    max_leaves=12,
)

ragged = st.binary(min_size=1, max_size=3)
"""Appended to packed ranges: a length that is not a multiple of 4 (a float32 beam)."""

good_scans = st.fixed_dictionaries(  # scan-shaped, in and out of the schema's bounds
    {
        "stamp": st.integers(0, 2**62),
        "frame_id": st.text(max_size=8),
        "angle_min": st.floats(),
        "angle_increment": st.floats(),
        "range_min": st.floats(),
        "range_max": st.floats(),
        "ranges": st.one_of(  # packed float32, valid or not (NaN, negative), or any bytes
            st.lists(st.floats(-1, math.inf, width=32) | st.just(math.nan), max_size=8).map(
                pack_ranges
            ),
            st.binary(max_size=33),
        ),
    }
)

bodies = (
    good_scans.map(msgspec.msgpack.encode)
    | msgpack_values.map(msgspec.msgpack.encode)
    | st.binary(max_size=32)
)

envelopes = st.builds(
    lambda uid, ts, source, seq, type_, body: msgspec.msgpack.encode(
        Envelope(uid=uid, ts=ts, source=source, seq=seq, type=type_, body=msgspec.Raw(body))
    ),
    uid=st.binary(min_size=15, max_size=17),
    ts=st.integers(0, 2**63 - 1),
    source=st.sampled_from(["a", "b"]),
    seq=st.integers(0, 5),
    type_=st.sampled_from([LaserScan.TYPE, *(m.TYPE for m in MESSAGES[:3]), "junk"]),
    body=bodies,
)


def deep(depth: int) -> bytes:
    """msgpack nested ``depth`` arrays deep (about 1 KB killed a node at depth ~1000)."""
    return b"\x91" * depth + b"\xc0"


hostile_bodies = st.one_of(
    st.integers(1, 5000).map(deep),
    st.integers(1, 5000).map(lambda d: b"\x81\xa6ranges" + deep(d)),  # where bytes go
    st.integers(1, 5000).map(lambda d: b"\x81\xa1z" + deep(d)),  # an unknown field
    st.sampled_from([b"\xdd\xff\xff\xff\xff", b"\xdf\xff\xff\xff\xff", b"\xc6\xff\xff\xff\xff"]),
    st.fixed_dictionaries(  # NaN, inf, -inf and wrong types where a scan has numbers
        {
            "stamp": st.integers(0, 2**62) | st.text(max_size=3),
            "frame_id": st.text(max_size=8),
            "angle_min": st.sampled_from([math.nan, math.inf, -math.inf, 0.0]),
            "angle_increment": st.floats(),
            "range_min": st.floats(),
            "range_max": st.floats(),
            "ranges": st.one_of(
                st.lists(st.sampled_from([math.nan, -math.inf, -1.0, 1.0, math.inf])).map(
                    pack_ranges
                ),
                st.tuples(st.lists(st.just(1.0)).map(pack_ranges), ragged).map(
                    lambda parts: parts[0] + parts[1]
                ),
                st.lists(st.floats()),  # a list, as rap.LaserScan/1 sent it
            ),
        }
    ).map(msgspec.msgpack.encode),
)
hostile = st.builds(
    lambda ts, seq, body: msgspec.msgpack.encode(
        Envelope(
            uid=b"u" * 16, ts=ts, source="x", seq=seq, type=LaserScan.TYPE, body=msgspec.Raw(body)
        )
    ),
    ts=st.integers(0, 2**63 - 1),
    seq=st.integers(0, 2**63 - 1),
    body=hostile_bodies,
)
truncated = (envelopes | hostile).flatmap(
    lambda p: st.integers(0, max(0, len(p) - 1)).map(lambda n: p[:n])
)
payloads = (
    st.binary(max_size=64)
    | msgpack_values.map(msgspec.msgpack.encode)
    | envelopes
    | hostile
    | truncated
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(payloads, min_size=1, max_size=25))
def test_any_payload_is_delivered_or_rejected_never_a_crash(batch: list[bytes]) -> None:
    anyio.run(_feed, batch)


async def _feed(batch: list[bytes]) -> None:
    node = Node("n", stage="monitor")
    delivered: list[LaserScan] = []

    @node.on_data("scan")
    async def on_scan(ctx: Context, scan: LaserScan) -> None:
        delivered.append(scan)

    async with MemoryFabric() as fabric:
        rt = NodeRuntime(node, fabric=fabric, system="t")
        for payload in batch:
            await rt.handle(node.routes[0], Sample(KEY, payload))
        s, dup = rt.stats, rt.sender_stats.duplicates
        assert s.received == len(batch)
        assert s.handled + s.failed + s.rejected + dup == len(batch)
        assert s.failed == 0
        assert len(delivered) == s.handled
        # and the node still works
        good = msgspec.msgpack.encode(
            LaserScan(
                stamp=1,
                frame_id="f",
                angle_min=0.0,
                angle_increment=1.0,
                range_min=0.0,
                range_max=1.0,
                ranges=b"",
            )
        )
        payload, _ = rt.sealer.seal(KEY, LaserScan.TYPE, good)
        await rt.handle(node.routes[0], Sample(KEY, payload))
        assert delivered[-1].stamp == 1
