"""SimConfig, open_service (as the CLI uses it), the run summary, SimService's signature."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import anyio
import msgspec
import pytest
from blockbuster import BlockBuster, blockbuster_ctx
from rap_schemas import LaserScan, Twist, keys
from rap_sdk import Context, Node
from rap_sdk.testing import Harness
from sim_world.config import SimConfig, SimConfigError
from sim_world.service import SimService, open_service
from sim_world.sim import Simulation
from sim_world.world import WorldError, parse_world

pytestmark = pytest.mark.anyio

TINY = """
room: {width: 4.0, height: 2.0}
robots:
  - name: r
    start: {x: 0.5, y: 1.0, theta: 0.0}
    route: [{x: 1.5, y: 1.0}]
"""


@pytest.mark.parametrize(
    ("fields", "field", "words"),
    [
        ({"speed": 0.0}, "speed", "> 0"),
        ({"speed": math.nan}, "speed", "> 0"),
        ({"speed": 2e6}, "speed", "at most 1e+06"),
        ({"duration": -1.0}, "duration", "seconds of sim time > 0"),
        ({"duration": math.inf}, "duration", "seconds of sim time > 0"),
        ({"system": "a/b"}, "system", "invalid system 'a/b'"),
        ({"world": ""}, "world", "shipped world's name or a path"),
        ({"rerun": ""}, "rerun", ".rrd"),
        ({"sync_timeout": 0.0}, "sync_timeout", "> 0"),
    ],
)
def test_a_config_value_out_of_range_names_the_field(
    fields: dict[str, object], field: str, words: str
) -> None:
    with pytest.raises(SimConfigError) as exc:
        SimConfig(**fields)  # type: ignore[arg-type]
    assert exc.value.field == field
    assert words in str(exc.value)


def test_a_decoded_config_is_checked_and_refuses_unknown_fields() -> None:
    ok = msgspec.json.decode(b'{"world": "corridor", "lockstep": true}', type=SimConfig)
    assert ok.realtime_factor is None
    assert SimConfig(speed=3.0).realtime_factor == 3.0
    with pytest.raises(msgspec.ValidationError, match=r"speed -1\.0"):
        msgspec.json.decode(b'{"speed": -1}', type=SimConfig)
    with pytest.raises(msgspec.ValidationError, match="unknown field `sped`"):
        msgspec.json.decode(b'{"sped": 2}', type=SimConfig)


async def test_fabric_is_keyword_only_and_the_factor_is_checked() -> None:
    sim = Simulation(parse_world(TINY))
    async with Harness(system="s") as h:
        with pytest.raises(TypeError):
            SimService(sim, h.fabric, system="s")  # type: ignore[call-arg]
        with pytest.raises(ValueError, match="realtime_factor 0"):
            SimService(sim, fabric=h.fabric, system="s", realtime_factor=0.0)


async def test_open_service_runs_a_named_world_for_its_duration() -> None:
    config = SimConfig(world="corridor", system="s", lockstep=True, duration=2.0)
    async with Harness(system="s") as h, open_service(config, fabric=h.fabric) as service:
        await service.finished.wait()
        summary = service.summary()
        scans = h.of(keys.Kind.DATA, "tb1/scan")
    assert service.sim.world.room.width == 20.0  # the corridor
    assert summary.finished
    assert summary.scans_published == 10  # 2 s at 5 Hz
    assert len(scans) == 10
    for rec in scans:  # decoding checks every bound of the wire schema
        assert len(rec.decode(LaserScan).values()) == 360
    assert summary.clock == "lockstep"
    assert [r.name for r in summary.robots] == ["tb1"]


async def test_a_bad_world_or_recording_path_fails_on_entry(tmp_path: Path) -> None:
    async with Harness(system="s") as h:
        with pytest.raises(WorldError, match="the shipped worlds are"):
            async with open_service(SimConfig(world="nope", system="s"), fabric=h.fabric):
                pass
        bad = SimConfig(system="s", rerun=str(tmp_path / "no" / "x.rrd"))
        with pytest.raises(ValueError, match="cannot write the Rerun recording"):
            async with open_service(bad, fabric=h.fabric):
                pass
        with pytest.raises(ValueError, match=r"loop_nodes needs config\.lockstep"):
            async with open_service(SimConfig(system="s"), fabric=h.fabric, loop_nodes=[]):
                pass


async def test_the_summary_counts_collisions_and_the_route() -> None:
    world = parse_world(TINY + "  - name: w\n    start: {x: 3.5, y: 1.0}\n")
    async with Harness(system="s") as h:
        config = SimConfig(system="s", lockstep=True, duration=8.0)
        async with open_service(config, fabric=h.fabric, world=world) as service:
            service.sim.set_velocity("w", Twist(linear=0.31, angular=0.0), duration=8.0)
            await service.finished.wait()
            summary = service.summary()
    r, w = summary.robots
    assert (r.name, r.waypoints_reached, r.route_points, r.route_completed) == ("r", 1, 1, True)
    assert r.collisions == 0
    assert (w.route_points, w.route_completed) == (0, False)
    assert w.collisions >= 1  # drove into the east wall
    text = summary.render()
    assert "sim_world finished at 8 s of sim time (lockstep): 80 scans published" in text
    assert "r: 0 collisions, 1 of 1 waypoints reached, route completed" in text
    assert f"w: {w.collisions} collisions, no route" in text


async def test_in_lockstep_with_loop_nodes_each_scan_waits_for_its_cycle() -> None:
    seen: list[float] = []
    node = Node("watcher", stage="monitor")

    @node.on_data("r/scan")
    async def on_scan(ctx: Context, scan: LaserScan) -> None:
        await anyio.sleep(0.01)  # slower than the simulator: lockstep must wait
        seen.append(scan.stamp / 1e9)

    config = SimConfig(system="s", lockstep=True, duration=2.0)
    async with Harness(system="s") as h:
        await h.start(node)
        async with open_service(
            config, fabric=h.fabric, world=parse_world(TINY), loop_nodes=[node]
        ) as service:
            await service.finished.wait()
            assert service.sync is not None
            assert service.sync.timeouts == 0
    assert seen == pytest.approx([0.2 * (i + 1) for i in range(10)])


@pytest.fixture
def blockbuster() -> Iterator[BlockBuster]:
    with blockbuster_ctx() as bb:
        yield bb


async def test_open_service_makes_no_blocking_call_on_the_loop(
    tmp_path: Path, blockbuster: BlockBuster
) -> None:
    """The world file is read, and the recording opened and closed, off the event loop."""
    world = tmp_path / "w.yaml"
    await anyio.Path(world).write_text(TINY, encoding="utf-8")
    rrd = tmp_path / "w.rrd"
    config = SimConfig(world=str(world), system="s", lockstep=True, duration=1.0, rerun=str(rrd))
    async with Harness(system="s") as h, open_service(config, fabric=h.fabric) as service:
        await service.finished.wait()
    assert (await anyio.Path(rrd).stat()).st_size > 0
