"""The peer side of the loop latency race: RPIO 0.4.3 (PyPI ``robosapiensio``, client library
``rpio.clientLibraries.rpclpy``) running the lidar-occlusion MAPLE-K chain.

Runs with the peer's own interpreter (``bench/.rpio-venv``, see ``peer_venv.py``); it imports
nothing from the RAP workspace. It follows the RoboSAPIENS reference harness of the peer's
own lidar-occlusion loop.

    bench/.rpio-venv/bin/python bench/loop/rpio_peer.py --variant redis|mqtt \
        --rates 5,20,100 --cycles N --warmup W --out FILE.json

The chain is five rpclpy ``Node`` subclasses, one OS process each, wired as the RoboSAPIENS
HelloWorld / York demos (same event names and knowledge keys), with no sleep in any callback:

    robot --/Scan--> Monitor     knowledge laser_scan := scan; event new_data
                     Analysis    on new_data: read laser_scan, occlusion mask (inf beams),
                                 knowledge lidar_mask; event anomaly (every scan: full loop)
                     Plan        on anomaly: read lidar_mask, knowledge directions :=
                                 {"commands": [{"omega": 1.0, "duration": 0.5}], "period": 8};
                                 event new_plan
                     Legitimate  on new_plan: event isLegit
                     Execute     on isLegit: read directions, message /spin_config
    robot <--/spin_config--

The "robot" is an rpclpy Node in this orchestrating process: it paces /Scan on absolute
deadlines and timestamps the matching /spin_config (both ends with ``perf_counter_ns`` in this
process). The scan's seq travels through the knowledge values, as the real data does. Loop
latency = plan received - scan sent. A cycle is lost when no plan for its scan arrived within
2 s. ``lost_superseded`` counts the lost cycles that a newer cycle's plan answered within 2 s:
knowledge is last-value, so a scan overwritten before Analysis read it gets no plan of its own
(and the newer cycle's plan often arrives twice: ``duplicates``).

Variants: ``redis`` (events and messages over Redis pub/sub, knowledge in Redis; the York
setup) and ``mqtt`` (events and messages over MQTT QoS 0 via mosquitto, knowledge in Redis;
the HelloWorld setup).

Each run starts its own ``redis-server`` (and ``mosquitto``) on free loopback ports and stops
them by PID at the end; each rate gets a fresh set of node processes and an empty database.
CPU: utime+stime from /proc/<pid>/stat over the measured window, % of one core.

Sub-command used internally: ``node --role ROLE ...``.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import math
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

ROLES = ("Monitor", "Analysis", "Plan", "Legitimate", "Execute")
VARIANTS = ("redis", "mqtt")
HOST = "127.0.0.1"
LOST_AFTER_NS = 2_000_000_000
PRIME_TIMEOUT_S = 30.0
CLK_TCK = os.sysconf("SC_CLK_TCK")
SCAN_BEAMS = 360
OCCLUDED = (*range(100, 130), *range(250, 262))  # two occluded sectors: 42 inf beams


def log(msg: str) -> None:
    print(f"  [rpio-peer] {msg}", file=sys.stderr, flush=True)


# ------------------------------------------------------------------------------------------
# processes and ports (the peer venv has no rap_sdk: small local helpers)
# ------------------------------------------------------------------------------------------
def free_port() -> int:
    """A free TCP port on loopback (the OS picks it; the caller binds it soon after)."""
    with socket.socket() as s:
        s.bind((HOST, 0))
        port: int = s.getsockname()[1]
        return port


def port_open(port: int) -> bool:
    try:
        with socket.create_connection((HOST, port), timeout=0.3):
            return True
    except OSError:
        return False


def die_with_parent() -> None:
    """Linux: SIGTERM this process when its parent dies (no orphaned brokers or nodes)."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def stop_pid(proc: subprocess.Popen[Any], grace: float = 5.0) -> None:
    """SIGTERM the process we started, SIGKILL after ``grace`` seconds."""
    if proc.poll() is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        os.kill(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.kill(proc.pid, signal.SIGKILL)
        proc.wait()


def proc_ticks(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return int(fields[11]) + int(fields[12])  # utime + stime


def system_busy_ticks() -> int:
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:9]]
    return sum(v) - v[3] - v[4]  # all but idle and iowait


