"""Whatever a possible world makes the simulator publish, the wire schema accepts:
ranges >= 0 (inf allowed, never NaN), range_min <= range_max, bounded angles, speeds
and times. Decoding a message checks every constraint of its type."""

from __future__ import annotations

import math

import msgspec
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from rap_schemas import SimTime
from sim_world.config import MAX_REALTIME_FACTOR
from sim_world.sim import Simulation
from sim_world.world import MAX_SPEED, WorldSpec, check_world

_enc = msgspec.msgpack.Encoder()


def roundtrip(msg: msgspec.Struct) -> None:
    msgspec.msgpack.decode(_enc.encode(msg), type=type(msg))


def world(lidar: dict[str, float | int], robot: dict[str, float]) -> WorldSpec:
    spec = {
        "seed": 3,
        "room": {"width": 4.0, "height": 3.0},
        "obstacles": [{"kind": "circle", "x": 2.5, "y": 1.5, "r": 0.3}],
        "robots": [
            {
                "name": "r",
                "start": {"x": 1.0, "y": 1.0, "theta": 0.3},
                "route": [{"x": 3.5, "y": 2.5}, {"x": 0.5, "y": 2.5}],
                "loop_route": True,
                **robot,
            }
        ],
        "lidar": lidar,
        "occlusions": [{"robot": "r", "mode": "random", "period": 0.5}],
        "physics_hz": 50.0,
    }
    return check_world(msgspec.convert(spec, WorldSpec))


def check_run(w: WorldSpec, seconds: float) -> int:
    sim = Simulation(w)
    lidar = w.lidar
    n = 0
    for ev in sim.run(seconds):
        roundtrip(ev.scan)
        roundtrip(sim.odometry(ev.robot))
        r = np.asarray(ev.scan.values())  # float32: compare with float32 bounds
        kept = r[np.isfinite(r)]
        assert not np.isnan(r).any()
        lo, hi = np.float32(lidar.range_min), np.float32(lidar.range_max)
        assert ((kept >= lo) & (kept <= hi)).all()
        n += 1
    roundtrip(SimTime(t=round(sim.t * 1e9), realtime_factor=MAX_REALTIME_FACTOR))
    return n


def test_a_world_at_the_limits_publishes_only_valid_messages() -> None:
    w = world(
        {
            "beams": 720,
            "angle_min": 2 * math.pi,
            "range_min": 0.0,
            "range_max": 2.0,
            "rate_hz": 50.0,  # a scan every physics step
            "noise_std": 1.0,  # pushes returns below 0 and past range_max
        },
        {"max_linear": MAX_SPEED, "max_angular": MAX_SPEED},
    )
    assert check_run(w, 3.0) == 150


@settings(max_examples=25, deadline=None)
@given(
    beams=st.integers(1, 720),
    angle_min=st.floats(-2 * math.pi, 2 * math.pi),
    range_min=st.floats(0.0, 3.0),
    span=st.floats(1e-3, 20.0),
    rate_hz=st.floats(0.5, 50.0),
    noise_std=st.floats(0.0, 2.0),
    max_linear=st.floats(0.01, 3.0),
)
def test_any_possible_lidar_publishes_only_valid_messages(
    beams: int,
    angle_min: float,
    range_min: float,
    span: float,
    rate_hz: float,
    noise_std: float,
    max_linear: float,
) -> None:
    lidar = {
        "beams": beams,
        "angle_min": angle_min,
        "range_min": range_min,
        "range_max": range_min + span,
        "rate_hz": rate_hz,
        "noise_std": noise_std,
    }
    check_run(world(lidar, {"max_linear": max_linear}), 2.0)
