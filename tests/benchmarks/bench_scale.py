"""How many serial buses one host drives while every timing rule holds, and at what CPU; and
how long an e-stop takes to reach every bus, beside a bare loop's.

Not a test (pytest does not collect it). Everything on this machine, on 127.0.0.1 with
multicast scouting off: the simulators, the daemon (``busgate run``) and the bare loops as
child processes, the streaming client here; every process ended by its PID.

    .venv/bin/python tests/benchmarks/bench_scale.py [--buses 1,2,4,6,8] [--daemons 2] [--runs 2]
        [--workers 1,auto] [--estop 50] [--estop-hop] [--realtime 50]

For each N: N simulated UARTs of 3 Inspire LA actuators at 921600 baud (``busgate sim``,
each recording its wire). First the gateway: one daemon drives all N buses (``--daemons K``:
K daemons, the buses split evenly, each its own gateway name), every device followed at 10 ms
and polled at 20 Hz, a client here putting a new target to every device
at 50 Hz over zenoh. Then, on the same simulators for the same time, the yardstick: N bare
sleep-then-spin loops in one process (one thread each, ``busgate bench --baseline``'s loop)
writing each bus's follow frame every 10 ms with targets a thread there updates at 50 Hz.

``--workers LIST`` (comma-separated, each ``auto`` or a count): the gateway part of each step
runs once per value, with ``[gateway] workers`` set to it in every daemon's config (without
the option the key is not written: the gateway's default, ``auto``); each row names its value
(``unset`` without the option).
The bare loops run once per N, whatever the list.

Host side, as each writer timed its own writes: the follow intervals under the period (the
gateway's stats keep only the shortest, so for it "0" or "some") and the shortest interval
less the period, the interval error p50 (median over buses) and p99 (worst bus); for the
gateway also its smallest gap and timeouts, from its stats key (since its start: the warm-up
included). Device side, from the simulators' records: the follow error p50/p99, the
intervals under the period and the gaps under the 1 ms minimum. The simulators wait in
``select`` rather than busy-poll (N spinning simulators would take the two cores from what
is measured), so a device-side time is late by their wake-up, some 0.1 ms and more under
load, the bare loops' as much as the gateway's: a frame read late looks longer, and the gap
after it shorter, than on a wire. CPU: utime + stime from /proc, % of one core; the gateway's
is its daemons' and all their descendants' (workers), listed from /proc at the end of the
window; the daemon's split into its bus threads, its other Python threads and the rest
(zenoh's), and the simulators' together.

``--realtime PRIORITY`` (1–98; default: none): ``realtime_priority`` on every bus, as a
robot's config has it (``deploy/config/robot.toml``): every thread of the gateway's processes
under SCHED_FIFO at that priority; every thread of the bare loops and of the e-stop yardstick
too, so that both sides are measured alike; and the simulators one priority above, as
devices that no host thread delays. It needs the privilege (root, or ``RLIMIT_RTPRIO``):
without it the gateway warns and runs at normal priority, and the bare loops stop with the
kernel's refusal.

``--estop-hop`` (with ``--estop``): also the first hop of each e-stop, its put to the start
of the gateway's e-stop callback (zenoh carrying the put over loopback, and the gateway's
interpreter taken by zenoh's thread), which no busgate code comes before: a probe on the
daemons' ``PYTHONPATH`` (``estop_hop/sitecustomize.py``) notes when each callback began. Per
e-stop the slowest daemon's; p50, p99 and max under the e-stop table. Beside it, zenoh's hop
with no gateway behind it: after each e-stop the bench puts on ``bench/hop``, which a process
that does nothing else takes (``zenoh_hop_listener.py``, its callback declared as the
gateway's), timed the same way.

``--estop COUNT`` (default 0: none): after each gateway's measured window, a second phase on
the same daemons, simulators and traffic (the streams, polls and the client's 50 Hz targets
go on): COUNT e-stops, each after a uniformly random 150–400 ms (so they land anywhere in the
bus schedule), each a put on ``busgate/*/estop``, followed after 100 ms by a put on each
gateway's ``estop/reset`` (every device enabled again, holding still; the client's next
target starts its stream again) and a 150 ms pause for the streams to be running again. Its
latency on a bus: the start on that bus's wire (the simulator's record) of the first e-stop
frame (single control 0x23, ``InspireLaDriver.safe_stop``) after the put, less the put's
time; per e-stop, the worst bus. The yardstick, once per N after the bare loops: N threads in
one child process carrying the gateway's traffic (each bus a follow frame every 10 ms on its
grid and every device's status poll at 20 Hz, each poll an exchange: written, its reply
read, then the 1 ms gap; a poll only where it ends before the next follow frame is due, as
the gateway's planner has it) and the same e-stops at random moments, which the child
triggers itself, noting each signal's time: each thread finishes the exchange in flight,
waits the 1 ms gap and writes the gateway's e-stop frame to each device (each an exchange);
a reset 100 ms later enables each device (the gateway also sends a move to where it is) and
the follow frames start again. Its latency: the first e-stop frame's start on the wire less
the signal's time. The same clock on every side: ``time.perf_counter``, CLOCK_MONOTONIC on
Linux (the records', the bench's and the daemon's). Printed for both: p50, p99 and max of the
worst-bus latency, the gateway's added latency (its p50 and p99 less the bare loops'), how
many e-stops found every bus streaming (a follow frame in the 30 ms before), how many resets
reached every bus (an enable frame on each before the next e-stop), how many e-stops missed
a bus (no e-stop frame on it before the next), and the status polls per second per bus over
the phase, all from the records.

Then, once per N, the CPU yardstick: the e-stop yardstick's loops for the same seconds with
no e-stop, carrying the gateway's traffic (the follow frames, the 20 Hz polls as exchanges,
the gap), where the bare loops above write follow frames only. The summary divides each
gateway's CPU by theirs (``× bare, polls``).

A summary table closes the run: one row per step and writer.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import random
import select
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import serial
import zenoh
from bench_zenoh import Daemon, free_endpoint, serial_bus, wait_ready
from zenoh_hop_listener import KEY as HOP_KEY

from busgate.codecs import inspire_la as la
from busgate.gateway.bus.clock import (
    WakeUpLead,
    ask_realtime,
    now,
    tighten_timer_slack,
    tune_interpreter,
)
from busgate.gateway.bus.request import LinkTiming, Request
from busgate.gateway.bus.stats import percentile
from busgate.gateway.cli.bench import (
    bare_follow_loop,
    cpu_s,
    follow_frame_names,
    interval_figures,
)
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.scheduler.planner import HOST_SLACK_S
from busgate.gateway.sim.process import SimProcess
from busgate.gateway.sim.wire_analysis import analyse, load_records
from busgate.schemas.families import PROTOCOLS
from busgate.schemas.zenoh_session import session_config

IDS = (1, 2, 3)
BAUD = 921_600
PERIOD_S = 0.010
POLL_HZ = 20
TARGET_HZ = 50
WARM_UP_S = 3.0
MIN_GAP_S = PROTOCOLS["inspire_la"].timing.default_gap_s
SIM_ARGUMENTS = ("--ids", ",".join(map(str, IDS)), "--baudrate", str(BAUD), "--busy-poll-ms", "0")

#: The e-stop phase: the random wait before each e-stop, the reset after it, and the pause
#: after the reset for the streams to run again (the reset's frames, then the client's next
#: target, within 20 ms).
ESTOP_DELAY_S = (0.150, 0.400)
ESTOP_HOLD_S = 0.100
ESTOP_RESUME_S = 0.150
#: A bus counts as streaming at an e-stop with a follow frame this soon before it.
STREAMING_S = 3 * PERIOD_S
#: The gateway's warning lines of each e-stop and reset, left out of its log as shown.
EXPECTED_LOG = ("e-stop of every bus", "e-stop reset of every bus")
#: ``--realtime``: the SCHED_FIFO priority of every bus thread, the gateway's and the bare ones.
REALTIME: int | None = None
#: ``--estop-hop``: the daemons started with the probe that notes each e-stop callback's start.
ESTOP_HOP = False
#: The probe's folder, put first on the daemons' ``PYTHONPATH`` under ``--estop-hop``.
HOP_PROBE = Path(__file__).resolve().parent / "estop_hop"


def drivers_of(bus: int) -> list[InspireLaDriver]:
    return [InspireLaDriver(f"bus{bus}-{i}", i) for i in IDS]


def target(t_s: float, bus: int, index: int) -> dict:
    """Device ``index`` of bus ``bus`` at ``t_s``: the driver's follow sample, each device of
    every bus its own phase."""
    return InspireLaDriver.follow_sample(t_s, bus * len(IDS) + index)


def control_hex(code: la.ControlCode) -> str:
    """A single control frame's instruction and code, as they sit in a record's ``wire``
    (after the header, the length and the id): ``040023`` for the e-stop."""
    return f"0400{code:02x}"


# -- the gateway ---------------------------------------------------------------------------


class ScaleDaemon(Daemon):
    """``busgate run`` as ``Daemon`` starts it, but with ``[gateway] workers`` when given, and
    its log (each e-stop and reset logs a warning) kept in a file, shown when it stops."""

    def __init__(
        self, scratch: Path, endpoint: str, buses: str, name: str, workers: str | None
    ) -> None:
        setting = "" if workers is None else f"workers = {toml_workers(workers)}\n"
        self.name = name
        self.log = scratch / f"{name}-{workers}.log"
        with self.log.open("w") as log:
            super().__init__(scratch, endpoint, buses, name, gateway=setting, stderr=log)

    def stop(self) -> None:
        super().stop()
        for text in self.log.read_text().splitlines():
            if not any(expected in text for expected in EXPECTED_LOG):
                print(f"  [{self.name}] {text}", file=sys.stderr)


def realtime_field() -> str:
    return "" if REALTIME is None else f"realtime_priority = {REALTIME}\n"


def realtime_thread(who: str) -> None:
    """The calling bare thread under SCHED_FIFO at ``REALTIME``, as the gateway's bus threads."""
    if REALTIME is not None and not ask_realtime(REALTIME, who):
        raise SystemExit(f"{who}: SCHED_FIFO {REALTIME} refused")