class Brokers:
    """redis-server (always: knowledge) and mosquitto (mqtt variant) on free loopback ports."""

    def __init__(self, state: Path, *, mqtt: bool) -> None:
        self.state = state
        self.need_mqtt = mqtt
        self.redis_port = 0
        self.mqtt_port = 0
        self.redis: subprocess.Popen[bytes] | None = None
        self.mosquitto: subprocess.Popen[bytes] | None = None

    def _spawn(self, name: str, args: list[str]) -> subprocess.Popen[bytes]:
        with open(self.state / f"{name}.log", "wb") as out:
            return subprocess.Popen(  # started before any thread exists: preexec_fn is safe
                args, stdout=out, stderr=subprocess.STDOUT, preexec_fn=die_with_parent
            )

    def _up(self, name: str, proc: subprocess.Popen[bytes], port: int, ready: str) -> bool:
        """Our process logged ``ready`` and the port answers (not someone else's listener)."""
        log_file = self.state / f"{name}.log"
        end = time.monotonic() + 10.0
        while time.monotonic() < end:
            if proc.poll() is not None:
                return False
            if ready in log_file.read_text(errors="replace") and port_open(port):
                return True
            time.sleep(0.05)  # startup poll, outside any measurement
        return False

    def _start_one(
        self, name: str, ready: str, make: Callable[[int], list[str]]
    ) -> tuple[subprocess.Popen[bytes], int]:
        for _ in range(5):  # a free port may be taken between the probe and the bind
            port = free_port()
            proc = self._spawn(name, make(port))
            if self._up(name, proc, port, ready):
                return proc, port
            stop_pid(proc)
        tail = (self.state / f"{name}.log").read_text(errors="replace")[-1500:]
        raise RuntimeError(f"{name} did not come up on loopback:\n{tail}")

    def start(self) -> None:
        binary = shutil.which("redis-server")
        if binary is None:
            raise RuntimeError("redis-server not found on PATH (apt-get install redis-server)")
        self.redis, self.redis_port = self._start_one(
            "redis",
            "Ready to accept connections",
            lambda p: [
                binary, "--bind", HOST, "--port", str(p), "--save", "", "--appendonly", "no",
                "--dir", str(self.state), "--logfile", "",
            ],
        )  # fmt: skip
        if self.need_mqtt:
            mosq = shutil.which("mosquitto") or (
                "/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else None
            )
            if mosq is None:
                raise RuntimeError("mosquitto not found (apt-get install mosquitto)")

            def conf(p: int) -> list[str]:
                path = self.state / f"mosquitto-{p}.conf"
                text = f"listener {p} {HOST}\nallow_anonymous true\n"
                if os.geteuid() == 0:  # else it drops to its own user, which clears PDEATHSIG
                    text += "user root\n"
                path.write_text(text)
                path.chmod(0o644)
                return [mosq, "-c", str(path)]

            self.mosquitto, self.mqtt_port = self._start_one("mosquitto", " running", conf)

    def pids(self) -> dict[str, int]:
        out = {}
        if self.redis is not None:
            out["redis-server"] = self.redis.pid
        if self.mosquitto is not None:
            out["mosquitto"] = self.mosquitto.pid
        return out

    def flush(self) -> None:
        import redis

        client = redis.Redis(host=HOST, port=self.redis_port)
        client.flushdb()
        client.close()

    def stop(self) -> None:
        for proc in (self.mosquitto, self.redis):
            if proc is not None:
                stop_pid(proc)


# ------------------------------------------------------------------------------------------
# rpclpy configuration and the five MAPLE-K nodes
# ------------------------------------------------------------------------------------------
def node_config(variant: str, redis_port: int, mqtt_port: int) -> dict[str, Any]:
    if variant == "redis":
        transport: dict[str, Any] = {"protocol": "redis", "host": HOST, "port": redis_port}
    elif variant == "mqtt":
        transport = {"protocol": "mqtt", "broker": HOST, "port": mqtt_port}
    else:
        raise ValueError(f"unknown variant {variant!r}")
    return {
        # the handler is there, as in the demos, but nothing at WARNING is logged in the loop
        "Logger_Config": {
            "log_level": "WARNING",
            "logger_type": "terminal",
            "format": "%(asctime)s - %(name)s - %(levelname)s - %(message)s",
            "terminal": {},
        },
        "Knowledge_Config": {"knowledge_type": "redis", "host": HOST, "port": redis_port, "db": 0},
        "Event_Manager_Config": dict(transport),
        "Message_Manager_Config": dict(transport),
    }


