"""Impossible worlds are refused with file:line:col and a fix; shipped worlds by name."""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import numpy as np
import pytest
from sim_world.occlusion import occlusion_mask
from sim_world.sim import Simulation
from sim_world.world import (
    WorldError,
    WorldSpec,
    check_world,
    default_world_path,
    find_world,
    load_world,
    parse_world,
    shipped_worlds,
)

ROOM = "room: {width: 4.0, height: 3.0}\n"
ROBOT = "robots:\n  - name: r\n"  # the start follows, on line 4
OK = ROOM + ROBOT + "    start: {x: 1.0, y: 1.0}\n"  # 4 lines


@pytest.mark.parametrize(
    ("text", "where", "words"),
    [
        pytest.param(
            OK + "lidar: {range_min: 5.0, range_max: 2.0}\n",
            "w.yaml:5:20:",
            ["range_min 5 is not below range_max 2", "make range_min smaller"],
            id="range_min-above-range_max",
        ),
        pytest.param(
            OK + "lidar: {range_min: 2.0, range_max: 2.0}\n",
            "w.yaml:5:20:",
            ["not below range_max"],
            id="range_min-equal-range_max",
        ),
        pytest.param(
            ROOM + ROBOT + "    start: {x: .nan, y: 1.0}\n",
            "w.yaml:4:16:",
            [".nan at `$.robots[0].start.x` is not a finite number", "write a finite number"],
            id="nan",
        ),
        pytest.param(
            "room: {width: .inf}\n" + ROBOT + "    start: {x: 1.0, y: 1.0}\n",
            "w.yaml:1:15:",
            [".inf at `$.room.width` is not a finite number"],
            id="inf",
        ),
        pytest.param(
            OK + "occlusions: [{robot: r, mode: global, t_end: .inf}]\n",
            "w.yaml:5:46:",
            ["not a finite number", "leave t_end out"],
            id="inf-t_end",
        ),
        pytest.param(
            OK + "lidar: {noise_std: -.inf}\n",
            "w.yaml:5:20:",
            ["-.inf at `$.lidar.noise_std` is not a finite number"],
            id="minus-inf",
        ),
        pytest.param(
            ROOM + ROBOT + "    start: {x: 'nan', y: 1.0}\n",
            "w.yaml:4:16:",
            ["`$.robots[0].start.x` is not a finite number"],
            id="nan-as-a-string",
        ),
        pytest.param(
            ROOM + ROBOT + "    start: {x: 4.5, y: 1.0}\n",
            "w.yaml:4:12:",
            ["robot 'r' starts at (4.5, 1), not inside the 4 x 3 m room", "0.17 <= x <= 3.83"],
            id="start-outside-the-room",
        ),
        pytest.param(
            ROOM + ROBOT + "    start: {x: 0.1, y: 1.0}\n",
            "w.yaml:4:12:",
            ["not inside the 4 x 3 m room", "move the start inside the room"],
            id="start-half-in-the-wall",
        ),
        pytest.param(
            OK + "    route: [{x: 2.0, y: 2.0}, {x: 2.0, y: -1.0}]\n",
            "w.yaml:5:31:",
            ["route point 1 of robot 'r', (2, -1), is outside the 4 x 3 m room", "move it"],
            id="route-point-outside-the-room",
        ),
        pytest.param(
            "obstacles:\n  - {kind: box, x: 20.0, y: 1.0, w: 1.0, h: 1.0}\n" + OK,
            "w.yaml:2:5:",
            ["obstacle 0 (box at (20, 1)) is outside the 4 x 3 m room", "move its centre"],
            id="obstacle-outside-the-room",
        ),
        pytest.param(
            "obstacles:\n  - {kind: circle, x: 1.2, y: 1.0, r: 0.3}\n" + OK,
            "w.yaml:6:12:",
            ["robot 'r' starts at (1, 1), overlapping obstacle 0 (circle at (1.2, 1))"],
            id="start-inside-an-obstacle",
        ),
        pytest.param(
            OK + "  - name: s\n    start: {x: 1.2, y: 1.1}\n",
            "w.yaml:6:12:",
            ["robot 's' starts at (1.2, 1.1), overlapping robot 'r'", "0.34 m apart"],
            id="robots-on-top-of-each-other",
        ),
        pytest.param(
            "obstacles:\n  - {kind: box, x: 3.0, y: 2.0, w: 1.0, h: 1.0, theta: 0.5}\n"
            + OK
            + "    route: [{x: 3.0, y: 2.0}]\n",
            "w.yaml:7:13:",
            ["route point 0 of robot 'r', (3, 2), lies inside obstacle 0", "no nearer than"],
            id="route-point-inside-an-obstacle",
        ),
        pytest.param(
            ROOM + ROBOT + "    radius: 0.5\n    start: {x: 1.0, y: 1.0}\n"
            "    route: [{x: 0.0, y: 1.5}]\n",
            "w.yaml:6:13:",
            ["too close to a wall", "radius 0.5 m"],
            id="route-point-out-of-reach-by-a-wall",
        ),
        pytest.param(
            ROOM + ROBOT + "    radius: 2.0\n    start: {x: 1.0, y: 1.0}\n",
            "w.yaml:4:13:",
            ["robot 'r' (radius 2 m) does not fit in the 4 x 3 m room"],
            id="robot-larger-than-the-room",
        ),
        pytest.param(
            OK + "lidar: {rate_hz: 100}\nphysics_hz: 50\n",
            "w.yaml:5:18:",
            ["rate_hz 100 is above physics_hz 50", "lower rate_hz or raise physics_hz"],
            id="scans-faster-than-physics",
        ),
        pytest.param("seed: -1\n" + OK, "w.yaml:1:7:", ["Expected `int` >= 0"], id="seed"),
        pytest.param(
            OK + "    max_linear: 5000\n",
            "w.yaml:5:17:",
            ["Expected `float` <= 1000.0 - at `$.robots[0].max_linear`"],
            id="speed-past-the-wire-bound",
        ),
        pytest.param(
            OK + "lidar: {angle_min: 10}\n",
            "w.yaml:5:20:",
            ["`$.lidar.angle_min`"],
            id="angle_min",
        ),
        pytest.param(
            OK + "occlusions: [{robot: r, mode: arcs}]\n",
            "w.yaml:5:14:",
            ["an arcs occlusion needs at least one arc - add arcs"],
            id="arcs-without-arcs",
        ),
    ],
)
def test_an_impossible_world_is_refused_at_its_line_with_a_fix(
    text: str, where: str, words: list[str]
) -> None:
    with pytest.raises(WorldError) as exc:
        parse_world(text, "w.yaml")
    message = str(exc.value)
    assert message.startswith(where), message
    for w in words:
        assert w in message, message
    assert "\n" not in message


