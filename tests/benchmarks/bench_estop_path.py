"""An e-stop's path through the bus threads: from its hand-over to its first frame's write.

Not a test (pytest does not collect it). ``--buses`` buses of three Inspire LA each (921600
baud, every device streaming at 10 ms), each on a ``busgate sim`` of its own process, run in
this one process as the gateway runs them (``build_bus``). ``--estops`` times, at a random
moment, every bus is handed an e-stop as the gateway hands them (``runner.estop`` each, then
``let_estops_go``), and each bus's first e-stop frame is timed from its owner's frame hook;
then the e-stop is reset and the streams start again. Printed, in µs at p50 / p90:

- the worst bus of each e-stop, from the first hand-over to its first frame's write (wall);
- per bus, the bus thread's CPU from its wake (the flag it waited on raised) to that write.

With one bus, the second is the Python an e-stop's frame waits for; with several, their bus
threads take turns on this one interpreter, so the first figure grows with their sum.

    .venv/bin/python tests/benchmarks/bench_estop_path.py [--buses 1] [--estops 80]

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

from busgate.codecs import inspire_la as la
from busgate.gateway.bus.clock import now
from busgate.gateway.scheduler.runner import BusRunner, let_estops_go
from busgate.gateway.service.assembly import build_bus
from busgate.schemas.config import SerialBus

IDS = (1, 2, 3)
#: The e-stop frames (single control 0x23) of the devices: the frames timed.
ESTOP_FRAMES = frozenset(la.encode(la.ControlCommand(i, la.ControlCode.ESTOP)) for i in IDS)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--buses", type=int, default=1)
    parser.add_argument("--estops", type=int, default=80)
    args = parser.parse_args()
    busgate = shutil.which("busgate", path=str(Path(sys.executable).parent))
    sims = [subprocess.Popen([busgate, "sim", "inspire_la", "--ids", "1,2,3"],
                             stdout=subprocess.PIPE, text=True) for _ in range(args.buses)]
    runners: list[BusRunner] = []
    try:
        for index, sim in enumerate(sims):
            port = sim.stdout.readline().split()[1]
            runners.append(build_bus(_bus(f"uart{index}", port)).start())
        time.sleep(1.5)  # every device online
        worst, cpu = _estops(runners, args.estops)
    finally:
        for runner in runners:
            runner.stop()
        for sim in sims:
            sim.terminate()
            sim.wait()
    print(f"{args.buses} bus(es), {args.estops} e-stops: hand-over → the worst bus's first "
          f"e-stop frame p50 {_us(worst, .5)} / p90 {_us(worst, .9)} µs; a bus thread's CPU "
          f"from its wake to that frame p50 {_us(cpu, .5)} / p90 {_us(cpu, .9)} µs "
          f"({len(cpu)} woken from a wait)")
    return 0


def _bus(name: str, port: str) -> SerialBus:
    devices = [{"name": f"{name}-la{i}", "kind": "inspire_la", "id": i, "follow_period_ms": 10}
               for i in IDS]
    return SerialBus(name=name, transport="serial", port=port, baudrate=921_600,
                     devices=devices)


def _estops(runners: list[BusRunner], count: int) -> tuple[list[float], list[float]]:
    """Each e-stop's worst bus (s, wall), and each bus's CPU from its wake to its frame."""
    marks: dict[str, dict[str, tuple[float, float]]] = {r.name: {} for r in runners}
    for runner in runners:
        _mark_frames(runner, marks[runner.name])
        for flag in (runner._estop_due, runner._wake):  # what a bus thread waits on
            _mark_wakes(flag, marks[runner.name])
    worst, cpu = [], []
    for turn in range(count):
        for runner in runners:
            for device in runner.drivers:
                runner.follow(device, 1000 + 100 * (turn % 5))
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
        cpu += [m["write"][0] - m["woke"][0] for m in marks.values() if "woke" in m]
        for reset in [runner.reset_estop() for runner in runners]:
            reset.result(2)
        time.sleep(0.05)
    return worst, cpu


def _mark_frames(runner: BusRunner, marks: dict) -> None:
    def tap(frame: tuple) -> None:
        if frame[2] in ESTOP_FRAMES and "armed" in marks and "write" not in marks:
            marks["write"] = (time.thread_time(), now())

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