def node_classes() -> dict[str, type]:
    """The five stages (imported lazily: rpclpy is only in the peer venv)."""
    from rpio.clientLibraries.rpclpy.node import Node

    class Stage(Node):
        def __init__(self, config: dict[str, Any]) -> None:
            super().__init__(config=config)
            self.handled = 0
            self.stale = 0  # knowledge already overwritten by a newer cycle
            self.errors = 0
            self.first_error: str | None = None

        def guarded(self, fn: Callable[[str], None]) -> Callable[[str], None]:
            # rpclpy's redis listener thread dies on an exception from a callback: count it
            def run(msg: str) -> None:
                try:
                    fn(msg)
                    self.handled += 1
                except Exception:
                    self.errors += 1
                    if self.first_error is None:
                        self.first_error = traceback.format_exc()
                        print(self.first_error, file=sys.stderr, flush=True)

            return run

        def note_stale(self, event_msg: str, seq: int) -> None:
            if json.loads(event_msg).get("seq") != seq:
                self.stale += 1

        def register_callbacks(self) -> None:
            raise NotImplementedError

    class Monitor(Stage):
        def monitor_data(self, msg: str) -> None:
            scan = json.loads(msg)
            self.write_knowledge("laser_scan", msg)
            self.publish_event("new_data", {"seq": scan["header"]["seq"]})

        def register_callbacks(self) -> None:
            self.register_message_callback("/Scan", self.guarded(self.monitor_data))

    class Analysis(Stage):
        def analyse_scan_data(self, msg: str) -> None:
            scan = self.read_knowledge("laser_scan", queueSize=1)
            header = scan["header"]
            self.note_stale(msg, header["seq"])
            occluded = [1 if math.isinf(r) else 0 for r in scan["ranges"]]
            mask = {"seq": header["seq"], "t_send_ns": header["t_send_ns"], "occluded": occluded}
            self.write_knowledge("lidar_mask", json.dumps(mask))
            self.publish_event("anomaly", {"seq": header["seq"]})

        def register_callbacks(self) -> None:
            self.register_event_callback("new_data", self.guarded(self.analyse_scan_data))

    class Plan(Stage):
        def planner(self, msg: str) -> None:
            mask = self.read_knowledge("lidar_mask", queueSize=1)
            self.note_stale(msg, mask["seq"])
            directions = {
                "commands": [{"omega": 1.0, "duration": 0.5}],
                "period": 8,
                "seq": mask["seq"],
                "t_send_ns": mask["t_send_ns"],
            }
            # the demos publish new_plan before writing directions (a race without their
            # sleeps); here the knowledge is written first
            self.write_knowledge("directions", json.dumps(directions))
            self.publish_event("new_plan", {"seq": mask["seq"]})

        def register_callbacks(self) -> None:
            self.register_event_callback("anomaly", self.guarded(self.planner))

    class Legitimate(Stage):
        def legitimate(self, msg: str) -> None:
            self.publish_event("isLegit", {"seq": json.loads(msg).get("seq")})

        def register_callbacks(self) -> None:
            self.register_event_callback("new_plan", self.guarded(self.legitimate))

    class Execute(Stage):
        def executer(self, msg: str) -> None:
            directions = self.read_knowledge("directions", queueSize=1)
            self.note_stale(msg, directions["seq"])
            self.publish_message("/spin_config", json.dumps(directions))

        def register_callbacks(self) -> None:
            self.register_event_callback("isLegit", self.guarded(self.executer))

    classes: dict[str, type] = {"Node": Node}
    classes.update((c.__name__, c) for c in (Monitor, Analysis, Plan, Legitimate, Execute))
    return classes


