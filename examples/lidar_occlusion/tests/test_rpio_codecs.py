"""The RPIO chain's JSON shapes <-> RAP's lidar messages (lidar_occlusion.rpio), as an
rpclpy node writes and reads them (Python's json: ``Infinity`` for a beam with no
return). The stages themselves, with the real RPIO nodes: tests/test_rpio_stages.py."""

from __future__ import annotations

import json
import math
import re
from typing import Any

import pytest
from lidar_occlusion.rpio import (
    mask_from_rpio,
    mask_to_rpio,
    plan_from_rpio,
    plan_to_rpio,
    scan_from_rpio,
    scan_to_rpio,
)
from lidar_occlusion.scans import occluded_scan
from rap_bridges.rpio import dumps, loads
from rap_schemas import LidarMask, SpinCommand, SpinPlan, pack_flags

SCAN = occluded_scan(-0.4, 0.8, stamp=1_700_000_000_123_456_789)


def test_a_scan_goes_to_rpio_as_json_an_rpclpy_node_reads_and_comes_back_the_same() -> None:
    text = dumps(scan_to_rpio(SCAN, 7)).decode()
    assert "Infinity" in text  # as Python's json.dumps writes it; json.loads reads it
    read = json.loads(text)  # what rpclpy's read_knowledge hands the RPIO node
    assert read["header"]["seq"] == 7
    assert read["header"]["t_send_ns"] == SCAN.stamp
    assert read["header"]["stamp"] == {"secs": 1_700_000_000, "nsecs": 123_456_789}
    assert sum(math.isinf(r) for r in read["ranges"]) == sum(math.isinf(r) for r in SCAN.values())
    assert scan_from_rpio(loads(text.encode())) == SCAN


def test_a_mask_from_rpio_takes_its_angles_from_the_scan_and_must_fit_it() -> None:
    flags = [1 if math.isinf(r) else 0 for r in SCAN.values()]
    mask = mask_from_rpio({"seq": 1, "t_send_ns": 0, "occluded": flags}, scan=SCAN)
    assert mask == LidarMask(
        angle_min=SCAN.angle_min, angle_increment=SCAN.angle_increment, occluded=pack_flags(flags)
    )
    assert mask_from_rpio(loads(dumps(mask_to_rpio(mask, 3, 0)))) == mask  # angles carried
    with pytest.raises(ValueError, match="2 flags for a scan of 360 beams"):
        mask_from_rpio({"occluded": [0, 1]}, scan=SCAN)
    with pytest.raises(ValueError, match="no angle_min"):
        mask_from_rpio({"occluded": [0, 1]})


def test_a_plan_goes_both_ways() -> None:
    plan = SpinPlan(commands=[SpinCommand(omega=1.0, duration=0.5)], period=8.0)
    sent = plan_to_rpio(plan, 4, 99)
    assert sent == {
        "commands": [{"omega": 1.0, "duration": 0.5}],
        "period": 8.0,
        "seq": 4,
        "t_send_ns": 99,
    }
    assert plan_from_rpio(loads(dumps(sent))) == plan
    assert plan_from_rpio({"commands": [{"omega": 1, "duration": 2}]}).period == 8.0


S = scan_to_rpio(SCAN, 1)
ANGLES = {"angle_min": 0, "angle_increment": 1}
BAD: dict[str, tuple[Any, Any, str]] = {
    "scan with a NaN range": (scan_from_rpio, {**S, "ranges": [math.nan]}, "is nan"),
    "scan with a negative range": (scan_from_rpio, {**S, "ranges": [-1.0]}, "is -1.0"),
    "scan without header": (scan_from_rpio, {"ranges": []}, "required field `header`"),
    "scan range as text": (scan_from_rpio, {**S, "ranges": ["1"]}, "got `str`"),
    "scan angle out of range": (scan_from_rpio, {**S, "angle_min": 1e9}, "$.angle_min"),
    "scan not an object": (scan_from_rpio, "laser", "Expected `object`"),
    "mask flag 2": (mask_from_rpio, {"occluded": [2], **ANGLES}, "<= 1"),
    "mask flag true": (mask_from_rpio, {"occluded": [True], **ANGLES}, "got `bool`"),
    "plan too fast": (plan_from_rpio, {"commands": [{"omega": 1e6, "duration": 1}]}, "<= 1000.0"),
    "plan going back in time": (
        plan_from_rpio,
        {"commands": [{"omega": 1, "duration": -1}]},
        ">= 0",
    ),
    "plan period 0": (plan_from_rpio, {"commands": [], "period": 0}, "> 0"),
    "plan commands missing": (plan_from_rpio, {"period": 8}, "required field `commands`"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_what_is_not_a_valid_rap_message_is_refused_with_the_reason(case: str) -> None:
    decode, value, reason = BAD[case]
    with pytest.raises(ValueError, match=re.escape(reason)):
        decode(value)


def test_rpio_values_are_parsed_as_rpclpy_does_or_refused() -> None:
    assert loads(b'{"a": Infinity}') == {"a": math.inf}
    assert loads(b"plain text") == "plain text"  # rpclpy hands non-JSON over as a string
    for raw, why in (
        (b"\x80\x04\x95\x10", "pickled"),
        (b"\xff\xfe", "not UTF-8"),
        (b"[" * 5000, "nests too deeply"),
        (b"1" * 50, "over the limit of 10"),
    ):
        with pytest.raises(ValueError, match=why):
            loads(raw, max_bytes=10 if why.startswith("over") else 1 << 20)