def test_the_file_name_is_the_source_of_the_location(tmp_path: Path) -> None:
    path = tmp_path / "small.yaml"
    path.write_text(OK + "lidar: {range_min: 5.0, range_max: 2.0}\n", encoding="utf-8")
    with pytest.raises(WorldError, match=r"small\.yaml:5:20: lidar range_min"):
        load_world(path)


def test_a_binary_or_missing_world_file_is_a_world_error(tmp_path: Path) -> None:
    binary = tmp_path / "w.yaml"
    binary.write_bytes(b"seed: 1\n\xff\xfe\x00")
    with pytest.raises(WorldError, match=r"w\.yaml:2:1: the world file is not UTF-8 text"):
        load_world(binary)
    with pytest.raises(WorldError, match=r"cannot read the world file"):
        load_world(tmp_path / "missing.yaml")


def test_a_world_built_in_code_gets_the_same_checks() -> None:
    good = parse_world(OK)
    nan = msgspec.structs.replace(good.room, width=math.nan)
    with pytest.raises(WorldError, match=r"<world>: at `\$\.room\.width`: nan .* not a finite"):
        check_world(msgspec.structs.replace(good, room=nan))
    small = msgspec.structs.replace(good.room, width=1.0)
    with pytest.raises(WorldError, match=r"at `\$\.robots\[0\]\.start`: robot 'r' starts"):
        Simulation(msgspec.structs.replace(good, room=small))  # the simulator checks too
    assert check_world(good) is good


def test_an_occlusion_without_t_end_lasts_to_the_end() -> None:
    world = parse_world(OK + "occlusions: [{robot: r, mode: sector, width: 1.0, t_start: 2}]\n")
    assert world.occlusions[0].t_end is None
    beams = np.array([0.5])
    assert not occlusion_mask(world.occlusions, "r", 1.9, beams, 0).any()
    assert occlusion_mask(world.occlusions, "r", 1e6, beams, 0).all()


def test_shipped_worlds_are_found_by_name_and_all_load() -> None:
    assert shipped_worlds() == ["corridor", "default", "obstacles_only"]
    for name in shipped_worlds():
        path = find_world(name)
        assert path == default_world_path(name)
        assert isinstance(load_world(path), WorldSpec)


def test_an_unknown_name_or_missing_file_lists_the_shipped_worlds(tmp_path: Path) -> None:
    listing = "the shipped worlds are corridor, default, obstacles_only"
    with pytest.raises(WorldError, match="'coridor' is not a shipped world") as exc:
        find_world("coridor")
    assert listing in str(exc.value)
    with pytest.raises(WorldError, match="no such world file") as exc:
        find_world(str(tmp_path / "nope.yaml"))
    assert listing in str(exc.value)
    with pytest.raises(WorldError, match=listing):
        default_world_path("nope")


def test_a_path_is_a_file_even_when_it_looks_like_a_name(tmp_path: Path) -> None:
    own = tmp_path / "corridor"
    own.write_text(OK, encoding="utf-8")
    assert find_world(str(own)) == own
    assert find_world(own) == own  # a Path is never a name
    assert find_world("corridor") != own