def cmd_node(a: argparse.Namespace) -> None:
    die_with_parent()
    node = node_classes()[a.role](node_config(a.variant, a.redis_port, a.mqtt_port))
    node.register_callbacks()
    node.start()
    stopping = threading.Event()
    signal.signal(signal.SIGTERM, lambda _s, _f: stopping.set())
    print("READY", flush=True)
    stopping.wait()
    stats = {"handled": node.handled, "stale": node.stale, "errors": node.errors}
    stats["first_error"] = node.first_error
    Path(a.stats).write_text(json.dumps(stats))
    sys.stdout.flush()
    os._exit(0)  # rpclpy's listener threads do not stop on their own


# ------------------------------------------------------------------------------------------
# the robot: an rpclpy Node that sends /Scan and receives /spin_config
# ------------------------------------------------------------------------------------------
def scan_template(seed: int = 4) -> str:
    """A 360-beam LaserScan as JSON with ``%d`` holes for seq and send time (~4.5 KB)."""
    rnd = random.Random(seed)
    ranges: list[float] = [round(rnd.uniform(0.3, 8.0), 7) for _ in range(SCAN_BEAMS)]
    for i in OCCLUDED:
        ranges[i] = math.inf
    return (
        '{"header": {"seq": %d, "t_send_ns": %d, "frame_id": "rplidar_link"}, '
        '"angle_min": -3.141592653589793, "angle_max": 3.141592653589793, '
        '"angle_increment": 0.017453292519943295, "range_min": 0.164, "range_max": 12.0, '
        '"ranges": ' + json.dumps(ranges) + "}"  # inf -> Infinity, which json.loads accepts
    )


class Robot:
    def __init__(self, variant: str, brokers: Brokers) -> None:
        node_cls = node_classes()["Node"]
        self.node = node_cls(node_config(variant, brokers.redis_port, brokers.mqtt_port))
        self.node.register_message_callback("/spin_config", self.on_plan)
        self.template = scan_template()
        self.lock = threading.Lock()
        self.recv: dict[int, int] = {}
        self.duplicates = 0
        self.expect: set[int] = set()
        self.all_back = threading.Event()
        self.primed = threading.Event()

    def start(self) -> None:
        self.node.start()

    def stop(self) -> None:
        with contextlib.suppress(Exception):
            self.node.shutdown()

    def on_plan(self, msg: str) -> None:
        t = time.perf_counter_ns()
        seq = json.loads(msg)["seq"]
        with self.lock:
            if seq in self.recv:
                self.duplicates += 1
                return
            self.recv[seq] = t
            self.expect.discard(seq)
            if not self.expect:
                self.all_back.set()
        if seq < 0:
            self.primed.set()

    def send(self, seq: int) -> int:
        t = time.perf_counter_ns()
        self.node.publish_message("/Scan", self.template % (seq, t))
        return t

    def prime(self, next_seq: int) -> int:
        """One scan every 200 ms (negative seqs) until one comes all the way round."""
        self.primed.clear()
        end = time.monotonic() + PRIME_TIMEOUT_S
        while not self.primed.is_set():
            if time.monotonic() > end:
                raise RuntimeError(f"the chain never answered within {PRIME_TIMEOUT_S:.0f} s")
            self.send(next_seq)
            next_seq -= 1
            self.primed.wait(0.2)
        time.sleep(0.3)  # let the other priming scans come back before measuring
        return next_seq

    def run(self, rate: float, warmup: int, cycles: int, first: int, pids: dict[str, int]) -> Any:
        total = warmup + cycles
        measured = range(first + warmup, first + total)
        with self.lock:
            self.expect = set(measured)
            self.all_back.clear()
        sent: dict[int, int] = {}
        period = 1.0 / rate
        late_sends = 0
        cpu0: dict[str, int | None] = {}
        busy0 = 0
        t_first = t_last = 0.0
        t0 = time.perf_counter() + 0.02
        for i in range(total):
            wait = t0 + i * period - time.perf_counter()
            if wait > 0:
                time.sleep(wait)  # pacing on absolute deadlines
            elif wait < -period:
                late_sends += 1
            if i == warmup:
                cpu0 = {k: proc_ticks(p) for k, p in pids.items()}
                busy0 = system_busy_ticks()
                t_first = time.perf_counter()
            sent[first + i] = self.send(first + i)
        t_last = time.perf_counter()
        cpu1 = {k: proc_ticks(p) for k, p in pids.items()}
        busy1 = system_busy_ticks()
        self.all_back.wait(max(0.0, LOST_AFTER_NS / 1e9 + 0.5 - (time.perf_counter() - t_last)))
        with self.lock:
            recv = dict(self.recv)
            duplicates = self.duplicates
        latencies: list[int] = []
        late = 0
        for seq in measured:
            got = recv.get(seq)
            if got is None:
                continue
            if got - sent[seq] > LOST_AFTER_NS:
                late += 1
            else:
                latencies.append(got - sent[seq])
        # knowledge is last-value: a cycle whose scan was overwritten before Analysis read it
        # gets no plan of its own, but a newer cycle's plan may still answer it within 2 s
        superseded, newest = 0, None
        for seq in reversed(measured):
            got = recv.get(seq)
            own = got is not None and got - sent[seq] <= LOST_AFTER_NS
            if not own and newest is not None and newest - sent[seq] <= LOST_AFTER_NS:
                superseded += 1
            if got is not None:
                newest = got if newest is None else min(newest, got)
        window = t_last - t_first
        cpu = {
            k: round(100.0 * (cpu1[k] - v) / CLK_TCK / window, 1)
            for k, v in cpu0.items()
            if v is not None and cpu1.get(k) is not None and window > 0
        }
        return {
            "rate_hz": rate,
            "warmup": warmup,
            "sent": cycles,
            "received": len(latencies),
            "lost": cycles - len(latencies),
            "lost_superseded": superseded,
            "late_over_2s": late,
            "duplicates": duplicates,
            "latencies_ns": latencies,
            "send_rate_hz": round((cycles - 1) / window, 2) if window > 0 else None,
            "late_sends": late_sends,
            "window_s": round(window, 3),
            "cpu_pct": cpu,
            "cpu_pct_total": round(sum(cpu.values()), 1),
            "system_busy_pct": round(100.0 * (busy1 - busy0) / CLK_TCK / window, 1)
            if window > 0
            else None,
        }


