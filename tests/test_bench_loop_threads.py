"""bench.loop.threads: the per-thread CPU accounting finds the loop's processes and
reads their threads' CPU time."""

from __future__ import annotations

import subprocess
import sys
import time

from bench.loop.threads import _expected, _processes, _snapshot


def test_finds_runner_children_and_counts_their_cpu() -> None:
    spin = (
        "import sys, time\n"
        "t = time.process_time()\n"
        "while time.process_time() - t < 0.3: pass\n"
        "sys.stdin.read()"
    )
    child = subprocess.Popen(
        [sys.executable, "-c", spin, "--node", "m"], stdin=subprocess.PIPE, text=True
    )
    try:
        time.sleep(0.5)
        procs = _processes()
        assert procs.get(child.pid) == "runner m"
        assert "robot" in procs.values()
        snap = _snapshot(procs)
        cpu_ns, runs = snap[("runner m", "loop")]
        assert cpu_ns >= 200_000_000  # it spun for 0.3 s of CPU
        assert runs >= 1
    finally:
        assert child.stdin is not None
        child.stdin.close()
        child.wait(timeout=10)


def test_expects_a_runner_per_compute_node_the_service_and_the_robot() -> None:
    assert _expected("rap-5proc") == 7
    assert _expected("rap-1proc") == 3
