"""rap.LaserScan/2 and rap.LidarMask/2 carry their per-beam arrays packed: float32
little-endian ranges, one byte per flag. Round trips, float32 rounding, what is refused
(with the beam that is wrong), the bounds, the readers, and how JSON shows them."""

from __future__ import annotations

import base64
import json
import math
import struct
import sys
from typing import Any

import msgspec
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from rap_schemas import LaserScan, LidarMask, pack_flags, pack_ranges
from rap_schemas.export import render
from rap_schemas.limits import DecodeRejected, SafeDecoder

BEAMS = 100_000
little_endian_only = pytest.mark.skipif(
    sys.byteorder != "little", reason="values() copies on a big-endian host"
)


def scan(ranges: bytes) -> LaserScan:
    return LaserScan(
        stamp=1,
        frame_id="base_link",
        angle_min=-math.pi,
        angle_increment=math.radians(1),
        range_min=0.1,
        range_max=12.0,
        ranges=ranges,
    )


def mask(occluded: bytes) -> LidarMask:
    return LidarMask(angle_min=-math.pi, angle_increment=math.radians(1), occluded=occluded)


def scan_body(ranges: Any) -> bytes:
    """A scan's msgpack body with ``ranges`` as given (not checked on the way)."""
    raw = msgspec.to_builtins(scan(b""), builtin_types=(bytes,))
    raw["ranges"] = ranges
    return msgspec.msgpack.encode(raw)


def mask_body(occluded: Any) -> bytes:
    raw = msgspec.to_builtins(mask(b""), builtin_types=(bytes,))
    raw["occluded"] = occluded
    return msgspec.msgpack.encode(raw)


float32_ranges = st.lists(st.floats(0, math.inf, width=32), max_size=64)


# -- round trips ---------------------------------------------------------------------------
@given(float32_ranges)
def test_a_scan_round_trips_through_msgpack_and_json(values: list[float]) -> None:
    s = scan(pack_ranges(values))
    assert msgspec.msgpack.decode(msgspec.msgpack.encode(s), type=LaserScan) == s
    assert msgspec.json.decode(msgspec.json.encode(s), type=LaserScan) == s
    assert list(s.values()) == values  # float32-representable: exact
    assert s.beams == len(values)


@given(st.lists(st.booleans(), max_size=64))
def test_a_mask_round_trips_through_msgpack_and_json(flags: list[bool]) -> None:
    m = mask(pack_flags(flags))
    assert msgspec.msgpack.decode(msgspec.msgpack.encode(m), type=LidarMask) == m
    assert msgspec.json.decode(msgspec.json.encode(m), type=LidarMask) == m
    assert list(m.flags()) == flags
    assert m.beams == len(flags)


def test_ranges_are_rounded_to_float32_once_at_packing() -> None:
    packed = pack_ranges([0.1, 1 / 3, math.inf])
    assert packed == struct.pack("<3f", 0.1, 1 / 3, math.inf)
    got = list(scan(packed).values())
    assert got[0] != 0.1
    assert got == [float(np.float32(0.1)), float(np.float32(1 / 3)), math.inf]
    # a numpy array (float64 here) packs to the same bytes as the list
    assert pack_ranges(np.array([0.1, 1 / 3, np.inf])) == packed
    assert pack_ranges(np.array([0.1, 1 / 3, np.inf], dtype=np.float32)) == packed
    assert pack_ranges([]) == b""


def test_flags_pack_from_a_list_or_a_numpy_bool_array() -> None:
    assert pack_flags([True, False, True]) == b"\x01\x00\x01"
    assert pack_flags(np.array([True, False, True])) == b"\x01\x00\x01"
    assert pack_flags([]) == b""


# -- refusals ------------------------------------------------------------------------------
BAD_RANGES = [
    pytest.param([1.0, 2.0, math.nan], r"ranges\[2\] is nan", id="nan"),
    pytest.param([1.0, -1.0], r"ranges\[1\] is -1\.0", id="negative"),
    pytest.param([-math.inf, 1.0], r"ranges\[0\] is -inf", id="-inf"),
]


@pytest.mark.parametrize(("values", "reason"), BAD_RANGES)
def test_a_bad_range_is_refused_naming_its_beam(values: list[float], reason: str) -> None:
    packed = pack_ranges(values)
    with pytest.raises(ValueError, match=reason):
        scan(packed)
    with pytest.raises(msgspec.ValidationError, match=reason):
        msgspec.msgpack.decode(scan_body(packed), type=LaserScan)
    with pytest.raises(DecodeRejected, match=reason):
        SafeDecoder(LaserScan).decode(scan_body(packed))
    raw = msgspec.json.encode(msgspec.to_builtins(msgspec.msgpack.decode(scan_body(packed))))
    with pytest.raises(msgspec.ValidationError, match=reason):
        msgspec.json.decode(raw, type=LaserScan)


def test_a_nan_planted_in_the_packed_bytes_is_refused() -> None:
    packed = bytearray(pack_ranges([3.0] * 20))
    struct.pack_into("<f", packed, 4 * 10, math.nan)
    with pytest.raises(DecodeRejected, match=r"ranges\[10\] is nan"):
        SafeDecoder(LaserScan).decode(scan_body(bytes(packed)))