# ------------------------------------------------------------------------------------------
# orchestration
# ------------------------------------------------------------------------------------------
@contextlib.contextmanager
def chain(variant: str, brokers: Brokers, run_dir: Path) -> Iterator[dict[str, Any]]:
    """The five node processes; yields {role: pid}; on exit SIGTERM them and collect stats."""
    run_dir.mkdir(parents=True, exist_ok=True)
    procs: dict[str, subprocess.Popen[bytes]] = {}
    info: dict[str, Any] = {"pids": {}, "stats": {}}
    try:
        for role in ROLES:
            args = [sys.executable, str(Path(__file__).resolve()), "node", "--role", role]
            args += ["--variant", variant, "--stats", str(run_dir / f"{role}.stats.json")]
            args += ["--redis-port", str(brokers.redis_port), "--mqtt-port", str(brokers.mqtt_port)]
            with open(run_dir / f"{role}.log", "wb") as out:
                procs[role] = subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT)
            info["pids"][role] = procs[role].pid
        yield info
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(proc.pid, signal.SIGTERM)
        for role, proc in procs.items():
            stop_pid(proc)
            stats = run_dir / f"{role}.stats.json"
            if stats.exists():
                info["stats"][role] = json.loads(stats.read_text())
            else:
                log_tail = (run_dir / f"{role}.log").read_text(errors="replace")[-1500:]
                info["stats"][role] = {"exit": proc.returncode, "log_tail": log_tail}


def versions() -> dict[str, Any]:
    from importlib.metadata import version

    def first_line(args: list[str]) -> str:
        try:
            done = subprocess.run(args, capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.TimeoutExpired):
            return "-"
        return ((done.stdout or done.stderr).splitlines() or ["-"])[0].strip()

    return {
        "robosapiensio": version("robosapiensio"),
        "redis-py": version("redis"),
        "paho-mqtt": version("paho-mqtt"),
        "python": sys.version.split()[0],
        "redis-server": first_line(["redis-server", "--version"]),
        "mosquitto": first_line(["mosquitto", "-h"]),
    }