def realtime_label() -> str:
    return "" if REALTIME is None else f", bus threads SCHED_FIFO {REALTIME}"


def realtime_device(pid: int) -> None:
    """Under ``--realtime``, every thread of a simulator at one priority above the bus
    threads: it stands for a device, whose replies and wire record no gateway thread (nor a
    bare loop's) ever delays."""
    if REALTIME is None:
        return
    for task in os.listdir(f"/proc/{pid}/task"):
        os.sched_setscheduler(int(task), os.SCHED_FIFO, os.sched_param(REALTIME + 1))


@contextlib.contextmanager
def hop_listener(scratch: Path):
    """Under ``--estop-hop``, the idle listener of ``bench/hop`` in a process of its own:
    yields ``(its endpoint, the file its notes go to once it ends)``, or ``None`` without."""
    if not ESTOP_HOP:
        yield None
        return
    endpoint, notes = free_endpoint(), scratch / "floor-hops.txt"
    listener = subprocess.Popen(
        [sys.executable, str(Path(__file__).parent / "zenoh_hop_listener.py"), endpoint,
         str(notes)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        listener.stdout.readline()  # ready
        yield endpoint, notes
    finally:
        listener.stdin.close()
        try:
            listener.wait(10)
        except subprocess.TimeoutExpired:
            listener.kill()


@contextlib.contextmanager
def hop_probe(notes: Path):
    """Under ``--estop-hop``, the environment a daemon started within is given: the probe
    first on its ``PYTHONPATH``, noting in ``notes``; yields ``notes`` (``None`` without)."""
    if not ESTOP_HOP:
        yield None
        return
    before = dict(os.environ)
    os.environ["PYTHONPATH"] = os.pathsep.join(
        [str(HOP_PROBE), *filter(None, [before.get("PYTHONPATH")])]
    )
    os.environ["BUSGATE_ESTOP_HOP"] = str(notes)
    try:
        yield notes
    finally:
        os.environ.clear()
        os.environ.update(before)


def noted_times(notes: Path) -> list[float]:
    """The callback starts the probe noted (none: the file was never written)."""
    return sorted(float(line) for line in notes.read_text().split()) if notes.exists() else []


def hop_figures(signals: list[float], hops: list[list[float]]) -> dict | None:
    """Per put in ``signals``, the slowest of ``hops``' callbacks to start after it (each
    daemon's, or the idle listener's); p50, p99, max (ms)."""
    if not hops:
        return None
    worst = []
    for i, signal in enumerate(signals):
        until = signals[i + 1] if i + 1 < len(signals) else math.inf
        latency = slowest_first(signal, until, hops)
        if latency is not None:
            worst.append(latency)
    worst.sort()
    return {
        "count": len(worst),
        "p50_ms": ms(percentile(worst, 0.5)),
        "p99_ms": ms(percentile(worst, 0.99)),
        "max_ms": ms(worst[-1] if worst else None),
    }


def realtime_arguments() -> list[str]:
    return [] if REALTIME is None else ["--realtime", str(REALTIME)]


def toml_workers(workers: str) -> str:
    return '"auto"' if workers == "auto" else workers


def gateway_step(
    scratch: Path,
    ports: list[str],
    seconds: float,
    sims: list[SimProcess],
    daemons: int,
    workers: str | None,
    estops: int,
) -> dict:
    """The N buses, split over ``daemons`` daemons (``bench0``, ``bench1`` …), under a
    streaming client: the window, the daemons' CPU (their workers' included) by thread, their
    stats (host side), and the simulators' CPU; then, with ``estops``, the e-stop phase."""

    def sims_cpu_s() -> float:
        return sum(cpu_s(f"/proc/{sim.process.pid}/stat") for sim in sims)

    gateways = [f"bench{k}" for k in range(daemons)]
    owner = {f"bus{n}": gateways[n * daemons // len(ports)] for n in range(len(ports))}
    endpoints = [free_endpoint() for _ in gateways]
    started_daemons: list[ScaleDaemon] = []
    hop_notes: list[Path | None] = []
    stats: dict[str, dict] = {}
    phase: dict = {}
    with contextlib.ExitStack() as stack:
        floor = stack.enter_context(hop_listener(scratch))
        stack.callback(lambda: [daemon.stop() for daemon in started_daemons])
        for gateway, endpoint in zip(gateways, endpoints, strict=True):
            config = "".join(
                serial_bus(
                    bus,
                    ports[n],
                    "inspire_la",
                    list(IDS),
                    BAUD,
                    poll_hz=POLL_HZ,
                    follow_period_ms=round(PERIOD_S * 1000),
                    bus_fields=realtime_field(),
                )
                for n, bus in enumerate(owner)
                if owner[bus] == gateway
            )
            with hop_probe(scratch / f"{gateway}-{label(workers)}-hops.txt") as notes:
                started_daemons.append(ScaleDaemon(scratch, endpoint, config, gateway, workers))
                hop_notes.append(notes)
        listeners = [floor[0]] if floor else []
        with zenoh.open(session_config(connect=endpoints + listeners)) as session:
            for gateway in gateways:
                wait_ready(session, gateway=gateway)
            session.declare_subscriber(
                "busgate/*/bus/*/stats",
                lambda sample: stats.__setitem__(
                    str(sample.key_expr), json.loads(sample.payload.to_bytes())
                ),
            )
            devices = {
                f"busgate/{owner[f'bus{n}']}/dev/bus{n}-{ident}": (n, index)
                for n in range(len(ports))
                for index, ident in enumerate(IDS)
            }
            for key in devices:
                session.get(f"{key}/cmd", payload='{"op":"enable"}', timeout=5).recv()
            stop = threading.Event()
            streamer = threading.Thread(target=stream, args=(session, devices, stop))
            streamer.start()
            try:
                time.sleep(WARM_UP_S)
                roots = [daemon.process.pid for daemon in started_daemons]
                before, started = dict(stats), now()
                processes_before, threads_before = tree_cpu_s(roots)
                sims_before = sims_cpu_s()
                time.sleep(seconds)
                # Listed at the end of the window, while every worker still runs: a worker
                # that ended (restarted) in the window loses the time it had counted since its
                # start (its successor counts from its own start); its parent counts a reaped
                # child's time only in cutime/cstime, which this leaves out.
                processes, threads = tree_cpu_s(roots)
                ended = now()
                sims_cpu = sims_cpu_s() - sims_before
                time.sleep(1.5)  # one more stats sample, covering the window
                after = dict(stats)
                if estops:
                    phase = estop_phase(session, gateways, estops, bool(floor))
                    time.sleep(0.1)  # the last callback noted
                    phase["hops"] = [noted_times(notes) for notes in hop_notes if notes]
            finally:
                stop.set()
                streamer.join()
    if floor:  # the listener wrote its notes as it ended
        phase["floor"] = [noted_times(floor[1])]
    buses = list(after.values())
    elapsed = ended - started
    return {
        "workers": label(workers),
        "window": (started, ended),
        "host_min_ms": 1000 * min(bus["follow_error_min_s"] for bus in buses),
        # The stats keep the shortest interval, not a count: none is under when it is not.
        "host_under": 0 if min(bus["follow_error_min_s"] for bus in buses) >= 0 else None,
        "host_p50_ms": 1000 * statistics.median(bus["follow_error_p50_s"] for bus in buses),
        "host_p99_ms": 1000 * max(bus["follow_error_p99_s"] for bus in buses),
        "host_gap_ms": 1000 * min(bus["smallest_gap_s"] for bus in buses),
        "timeouts": sum(bus["timeouts"] for bus in buses)
        - sum(bus["timeouts"] for bus in before.values()),
        "processes": len(processes),
        "cpu_percent": 100 * used_since(processes, processes_before) / elapsed,
        "threads_cpu_percent": {
            role: 100 * used / elapsed for role, used in by_role(threads, threads_before).items()
        },
        "simulators_cpu_percent": 100 * sims_cpu / elapsed,
        "estop_phase": phase,
    }


def estop_phase(session: zenoh.Session, gateways: list[str], count: int, floor: bool) -> dict:
    """``count`` e-stops of every gateway at random moments, each reset: when each was put
    (``signals``, as the bare loops' are named), when each reset was (``resets``), and the
    phase's window; with ``floor``, a put on the idle listener's key after each e-stop, and
    when (``floor_signals``)."""
    chance = random.Random()
    puts: list[float] = []
    floor_puts: list[float] = []
    resets: list[float] = []
    started = now()
    for _ in range(count):
        time.sleep(chance.uniform(*ESTOP_DELAY_S))
        puts.append(now())
        session.put("busgate/*/estop", b"")
        if floor:
            floor_puts.append(now())
            session.put(HOP_KEY, b"")
        time.sleep(ESTOP_HOLD_S)
        resets.append(now())
        for gateway in gateways:
            session.put(f"busgate/{gateway}/estop/reset", b"")
        time.sleep(ESTOP_RESUME_S)
    return {
        "signals": puts,
        "floor_signals": floor_puts,
        "resets": resets,
        "window": (started, now()),
    }


def descendants(root: int) -> list[int]:
    """``root`` and every process under it, from /proc (each thread's ``children``)."""
    found: list[int] = []
    todo = [root]
    while todo:
        pid = todo.pop()
        found.append(pid)
        with contextlib.suppress(OSError):  # gone meanwhile
            for task in Path(f"/proc/{pid}/task").iterdir():
                with contextlib.suppress(OSError):
                    todo += map(int, (task / "children").read_text().split())
    return found


def tree_cpu_s(
    roots: list[int],
) -> tuple[dict[int, float], dict[tuple[int, int], tuple[str, float]]]:
    """CPU seconds of the processes under ``roots`` (themselves included) by PID, and of
    each of their threads by (PID, TID) with its role: the bus threads (named ``bus-<bus>``),
    the other Python threads (the event loop's: publishing), and the rest (zenoh's, Rust)."""
    processes: dict[int, float] = {}
    threads: dict[tuple[int, int], tuple[str, float]] = {}
    for pid in (pid for root in roots for pid in descendants(root)):
        processes[pid] = cpu_s(f"/proc/{pid}/stat")
        with contextlib.suppress(OSError):
            for task in Path(f"/proc/{pid}/task").iterdir():
                with contextlib.suppress(OSError):
                    name = (task / "comm").read_text().strip()
                    role = (
                        "bus" if name.startswith("bus-") else "python" if name == "python" else
                        "zenoh"
                    )  # fmt: skip
                    threads[pid, int(task.name)] = (role, cpu_s(str(task / "stat")))
    return processes, threads


def used_since(after: dict, before: dict) -> float:
    """CPU seconds used between two ``tree_cpu_s`` counts, summed over what ran at the end
    (one that started since counts from its start); NaN (gone while read) counts 0."""
    used = (value - before.get(key, 0.0) for key, value in after.items())
    return sum(value for value in used if not math.isnan(value))


def by_role(after: dict, before: dict) -> dict[str, float]:
    """The threads' CPU seconds between two ``tree_cpu_s`` counts, by role."""
    used: dict[str, float] = {}
    for key, (role, value) in after.items():
        spent = value - before.get(key, (role, 0.0))[1]
        if not math.isnan(spent):
            used[role] = used.get(role, 0.0) + spent
    return used


def stream(session: zenoh.Session, devices: dict[str, tuple[int, int]], stop) -> None:
    """A new target for every device (key → bus and index) at ``TARGET_HZ``, until ``stop``."""
    publishers = {
        key: (session.declare_publisher(f"{key}/follow"), where) for key, where in devices.items()
    }
    start = now()
    deadline = start
    while not stop.is_set():
        t = now() - start
        for publisher, (n, index) in publishers.values():
            publisher.put(json.dumps(target(t, n, index)))
        deadline += 1 / TARGET_HZ
        time.sleep(max(0.0, deadline - now()))


# -- the bare loops (a child process: ``--bare``) -------------------------------------------


def bare_step(ports: list[str], seconds: float) -> dict:
    """N bare loops in a child process of their own: its window, host-side figures, CPU."""
    child = subprocess.run(
        [
            sys.executable,
            __file__,
            "--bare",
            ",".join(ports),
            "--seconds",
            str(seconds),
            *realtime_arguments(),
        ],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).parent,
    )
    return json.loads(child.stdout)


class BareTargets:
    """Each bare bus's drivers and their latest follow targets, which ``feed`` updates at
    ``TARGET_HZ`` (as the gateway's client puts them) until ``stop`` is set."""

    def __init__(self, buses: int, started: float) -> None:
        self.drivers = [drivers_of(n) for n in range(buses)]
        self.started = started
        self.latest = {
            (n, index): driver.follow_target(target(0.0, n, index))
            for n, bus in enumerate(self.drivers)
            for index, driver in enumerate(bus)
        }

    def feed(self, stop: threading.Event) -> None:
        while not stop.wait(1 / TARGET_HZ):
            t = now() - self.started
            for n, bus in enumerate(self.drivers):
                for index, driver in enumerate(bus):
                    self.latest[n, index] = driver.follow_target(target(t, n, index))


def bare_loops(ports: list[str], seconds: float) -> dict:
    tune_interpreter()  # as the daemon does
    started = now() + 0.2
    targets = BareTargets(len(ports), started)
    drivers, latest = targets.drivers, targets.latest
    end = started + seconds
    stop = threading.Event()
    figures: list[dict] = []

    def loop(n: int) -> None:
        bus = drivers[n]
        realtime_thread(f"bare loop {n}")

        def request_of() -> Request:
            return InspireLaDriver.follow_request(
                [(driver, latest[n, index]) for index, driver in enumerate(bus)]
            )

        time.sleep(max(0.0, started - now()))
        starts = bare_follow_loop(ports[n], BAUD, request_of, PERIOD_S, end)
        figures.append(interval_figures(starts, PERIOD_S))

    threads = [threading.Thread(target=loop, args=(n,)) for n in range(len(ports))]
    feeder = threading.Thread(target=targets.feed, args=(stop,))
    cpu_before = time.process_time()
    for thread in [*threads, feeder]:
        thread.start()
    for thread in threads:
        thread.join()
    stop.set()
    feeder.join()
    ended = now()
    return {
        "window": (started, ended),
        "host_min_ms": min(f["follow_error_min_ms"] for f in figures),
        "host_under": sum(f["follow_intervals_under_period"] for f in figures),
        "host_p50_ms": statistics.median(f["follow_error_p50_ms"] for f in figures),
        "host_p99_ms": max(f["follow_error_p99_ms"] for f in figures),
        "cpu_percent": 100 * (time.process_time() - cpu_before) / (ended - started),
    }


# -- the e-stop yardstick (a child process: ``--bare-estop``) -------------------------------

#: Each bus thread's wake-up lateness, learnt as ``sleep_until`` learns it (per thread).
LEAD = WakeUpLead()
TIMING = LinkTiming(
    protocol="inspire_la",
    protocol_timing=PROTOCOLS["inspire_la"].timing,
    can=False,
    rate=BAUD,
    margin_s=0.002,  # a bus's default reply margin
    gap_s=MIN_GAP_S,
)
#: A wake-up that never comes: a wait the e-stop does not cut short (the gap before its frames).
NEVER = threading.Event()


def bare_estop_step(ports: list[str], count: int, seconds: float = 0.0) -> dict:
    """The e-stop yardstick in a child process of its own: its e-stop signals' and resets'
    times, its window, polls and timeouts, CPU; with no e-stop, its loops for ``seconds``
    (the same traffic as the gateway's, for its CPU)."""
    child = subprocess.run(
        [
            sys.executable,
            __file__,
            "--bare-estop",
            ",".join(ports),
            "--estop",
            str(count),
            *(["--seconds", str(seconds)] if seconds else []),
            *realtime_arguments(),
        ],
        stdout=subprocess.PIPE,
        text=True,
        check=True,
        cwd=Path(__file__).parent,
    )
    return json.loads(child.stdout)


def wait_until(deadline: float, wake: threading.Event) -> None:
    """``sleep_until`` that returns as soon as ``wake`` is set: sleep (on ``wake``) until the
    learnt lead before ``deadline``, then spin."""
    lead = LEAD.lead_s
    remaining = deadline - now()
    if remaining > lead:
        if wake.wait(remaining - lead):
            return
        LEAD.learn(now() - (deadline - lead))
    while now() < deadline and not wake.is_set():
        pass


def exchange(fd: int, request: Request) -> tuple[float, bool]:
    """Write ``request``, then read until its reply (or its timeout, as the gateway's): when
    the line went idle (the reply read, or the frame's last byte gone), and whether it was
    answered. Anything left on the line before is read and dropped."""
    while select.select([fd], [], [], 0)[0] and os.read(fd, 4096):
        pass
    os.write(fd, request.wire)
    start = now()
    expected = request.expected
    if expected is None:
        return start + TIMING.wire_time(request.wire), True
    deadline = start + TIMING.worst_case(request)
    decoder = la.ReplyDecoder()
    while select.select([fd], [], [], max(0.0, deadline - now()))[0]:
        decoder.feed(os.read(fd, 4096))
        if any(expected.matches(event) for event in list(decoder.events())):
            return now(), True
    return now(), False


def bare_estop_loops(ports: list[str], count: int, seconds: float) -> dict:
    """N bus threads with the gateway's traffic, and ``count`` e-stops (each reset) at random
    moments, signalled by this thread to each bus thread; with none, ``seconds`` of the
    traffic alone. CPU over the phase."""
    tune_interpreter()  # as the daemon does
    started = now() + 0.2
    targets = BareTargets(len(ports), started)
    drivers, latest = targets.drivers, targets.latest
    wakes = [threading.Event() for _ in ports]
    pending: list[deque[str]] = [deque() for _ in ports]
    done = threading.Event()
    totals = {"polls": 0, "timeouts": 0, "follow_frames": 0}
    totals_lock = threading.Lock()

    def control(code: la.ControlCode) -> list[Request]:
        return [Request.of(la, la.ControlCommand(i, code), idempotent=True) for i in IDS]

    def loop(n: int) -> None:
        bus, wake = drivers[n], wakes[n]
        polls = [request for driver in bus for request in driver.poll()]
        stops, enables = control(la.ControlCode.ESTOP), control(la.ControlCode.ENABLE)
        poll_period = 1 / POLL_HZ
        poll_due = [started + (k + 0.5) * poll_period / len(polls) for k in range(len(polls))]
        next_follow, streaming, line_free = started, True, -math.inf
        counts = {"polls": 0, "timeouts": 0, "follow_frames": 0}
        tighten_timer_slack()
        realtime_thread(f"bare e-stop loop {n}")

        def run(requests: list[Request]) -> float:
            """Each of ``requests`` an exchange, each after the gap: when the line is idle."""
            idle = line_free
            for request in requests:
                wait_until(idle + MIN_GAP_S, NEVER)
                idle, answered = exchange(fd, request)
                counts["timeouts"] += not answered
            return idle

        with serial.Serial(ports[n], BAUD, timeout=0, write_timeout=0.5) as handle:
            fd = handle.fileno()
            time.sleep(max(0.0, started - now()))
            while not done.is_set():
                if wake.is_set():
                    wake.clear()
                    while pending[n]:  # the exchange in flight has ended: the gap, the frames
                        if pending[n].popleft() == "estop":
                            line_free, streaming = run(stops), False
                        else:  # the reset: enabled again, a new stream starts now
                            line_free, streaming = run(enables), True
                            next_follow = now()
                    continue
                moment = now()
                ready = line_free + MIN_GAP_S
                follow_due = next_follow if streaming else math.inf
                poll = min(range(len(polls)), key=poll_due.__getitem__)
                if moment >= ready and follow_due <= moment:
                    request = InspireLaDriver.follow_request(
                        [(driver, latest[n, index]) for index, driver in enumerate(bus)]
                    )
                    line_free, _ = exchange(fd, request)
                    next_follow += PERIOD_S  # on its grid, as the bare follow loop
                    counts["follow_frames"] += 1
                    continue
                fits = moment + TIMING.worst_case(polls[poll]) + HOST_SLACK_S <= follow_due
                if moment >= ready and poll_due[poll] <= moment and fits:
                    line_free, answered = exchange(fd, polls[poll])
                    counts["polls"] += 1
                    counts["timeouts"] += not answered
                    late = moment - poll_due[poll] > poll_period  # skipped, as the planner's
                    poll_due[poll] = moment if late else poll_due[poll] + poll_period
                    continue
                if poll_due[poll] > moment:
                    wake_at = min(poll_due[poll], follow_due)
                elif fits:
                    wake_at = ready  # due, and it fits: after the gap
                else:
                    wake_at = follow_due  # after the follow frame it would delay
                wait_until(max(ready, wake_at), wake)
        with totals_lock:
            for name, value in counts.items():
                totals[name] += value

    failures: list[BaseException] = []

    def guarded(n: int) -> None:
        try:
            loop(n)
        except BaseException as exc:
            failures.append(exc)
            raise

    threads = [threading.Thread(target=guarded, args=(n,)) for n in range(len(ports))]
    feeder = threading.Thread(target=targets.feed, args=(done,))
    for thread in [*threads, feeder]:
        thread.start()
    time.sleep(max(0.0, started + 0.5 - now()))  # the loops under way
    chance = random.Random()
    signals: list[float] = []
    resets: list[float] = []
    phase_start, cpu_before = now(), time.process_time()
    if not count:
        time.sleep(seconds)

    def tell(what: str) -> None:
        for n in range(len(ports)):
            pending[n].append(what)
            wakes[n].set()

    for _ in range(count):
        time.sleep(chance.uniform(*ESTOP_DELAY_S))
        signals.append(now())
        tell("estop")
        time.sleep(ESTOP_HOLD_S)
        resets.append(now())
        tell("reset")
        time.sleep(ESTOP_RESUME_S)
    phase_end, cpu_after = now(), time.process_time()
    done.set()
    for wake in wakes:
        wake.set()
    for thread in [*threads, feeder]:
        thread.join()
    if failures:
        raise RuntimeError(f"{len(failures)} bare e-stop loop(s) failed") from failures[0]
    return {
        "signals": signals,
        "resets": resets,
        "window": (phase_start, phase_end),
        "cpu_percent": 100 * (cpu_after - cpu_before) / (phase_end - phase_start),
        **totals,
    }


# -- the device side -----------------------------------------------------------------------


def wire_figures(records: list[Path], window: tuple[float, float]) -> dict:
    follow = follow_frame_names(drivers_of(0))
    start, end = window
    figures = [
        analyse(
            [r for r in load_records(path) if start <= r.start <= end],
            min_gap_s=MIN_GAP_S,
            follow_frames=follow,
            follow_period_s=PERIOD_S,
        )
        for path in records
    ]
    return {
        "follow_frames": sum(f.follow_frames for f in figures),
        "device_under": sum(f.follow_intervals_under_period for f in figures),
        "device_gaps_under_1ms": sum(
            f.gaps_after_reply_below_minimum + f.gaps_after_silent_frame_below_minimum
            for f in figures
        ),
        "device_p50_ms": 1000 * statistics.median(f.follow_error_p50_s or 0.0 for f in figures),
        "device_p99_ms": 1000 * max(f.follow_error_p99_s or 0.0 for f in figures),
    }


def estop_figures(records: list[Path], phase: dict) -> dict:
    """An e-stop phase's figures from the records: the worst bus's latency per e-stop (its
    signal → the first e-stop frame's start on that bus's wire, before the next signal), and
    the checks: e-stops that found every bus streaming, resets that reached every bus, and
    e-stops that missed a bus; the status polls per second per bus."""
    signals, resets = phase["signals"], phase["resets"]
    start, end = phase["window"]
    follow = follow_frame_names(drivers_of(0))
    stop, enable, status = (
        control_hex(code)
        for code in (la.ControlCode.ESTOP, la.ControlCode.ENABLE, la.ControlCode.STATUS)
    )
    buses = []
    for path in records:
        frames = [r for r in load_records(path) if r.direction == "rx" and start <= r.start <= end]
        control = [(r.start, r.wire[8:14]) for r in frames if r.frame == "ControlCommand"]
        buses.append(
            {
                "stops": [t for t, code in control if code == stop],
                "enables": [t for t, code in control if code == enable],
                "polls": sum(1 for _, code in control if code == status),
                "follows": [r.start for r in frames if r.frame in follow],
            }
        )
    worst: list[float] = []
    missed = streaming = reset = 0
    for i, signal in enumerate(signals):
        until = signals[i + 1] if i + 1 < len(signals) else end
        latency = slowest_first(signal, until, [bus["stops"] for bus in buses])
        streaming += all(
            any(signal - STREAMING_S <= t < signal for t in bus["follows"]) for bus in buses
        )
        reset += all(any(resets[i] <= t < until for t in bus["enables"]) for bus in buses)
        if latency is None:
            missed += 1
        else:
            worst.append(latency)
    worst.sort()
    return {
        "estops": len(signals),
        "latencies_ms": [round(1000 * value, 3) for value in worst],
        "p50_ms": ms(percentile(worst, 0.5)),
        "p99_ms": ms(percentile(worst, 0.99)),
        "max_ms": ms(worst[-1] if worst else None),
        "missed": missed,
        "streaming": streaming,
        "reset": reset,
        "polls_per_s": sum(bus["polls"] for bus in buses) / len(buses) / (end - start),
    }


def slowest_first(signal: float, until: float, series: list[list[float]]) -> float | None:
    """From ``signal`` to the last of each series' first time in ``[signal, until)``: the
    slowest bus's first e-stop frame, or daemon's callback; ``None`` when one has none."""
    firsts = [min((t for t in times if signal <= t < until), default=None) for times in series]
    return None if None in firsts else max(t for t in firsts if t is not None) - signal


def ms(seconds: float | None) -> float | None:
    return None if seconds is None else 1000 * seconds


def step(buses: int, seconds: float, daemons: int, workers: list[str | None], estops: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench-scale-") as folder:
        scratch = Path(folder)
        records = [scratch / f"wire{n}.jsonl" for n in range(buses)]
        with contextlib.ExitStack() as stack:
            sims = [
                stack.enter_context(
                    SimProcess("inspire_la", [*SIM_ARGUMENTS, "--record", str(record)])
                )
                for record in records
            ]
            ports = [sim.port for sim in sims]
            for sim in sims:
                realtime_device(sim.process.pid)
            gateways = [
                gateway_step(scratch, ports, seconds, sims, min(daemons, buses), value, estops)
                for value in workers
            ]
            bare = bare_step(ports, seconds)
            traffic = bare_estop_step(ports, 0, seconds)
            bare_estop = bare_estop_step(ports, estops) if estops else {}
        # The simulators have stopped: their records are complete.
        for gateway in gateways:
            gateway |= wire_figures(records, gateway["window"])
            if estops:
                gateway["estop"] = estop_figures(records, gateway["estop_phase"])
                phase = gateway["estop_phase"]
                gateway["estop_hop"] = hop_figures(phase["signals"], phase["hops"])
                gateway["floor_hop"] = hop_figures(phase["floor_signals"], phase.get("floor", []))
        bare |= wire_figures(records, bare["window"])
        if estops:
            bare["estop"] = estop_figures(records, bare_estop) | {
                "cpu_percent": bare_estop["cpu_percent"],
                "timeouts": bare_estop["timeouts"],
            }
        return {"gateways": gateways, "bare": bare, "traffic": traffic}


# -- the output ----------------------------------------------------------------------------


def line(name: str, figures: dict) -> str:
    """One writer's figures in a line (see the module's docstring for what each is)."""
    under = figures["host_under"]
    text = (
        f"  {name:8} host: {'some' if under is None else under} intervals under the period "
        f"(the shortest {figures['host_min_ms']:+.3f} ms from it), error p50 "
        f"{figures['host_p50_ms']:.3f} p99 {figures['host_p99_ms']:.3f} ms"
    )
    if "host_gap_ms" in figures:
        text += f", smallest gap {figures['host_gap_ms']:.3f} ms, {figures['timeouts']} timeouts"
    text += (
        f"\n  {'':8} device: {figures['follow_frames']} ticks, error p50 "
        f"{figures['device_p50_ms']:.3f} p99 {figures['device_p99_ms']:.3f} ms, "
        f"{figures['device_under']} intervals under the period, "
        f"{figures['device_gaps_under_1ms']} gaps under 1 ms; CPU {figures['cpu_percent']:.1f} %"
    )
    threads = figures.get("threads_cpu_percent")
    if threads:
        split = ", ".join(f"{role} {value:.1f}" for role, value in sorted(threads.items()))
        text += f" ({split}; the simulators {figures['simulators_cpu_percent']:.0f} %)"
    if "processes" in figures:
        text += f", {figures['processes']} process(es)"
    return text


def number(value: float | None, sign: bool = False) -> str:
    if value is None:
        return "—"
    return f"{value:+.3f}" if sign else f"{value:.3f}"


def table(headers: list[str], rows: list[list[str]]) -> str:
    """Columns as wide as their widest cell, the first left-aligned, the rest right."""
    widths = [max(len(row[i]) for row in [headers, *rows]) for i in range(len(headers))]

    def cells(row: list[str]) -> str:
        first, *rest = row
        return "  ".join(
            [
                first.ljust(widths[0]),
                *(cell.rjust(w) for cell, w in zip(rest, widths[1:], strict=True)),
            ]
        )

    return "\n".join(["    " + cells(headers), *("    " + cells(row) for row in rows)])


def estop_table(figures: dict) -> str:
    """The e-stop phase of one step: each writer's worst-bus latency, and the checks."""
    bare = figures["bare"]["estop"]
    rows = []
    for gateway in figures["gateways"]:
        mine = gateway["estop"]
        added = [
            None if mine[q] is None or bare[q] is None else mine[q] - bare[q]
            for q in ("p50_ms", "p99_ms")
        ]
        rows.append(estop_row(f"gateway, workers {gateway['workers']}", mine, added))
    rows.append(estop_row("bare", bare, [None, None]))
    headers = ["writer", "e-stops", "p50", "p99", "max", "added p50", "added p99",
               "streaming", "reset", "missed", "polls/s/bus"]  # fmt: skip
    hops = [
        f"\n  gateway, workers {gateway['workers']}: put → {whose} (ms): p50 "
        f"{number(hop['p50_ms'])}, p99 {number(hop['p99_ms'])}, max {number(hop['max_ms'])} "
        f"({hop['count']} puts)"
        for gateway in figures["gateways"]
        for whose, hop in [
            ("the gateway's e-stop callback (zenoh's hop, the slowest daemon per e-stop)",
             gateway.get("estop_hop")),
            ("an idle process's callback (zenoh's hop, no gateway behind it)",
             gateway.get("floor_hop")),
        ]
        if hop
    ]  # fmt: skip
    return (
        "  e-stop → its frame on every bus (the worst bus per e-stop; device side, ms):\n"
        + table(headers, rows)
        + "".join(hops)
    )


def estop_row(name: str, figures: dict, added: list[float | None]) -> list[str]:
    count = figures["estops"]
    return [
        name,
        str(count),
        number(figures["p50_ms"]),
        number(figures["p99_ms"]),
        number(figures["max_ms"]),
        number(added[0], sign=True),
        number(added[1], sign=True),
        f"{figures['streaming']}/{count}",
        f"{figures['reset']}/{count}",
        str(figures["missed"]),
        f"{figures['polls_per_s']:.1f}",
    ]


def summary(rows: list[dict]) -> str:
    """One row per step and writer: the workers value, CPU, follow error p99 (host, device),
    and the e-stop figures."""
    headers = ["run", "buses", "daemons", "workers", "writer", "CPU %", "× bare, polls",
               "host p99", "device p99", "e-stop p50", "p99", "max", "added p50",
               "added p99"]  # fmt: skip
    cells = []
    for row in rows:
        estop = row["figures"].get("estop") or {}
        added = row.get("added", [None, None])
        cells.append(
            [
                str(row["run"]),
                str(row["buses"]),
                str(row["daemons"]),
                row["workers"],
                row["writer"],
                f"{row['figures']['cpu_percent']:.1f}",
                "—" if "times_bare" not in row else f"{row['times_bare']:.2f}",
                number(row["figures"].get("host_p99_ms")),
                number(row["figures"].get("device_p99_ms")),
                number(estop.get("p50_ms")),
                number(estop.get("p99_ms")),
                number(estop.get("max_ms")),
                number(added[0], sign=True),
                number(added[1], sign=True),
            ]
        )
    return "summary (ms; CPU % of one core, the e-stop phase left out):\n" + table(headers, cells)


#: How a refusal names what ``positive`` takes.
WORDS = {int: "whole number", float: "number"}


def positive(kind: type) -> Any:
    """An argparse type: a ``kind`` number above 0, else a one-line refusal."""

    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            value = 0
        if not value > 0:
            raise argparse.ArgumentTypeError(f"{text!r}: a {WORDS[kind]} above 0")
        return value

    return parse


def bus_counts(text: str) -> list[int]:
    """``--buses``: bus counts above 0, comma-separated."""
    return [positive(int)(part) for part in text.split(",")]


def workers_values(text: str) -> list[str]:
    """``--workers``: each ``auto`` or a whole number above 0, comma-separated."""
    values = []
    for part in text.split(","):
        try:
            values.append("auto" if part.strip() == "auto" else str(positive(int)(part)))
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(f"{part!r}: auto or a whole number above 0") from None
    return values


def count(text: str) -> int:
    """``--estop``: a whole number, 0 or more."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: a whole number, 0 or more")
    return value


def priority(text: str) -> int:
    """``--realtime``: a SCHED_FIFO priority, 1 to 98."""
    value = int(text)
    if not 1 <= value <= 98:  # the simulators run one above
        raise argparse.ArgumentTypeError(f"a SCHED_FIFO priority here is 1 to 98, not {value}")
    return value


def label(workers: str | None) -> str:
    return "unset" if workers is None else workers


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--buses", type=bus_counts, default="1,2,4,6,8", help="the values of N, e.g. 1,2,4,8"
    )
    parser.add_argument("--seconds", type=positive(float), default=10.0, help="measured per step")
    parser.add_argument("--runs", type=positive(int), default=1)
    parser.add_argument(
        "--daemons", type=positive(int), default=1, help="split the buses over this many daemons"
    )
    parser.add_argument(
        "--workers",
        type=workers_values,
        metavar="LIST",
        help="the gateway's [gateway] workers, each value in turn, e.g. 1,auto (default: not "
        "written, so the gateway's own default, auto)",
    )
    parser.add_argument(
        "--estop",
        type=count,
        default=0,
        metavar="COUNT",
        help="e-stops per step, beside a bare loop's (default 0)",
    )
    parser.add_argument(
        "--estop-hop",
        action="store_true",
        help="with --estop: also time each put to the start of the gateway's e-stop callback",
    )
    parser.add_argument(
        "--realtime",
        type=priority,
        metavar="PRIORITY",
        help="every bus thread, the gateway's and the bare loops', under SCHED_FIFO (1-98)",
    )
    parser.add_argument("--bare", help=argparse.SUPPRESS)  # the child: its ports
    parser.add_argument("--bare-estop", help=argparse.SUPPRESS)  # the e-stop child: its ports
    args = parser.parse_args()
    if args.estop_hop and not args.estop:
        parser.error("--estop-hop times the e-stops of --estop: give a count there too")
    global REALTIME, ESTOP_HOP
    REALTIME = args.realtime
    ESTOP_HOP = args.estop_hop
    if args.bare:
        print(json.dumps(bare_loops(args.bare.split(","), args.seconds)))
        return
    if args.bare_estop:
        print(json.dumps(bare_estop_loops(args.bare_estop.split(","), args.estop, args.seconds)))
        return
    workers: list[str | None] = args.workers or [None]
    rows: list[dict] = []
    for run in range(1, args.runs + 1):
        for buses in args.buses:
            figures = step(buses, args.seconds, args.daemons, workers, args.estop)
            daemons = min(args.daemons, buses)
            print(
                f"run {run}, {buses} bus(es) of {len(IDS)} LA, {daemons} daemon(s), "
                f"{args.seconds:g} s{realtime_label()}:"
            )
            where = {"run": run, "buses": buses, "daemons": daemons}
            bare_estop = figures["bare"].get("estop")
            for gateway in figures["gateways"]:
                print(f"  gateway, workers {gateway['workers']}:")
                print(line("gateway", gateway))
                added = [None, None]
                if bare_estop:
                    added = [
                        None if gateway["estop"][q] is None or bare_estop[q] is None
                        else gateway["estop"][q] - bare_estop[q]
                        for q in ("p50_ms", "p99_ms")
                    ]  # fmt: skip
                rows.append(
                    where
                    | {"workers": gateway["workers"], "writer": "gateway", "figures": gateway}
                    | {"added": added}
                )
            print(line("bare", figures["bare"]))
            rows.append(where | {"workers": "—", "writer": "bare", "figures": figures["bare"]})
            traffic = figures["traffic"]
            print(
                f"  bare, the same traffic (the e-stop yardstick's loops, no e-stop): CPU "
                f"{traffic['cpu_percent']:.1f} %, {traffic['timeouts']} timeouts"
            )
            rows.append(
                where
                | {"workers": "—", "writer": "bare, polls"}
                | {"figures": {"cpu_percent": traffic["cpu_percent"]}}
            )
            for row in rows[-len(figures["gateways"]) - 2 : -2]:
                row["times_bare"] = row["figures"]["cpu_percent"] / traffic["cpu_percent"]
            if args.estop:
                print(estop_table(figures))
                print(
                    f"  the bare e-stop loops: CPU {bare_estop['cpu_percent']:.1f} %, "
                    f"{bare_estop['timeouts']} timeouts"
                )
            sys.stdout.flush()
    print(summary(rows), flush=True)


if __name__ == "__main__":
    main()
