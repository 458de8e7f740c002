"""An e-stop's path through the bus threads: from its hand-over to its first frame's write.

Not a test (pytest does not collect it). ``--buses`` buses, each on a ``busgate sim`` of its
own process, run in this one process as the gateway runs them (``build_bus``):

- ``--family inspire_la`` (the default): three Inspire LA a bus at 921600 baud, every device
  streaming at 10 ms (the streams start again after each e-stop's reset);
- ``--family zlac706_can``: a base's two ZLAC706 a bus, behind the simulator's SLCAN
  adapter, heartbeating every 10 ms.

``--estops`` times, at a random moment, every bus is handed an e-stop as the gateway hands
them (``runner.estop`` each, then ``let_estops_go``), each bus's first e-stop frame is timed
from its owner's frame hook, and the e-stop is reset. Printed, in µs at p50 / p90:

- the worst bus of each e-stop, from the first hand-over to its first frame's write (wall),
  and to the write that gave every device of the bus its first (a base's second wheel);
- per bus, the bus thread's CPU from its wake (the flag it waited on raised) to its first
  frame's write.

With one bus, the CPU figure is the Python an e-stop's first frame waits for; with several,
their bus threads take turns on this one interpreter, so the wall figures grow with their sum.

    .venv/bin/python tests/benchmarks/bench_estop_path.py [--family F] [--buses 1] [--estops 80]

Run with another checkout's interpreter (``OTHER/.venv/bin/python tests/benchmarks/...``) it
times that checkout's code: turn about, the two meet the same load.
"""

from __future__ import annotations

import argparse
import random
import shutil
import subprocess
import sys
import time
from pathlib import Path

from bench_scale import positive  # a sibling script's argparse type: its folder is on the path

from busgate.gateway.bus.clock import now
from busgate.gateway.scheduler.runner import BusRunner, let_estops_go
from busgate.gateway.service.assembly import build_bus
from busgate.schemas.config import CanBus, SerialBus

#: Per family: the simulator's arguments, and a bus of ``name`` on the simulator's port.
FAMILIES = {
    "inspire_la": (
        ["inspire_la", "--ids", "1,2,3"],
        lambda name, port: SerialBus(
            name=name, transport="serial", port=port, baudrate=921_600,
            devices=[{"name": f"{name}-la{i}", "kind": "inspire_la", "id": i,
                      "follow_period_ms": 10} for i in (1, 2, 3)]),
    ),
    "zlac706_can": (
        ["zlac706_can", "--ids", "1,2", "--interface", "slcan", "--heartbeat-ms", "10"],
        lambda name, port: CanBus(
            name=name, transport="can", interface="slcan", channel=port,
            devices=[{"name": f"{name}-wheel{i}", "kind": "zlac706", "id": i,
                      "heartbeat_ms": 10} for i in (1, 2)]),
    ),
}  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", choices=sorted(FAMILIES), default="inspire_la")
    parser.add_argument("--buses", type=positive(int), default=1)
    parser.add_argument("--estops", type=positive(int), default=80)
    args = parser.parse_args()
    sim_arguments, bus_of = FAMILIES[args.family]
    busgate = shutil.which("busgate", path=str(Path(sys.executable).parent))
    sims = [subprocess.Popen([busgate, "sim", *sim_arguments], stdout=subprocess.PIPE, text=True)
            for _ in range(args.buses)]
    runners: list[BusRunner] = []
    try:
        for index, sim in enumerate(sims):
            port = sim.stdout.readline().split()[1]
            runners.append(build_bus(bus_of(f"bus{index}", port)).start())
        time.sleep(1.5)  # every device online
        worst, every, cpu = _estops(runners, args.estops)
    finally:
        for runner in runners:
            runner.stop()
        for sim in sims:
            sim.terminate()
            sim.wait()
    print(f"{args.buses} {args.family} bus(es), {args.estops} e-stops: hand-over → the worst "
          f"bus's first e-stop frame p50 {_us(worst, .5)} / p90 {_us(worst, .9)} µs, → every "
          f"device's first p50 {_us(every, .5)} / p90 {_us(every, .9)} µs; a bus thread's CPU "
          f"from its wake to its first frame p50 {_us(cpu, .5)} / p90 {_us(cpu, .9)} µs "
          f"({len(cpu)} woken from a wait)")
    return 0


def _estops(runners: list[BusRunner], count: int) -> tuple[list[float], list[float], list[float]]:
    """Each e-stop's worst bus (s, wall) to its first frame and to every device's, and each
    bus's CPU from its wake to its first frame."""
    marks: dict[str, dict[str, tuple[float, float]]] = {r.name: {} for r in runners}
    for runner in runners:
        _mark_frames(runner, marks[runner.name])
        for flag in (runner._estop_due, runner._wake):  # what a bus thread waits on
            _mark_wakes(flag, marks[runner.name])
    worst, every, cpu = [], [], []
    for turn in range(count):
        for runner in runners:
            for name, driver in runner.drivers.items():
                if driver.follow_preparation == ():  # streams from the start (Inspire LA)
                    runner.follow(name, 1000 + 100 * (turn % 5), "position")
        time.sleep(random.uniform(0.1, 0.15))
        for bus_marks in marks.values():
            bus_marks.clear()
            bus_marks["armed"] = (0.0, 0.0)
        handed = now()
        estops = [runner.estop() for runner in runners]
        let_estops_go(runners)
        for estop in estops:
            estop.result(2)
        worst.append(max(m["write"][1] for m in marks.values()) - handed)
        every.append(max(m["every"][1] for m in marks.values()) - handed)
        cpu += [m["write"][0] - m["woke"][0] for m in marks.values() if "woke" in m]
        for reset in [runner.reset_estop() for runner in runners]:
            reset.result(2)
        time.sleep(0.05)
    return worst, every, cpu


def _mark_frames(runner: BusRunner, marks: dict) -> None:
    """The write of the bus's first e-stop frame (``write``), and of the frame that made every
    device of the bus have one (``every``): any of a device's safe-stop frames (those of a
    fresh driver, which knows nothing of the device's mode), as its owner's frame hook gives
    it (a UART's bytes, a CAN frame's data and identifier)."""
    device_of = {}
    for name, driver in runner.drivers.items():
        for request in type(driver)(name, driver.device_id).safe_stop():
            wire = request.wire
            device_of[wire if isinstance(wire, bytes) else (wire.data, wire.arbitration_id)] = name
    stopped: set[str] = set()

    def tap(frame: tuple) -> None:
        device = device_of.get(frame[2] if frame[3] is None else (bytes(frame[2]), frame[3]))
        if device is None or "armed" not in marks:
            return
        if "write" not in marks:
            marks["write"] = (time.thread_time(), now())
            stopped.clear()
        stopped.add(device)
        if len(stopped) == len(runner.drivers) and "every" not in marks:
            marks["every"] = (time.thread_time(), now())

    runner.owner.tap = tap


def _mark_wakes(flag, marks: dict) -> None:
    wait = flag.wait

    def marked(timeout: float | None = None) -> bool:
        raised = wait(timeout)
        if raised and "armed" in marks and "woke" not in marks:
            marks["woke"] = (time.thread_time(), now())
        return raised

    flag.wait = marked


def _us(values: list[float], q: float) -> str:
    ordered = sorted(values)
    return f"{1e6 * ordered[min(len(ordered) - 1, int(q * len(ordered)))]:.0f}"


if __name__ == "__main__":
    sys.exit(main())
