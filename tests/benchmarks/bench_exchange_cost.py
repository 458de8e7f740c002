"""Where a bus thread's CPU goes, exchange by exchange; and what one timed wait costs here.

Not a test (pytest does not collect it). cProfile triples a bus thread's CPU (it charges
every Python call), which hides what the thread pays for by the call rather than by the
microsecond: sleeping and waking. This reads ``time.thread_time`` around the runner's seams
instead (a clock read at each end, a microsecond or so), while ``busgate bench`` runs its
case in this process on the simulator, and prints each seam's CPU per exchange. Seams nest
(an exchange's write is inside ``execution``), so the lines do not add up.

    .venv/bin/python tests/benchmarks/bench_exchange_cost.py [-- BENCH ARGUMENTS]

The bench arguments default to 3 Inspire LA, 10 ms follow, 20 Hz polls, 8 s. First it prints
the CPU one wait of 2 ms costs a thread with the bus threads' 1 ns timer slack, as the
runner waits (``Event.wait``), as a bare lock would (``Lock.acquire``) and as
``sleep_until`` sleeps (``time.sleep``): on this host's virtual machine the kernel's timer
and the switch back cost some 25-35 us, whatever Python does around them.
"""

from __future__ import annotations

import collections
import contextlib
import io
import json
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from busgate.gateway.bus import serial_owner
from busgate.gateway.bus.clock import tighten_timer_slack
from busgate.gateway.cli import main as busgate
from busgate.gateway.scheduler import execution, planner, runner, tickers

BENCH = ["--protocol", "inspire_la", "--ids", "1,2,3", "--follow-period-ms", "10",
         "--poll-hz", "20", "--seconds", "8"]  # fmt: skip
WAITS = 500

cpu_s: collections.Counter[str] = collections.Counter()
calls: collections.Counter[str] = collections.Counter()


def timed(holder: Any, name: str, label: str) -> None:
    """``holder.name`` (a method, or a function a module imported) charged to ``label``."""
    original = getattr(holder, name)
    cpu_s[label] = calls[label] = 0  # listed in the order declared

    def charged(*args: Any, **kwargs: Any) -> Any:
        started = time.thread_time()
        try:
            return original(*args, **kwargs)
        finally:
            cpu_s[label] += time.thread_time() - started
            calls[label] += 1

    setattr(holder, name, charged)


def wait_cost(wait: Callable[[], object]) -> float:
    """The CPU, in us, one ``wait()`` costs a thread with the bus threads' timer slack."""
    spent: list[float] = []

    def waiting() -> None:
        tighten_timer_slack()
        started = time.thread_time()
        for _ in range(WAITS):
            wait()
        spent.append((time.thread_time() - started) / WAITS * 1e6)

    thread = threading.Thread(target=waiting)
    thread.start()
    thread.join()
    return spent[0]


def main() -> int:
    arguments = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else BENCH
    never_set, held = threading.Event(), threading.Lock()
    held.acquire()
    for label, wait in [
        ("Event.wait(2 ms)", lambda: never_set.wait(0.002)),
        ("Lock.acquire(timeout=2 ms)", lambda: held.acquire(timeout=0.002)),
        ("time.sleep(2 ms)", lambda: time.sleep(0.002)),
    ]:
        print(f"{label:28s} {wait_cost(wait):6.1f} us of CPU per wait")

    timed(runner.BusRunner, "_drain_inbox", "inbox")
    timed(runner.BusRunner, "_step", "step")
    timed(runner.BusRunner, "_wait_until", "  wait (runner)")
    timed(runner.BusRunner, "_pause", "    pause: Event.wait")
    timed(runner, "sleep_until", "    sleep_until (runner)")
    timed(planner.BusPlanner, "decide", "  decide")
    timed(tickers.FollowTicker, "build", "    follow tick build")
    timed(execution.Execution, "run", "  execution")
    timed(serial_owner, "sleep_until", "    sleep_until (owner)")
    timed(serial_owner.SerialBusOwner, "_write", "    write")
    timed(serial_owner.SerialBusOwner, "_wait_reply", "    reply wait")
    timed(runner.BusRunner, "_publish", "publish")
    whole: dict[str, float] = {}
    run = runner.BusRunner._run

    def measured_run(self: runner.BusRunner) -> None:
        started, wall = time.thread_time(), time.monotonic()
        try:
            run(self)
        finally:
            whole["cpu_s"], whole["wall_s"] = time.thread_time() - started, time.monotonic() - wall

    runner.BusRunner._run = measured_run  # type: ignore[method-assign]
    report = io.StringIO()
    with contextlib.redirect_stdout(report):
        busgate(["bench", "--json", *arguments])
    exchanges = calls["  execution"]
    figures = json.loads(report.getvalue())
    print(f"busgate bench {' '.join(arguments)}: {figures['frames_out_per_s']} frames/s")
    print(f"bus thread: {1000 * whole['cpu_s']:.0f} ms of CPU in {whole['wall_s']:.1f} s "
          f"({100 * whole['cpu_s'] / whole['wall_s']:.1f} %), {exchanges} exchanges, "
          f"{whole['cpu_s'] / exchanges * 1e6:.0f} us each")  # fmt: skip
    print(f"  {'seam':28s} {'us/exchange':>11s} {'calls':>7s} {'us/call':>8s}")
    for label, spent in cpu_s.items():
        per_call = spent / calls[label] * 1e6 if calls[label] else 0.0
        print(f"  {label:28s} {spent / exchanges * 1e6:11.1f} {calls[label]:7d} {per_call:8.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
