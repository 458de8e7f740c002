"""A CAN bus thread that takes heartbeats while it streams: what it costs, and how often it
turns its loop and decides.

Not a test (pytest does not collect it). Two ZLAC706 heartbeating every 10 ms on python-can's
``virtual`` bus, their simulator in this process, a client thread sending both wheels a new
speed every 10 ms for a 20 ms follow stream (a mobile base's wheels). After a second to
settle, for ``SECONDS``: the bus thread's CPU (read from /proc), its loop turns, its looks at
the bus and its planner's decisions a second, and the follow error. Each figure depends on
the host: compare checkouts turn about (each run with its own checkout's venv).

    .venv/bin/python tests/benchmarks/bench_can_heartbeats.py [SECONDS]
"""

from __future__ import annotations

import itertools
import os
import sys
import threading
import time
from collections import Counter
from typing import Any

import can
from usage import arguments

from busgate.codecs import zlac706_can as zcan
from busgate.gateway.bus.can_owner import CanBusOwner
from busgate.gateway.cli.bench import thread_cpu_s, wait_online
from busgate.gateway.scheduler.planner import BusPlanner
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.zlac706 import Zlac706CanDevice
from busgate.schemas.config import CanBus

IDS = (1, 2)
calls: Counter[str] = Counter()


def counted(holder: type, name: str, label: str) -> None:
    original = getattr(holder, name)

    def counting(*args: Any, **kwargs: Any) -> Any:
        calls[label] += 1
        return original(*args, **kwargs)

    setattr(holder, name, counting)


def stream(runner: BusRunner, stop: threading.Event) -> None:
    """A client: a new speed for every wheel each 10 ms."""
    rpm = itertools.cycle(range(50, 150))
    while not stop.is_set():
        for name, driver in runner.drivers.items():
            runner.follow(name, driver.follow_target({"rpm": next(rpm)}), "velocity")
        time.sleep(0.01)


def main() -> int:
    seconds = arguments(__doc__, ("seconds", float, 8.0, "how long to measure")).seconds
    counted(BusRunner, "_step", "loop turns")
    counted(CanBusOwner, "take_unsolicited", "looks at the bus")
    counted(BusPlanner, "decide", "decisions")
    channel = f"bench-heartbeats-{os.getpid()}"
    nodes = [Zlac706CanDevice(n, heartbeat_ms=10) for n in IDS]
    simulator = CanSimulator(zcan, nodes, bus=can.Bus(interface="virtual", channel=channel))
    devices = [{"name": f"wheel{n}", "kind": "zlac706", "id": n, "heartbeat_ms": 10,
                "follow_period_ms": 20} for n in IDS]  # fmt: skip
    bus = CanBus(name="can0", transport="can", interface="virtual", channel=channel,
                 devices=devices)  # fmt: skip
    simulator.start()
    runner = build_bus(bus).start()
    stop = threading.Event()
    client = threading.Thread(target=stream, args=(runner, stop))
    try:
        wait_online(runner)
        for name, driver in runner.drivers.items():
            for text in ('{"op":"set_mode","mode":"velocity"}', '{"op":"enable"}'):
                runner.submit(name, driver.parse(text)).result(10)
        client.start()
        time.sleep(1.0)
        before, cpu, started = calls.copy(), thread_cpu_s(runner.native_id), time.monotonic()
        time.sleep(seconds)
        elapsed = time.monotonic() - started
        cpu = thread_cpu_s(runner.native_id) - cpu
        spent = calls - before
        stats = runner.statistics()
    finally:
        stop.set()
        if client.is_alive():
            client.join()
        runner.stop()
        simulator.stop()
    print(f"bus thread CPU {100 * cpu / elapsed:.1f} %")
    for label in ("loop turns", "looks at the bus", "decisions"):
        print(f"{label}: {spent[label] / elapsed:.0f} a second")
    if stats.follow_error_p50_s is not None and stats.follow_error_p99_s is not None:
        print(f"follow error p50 {stats.follow_error_p50_s * 1e3:.3f} ms, "
              f"p99 {stats.follow_error_p99_s * 1e3:.3f} ms")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