@pytest.mark.parametrize("size", [1, 2, 3, 5, 7])
def test_ranges_not_a_whole_number_of_float32_are_refused(size: int) -> None:
    reason = rf"ranges holds {size} bytes, not a whole number of float32 beams"
    with pytest.raises(ValueError, match=reason):
        scan(b"\x00" * size)
    with pytest.raises(DecodeRejected, match=reason):
        SafeDecoder(LaserScan).decode(scan_body(b"\x00" * size))


def test_a_flag_byte_above_one_is_refused_naming_its_beam() -> None:
    reason = r"occluded\[2\] is byte 2; a packed flag is 0 or 1"
    with pytest.raises(ValueError, match=reason):
        mask(b"\x00\x01\x02\x01")
    with pytest.raises(DecodeRejected, match=reason):
        SafeDecoder(LidarMask).decode(mask_body(b"\x00\x01\x02\x01"))
    with pytest.raises(DecodeRejected, match=r"occluded\[0\] is byte 255"):
        SafeDecoder(LidarMask).decode(mask_body(b"\xff"))


def test_a_list_body_as_version_1_sent_it_is_refused() -> None:
    with pytest.raises(DecodeRejected, match=r"Expected `bytes`, got `array` - at `\$\.ranges`"):
        SafeDecoder(LaserScan).decode(scan_body([1.0, math.inf]))
    with pytest.raises(DecodeRejected, match=r"Expected `bytes`, got `array` - at `\$\.occluded`"):
        SafeDecoder(LidarMask).decode(mask_body([True, False]))


def test_beam_counts_are_bounded() -> None:
    most = SafeDecoder(LaserScan).decode(scan_body(pack_ranges(np.ones(BEAMS))))
    assert most.beams == BEAMS
    with pytest.raises(DecodeRejected, match=r"length <= 400000 - at `\$\.ranges`"):
        SafeDecoder(LaserScan).decode(scan_body(pack_ranges(np.ones(BEAMS + 1))))
    assert SafeDecoder(LidarMask).decode(mask_body(bytes(BEAMS))).beams == BEAMS
    with pytest.raises(DecodeRejected, match=r"length <= 100000 - at `\$\.occluded`"):
        SafeDecoder(LidarMask).decode(mask_body(bytes(BEAMS + 1)))


# -- readers -------------------------------------------------------------------------------
def test_values_reads_the_ranges_as_floats() -> None:
    s = scan(pack_ranges([1.5, math.inf, 0.25]))
    v = s.values()
    assert (len(v), v[0], v[1], v[-1]) == (3, 1.5, math.inf, 0.25)
    assert [type(x) for x in v] == [float, float, float]
    assert s.beams == 3
    assert v.readonly
    array = np.asarray(v)
    assert array.dtype == np.float32
    assert array.tolist() == [1.5, math.inf, 0.25]
    assert scan(b"").beams == 0
    assert list(scan(b"").values()) == []


@little_endian_only
def test_numpy_reads_the_packed_ranges_in_place() -> None:
    s = scan(pack_ranges(np.linspace(0.0, 10.0, 360)))
    array = np.asarray(s.values())
    assert np.shares_memory(array, np.frombuffer(s.ranges, dtype=np.uint8))
    assert not array.flags.writeable


def test_flags_reads_the_mask_as_bools() -> None:
    m = mask(pack_flags([False, True, True]))
    f = m.flags()
    assert (len(f), f[0], f[1]) == (3, False, True)
    assert list(f) == [False, True, True]
    assert m.beams == 3
    array = np.asarray(f)
    assert array.dtype == np.bool_
    assert np.count_nonzero(array) == 2
    assert np.shares_memory(array, np.frombuffer(m.occluded, dtype=np.uint8))


# -- JSON ----------------------------------------------------------------------------------
def test_json_shows_the_packed_arrays_as_base64() -> None:
    s = scan(pack_ranges([1.0, math.inf]))
    as_json = json.loads(msgspec.json.encode(s))
    assert as_json["ranges"] == base64.b64encode(s.ranges).decode()
    assert base64.b64decode(as_json["ranges"]) == struct.pack("<2f", 1.0, math.inf)
    m = mask(pack_flags([True, False, True]))
    assert json.loads(msgspec.json.encode(m))["occluded"] == base64.b64encode(b"\1\0\1").decode()


@pytest.mark.parametrize(
    ("file", "message", "field", "media_type", "max_bytes", "words"),
    [
        (
            "rap.LaserScan.v2.schema.json",
            "LaserScan",
            "ranges",
            "application/x.rap.float32le",
            4 * BEAMS,
            "packed float32, little-endian, 4 bytes per beam",
        ),
        (
            "rap.LidarMask.v2.schema.json",
            "LidarMask",
            "occluded",
            "application/x.rap.bool8",
            BEAMS,
            "packed flags, 1 byte per beam: 0 (false) or 1 (true)",
        ),
    ],
)
def test_the_exported_json_schema_describes_the_packed_field(
    file: str, message: str, field: str, media_type: str, max_bytes: int, words: str
) -> None:
    schema = json.loads(render()[file])
    prop = schema["$defs"][message]["properties"][field]
    assert prop["type"] == "string"
    assert prop["contentEncoding"] == "base64"
    assert prop["contentMediaType"] == media_type
    assert words in prop["description"]
    assert prop["maxLength"] == math.ceil(max_bytes / 3) * 4  # base64 of max_bytes
    assert field in schema["$defs"][message]["required"]