def cmd_run(a: argparse.Namespace) -> int:
    rates = [float(r) for r in a.rates.split(",") if r.strip()]
    if a.variant not in VARIANTS or not rates or min(rates) <= 0 or a.cycles < 2:
        raise SystemExit("need --variant redis|mqtt, positive --rates and --cycles >= 2")
    signal.signal(signal.SIGTERM, lambda _s, _f: sys.exit(143))  # run the finally blocks
    sys.stdout = open(os.devnull, "w")  # rpclpy prints on shutdown; the results go to --out
    out: dict[str, Any] = {"variant": a.variant, "meta": versions(), "rates": []}
    with tempfile.TemporaryDirectory(prefix="rpio_peer_") as tmp:
        state = Path(tmp)
        state.chmod(0o755)  # readable by mosquitto whatever user it runs as
        brokers = Brokers(state, mqtt=a.variant == "mqtt")
        try:
            brokers.start()
            out["meta"]["ports"] = {"redis": brokers.redis_port, "mqtt": brokers.mqtt_port}
            log(f"{a.variant}: redis-server :{brokers.redis_port}" + (
                f", mosquitto :{brokers.mqtt_port}" if a.variant == "mqtt" else ""
            ))  # fmt: skip
            seq, prime_seq = 0, -1
            for rate in rates:
                brokers.flush()
                t_start = time.monotonic()
                robot = None
                with chain(a.variant, brokers, state / f"{rate:g}hz") as nodes:
                    try:
                        robot = Robot(a.variant, brokers)  # threads only after the brokers
                        robot.start()
                        prime_seq = robot.prime(prime_seq)
                        t_primed = time.monotonic()
                        pids = {**nodes["pids"], **brokers.pids(), "robot": os.getpid()}
                        res = robot.run(rate, a.warmup, a.cycles, seq, pids)
                        res["startup_s"] = round(t_primed - t_start, 2)
                    except RuntimeError as exc:
                        res = {"rate_hz": rate, "error": str(exc)}
                    finally:
                        if robot is not None:
                            robot.stop()
                res["node_stats"] = nodes["stats"]
                if "error" in res:
                    res["error"] += "\n" + json.dumps(nodes["stats"])[-3000:]
                res["run_wall_s"] = round(time.monotonic() - t_start, 2)
                seq += a.warmup + a.cycles
                out["rates"].append(res)
                log(summary_line(a.variant, res))
        finally:
            brokers.stop()
    Path(a.out).write_text(json.dumps(out))
    return 0 if all("error" not in r for r in out["rates"]) else 2


def summary_line(variant: str, r: dict[str, Any]) -> str:
    if "error" in r:
        return f"{variant} {r['rate_hz']:g} Hz: ERROR {r['error'][:300]}"
    lat = sorted(r["latencies_ns"])

    def q(p: float) -> str:
        return f"{lat[max(0, math.ceil(p * len(lat)) - 1)] / 1e6:.2f}" if lat else "-"

    return (
        f"{variant} {r['rate_hz']:g} Hz: p50 {q(0.5)} p90 {q(0.9)} p99 {q(0.99)} ms, "
        f"lost {r['lost']}/{r['sent']}, sent at {r['send_rate_hz']} Hz, "
        f"cpu {r['cpu_pct_total']} % of a core ({r['run_wall_s']} s)"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    sub = ap.add_subparsers(dest="cmd")
    node = sub.add_parser("node")
    node.add_argument("--role", choices=ROLES, required=True)
    node.add_argument("--variant", choices=VARIANTS, required=True)
    node.add_argument("--stats", required=True)
    node.add_argument("--redis-port", type=int, required=True)
    node.add_argument("--mqtt-port", type=int, default=0)
    run = sub.add_parser("run")
    run.add_argument("--variant", choices=VARIANTS, required=True)
    run.add_argument("--rates", default="5,20,100")
    run.add_argument("--cycles", type=int, default=500)
    run.add_argument("--warmup", type=int, default=50)
    run.add_argument("--out", required=True)
    argv = sys.argv[1:]
    if not argv or argv[0].startswith("-"):
        argv = ["run", *argv]
    a = ap.parse_args(argv)
    if a.cmd == "node":
        cmd_node(a)
        return 0
    return cmd_run(a)


if __name__ == "__main__":
    sys.exit(main())
