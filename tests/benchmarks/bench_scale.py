"""How many serial buses one host drives while every timing rule holds, and at what CPU.

Not a test (pytest does not collect it). Everything on this machine, on 127.0.0.1 with
multicast scouting off: the simulators, the daemon (``busgate run``) and the bare loops as
child processes, the streaming client here; every process ended by its PID.

    .venv/bin/python tests/benchmarks/bench_scale.py [--buses 1,2,4,6,8] [--daemons 2] [--runs 2]

For each N: N simulated UARTs of 3 Inspire LA actuators at 921600 baud (``busgate sim``,
each recording its wire). First the gateway: one daemon drives all N buses (``--daemons K``:
K daemons, the buses split evenly, each its own gateway name), every device followed at 10 ms
and polled at 20 Hz, a client here putting a new target to every device
at 50 Hz over zenoh. Then, on the same simulators for the same time, the yardstick: N bare
sleep-then-spin loops in one process (one thread each, ``busgate bench --baseline``'s loop)
writing each bus's follow frame every 10 ms with targets a thread there updates at 50 Hz.

Host side, as each writer timed its own writes: the follow intervals under the period (the
gateway's stats keep only the shortest, so for it "0" or "some") and the shortest interval
less the period, the interval error p50 (median over buses) and p99 (worst bus); for the
gateway also its smallest gap and timeouts, from its stats key (since its start: the warm-up
included). Device side, from the simulators' records: the follow error p50/p99, the
intervals under the period and the gaps under the 1 ms minimum. The simulators wait in
``select`` rather than busy-poll (N spinning simulators would take the two cores from what
is measured), so a device-side time is late by their wake-up, some 0.1 ms and more under
load, the bare loops' as much as the gateway's: a frame read late looks longer, and the gap
after it shorter, than on a wire. CPU: utime + stime from /proc, % of one core; the daemon's
split into its bus threads, its other Python threads and zenoh's, and the simulators'
together.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import zenoh
from bench_zenoh import Daemon, free_endpoint, serial_bus, wait_ready

from busgate.gateway.bus.clock import now, tune_interpreter
from busgate.gateway.bus.request import Request
from busgate.gateway.cli.bench import (
    bare_follow_loop,
    cpu_s,
    follow_frame_names,
    interval_figures,
)
from busgate.gateway.drivers.inspire_la import InspireLaDriver
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


def drivers_of(bus: int) -> list[InspireLaDriver]:
    return [InspireLaDriver(f"bus{bus}-{i}", i) for i in IDS]


def target(t_s: float, bus: int, index: int) -> dict:
    """Device ``index`` of bus ``bus`` at ``t_s``: the driver's follow sample, each device of
    every bus its own phase."""
    return InspireLaDriver.follow_sample(t_s, bus * len(IDS) + index)


# -- the gateway ---------------------------------------------------------------------------


def gateway_step(
    scratch: Path, ports: list[str], seconds: float, sims: list[SimProcess], daemons: int
) -> dict:
    """The N buses, split over ``daemons`` daemons (``bench0``, ``bench1`` …), under a
    streaming client: the window, the daemons' CPU by thread, their stats (host side), and
    the simulators' CPU."""

    def sims_cpu_s() -> float:
        return sum(cpu_s(f"/proc/{sim.process.pid}/stat") for sim in sims)

    gateways = [f"bench{k}" for k in range(daemons)]
    owner = {f"bus{n}": gateways[n * daemons // len(ports)] for n in range(len(ports))}
    endpoints = [free_endpoint() for _ in gateways]
    started_daemons: list[Daemon] = []
    stats: dict[str, dict] = {}
    try:
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
                )
                for n, bus in enumerate(owner)
                if owner[bus] == gateway
            )
            started_daemons.append(Daemon(scratch, endpoint, config, name=gateway))
        with zenoh.open(session_config(connect=endpoints)) as session:
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
                pids = [daemon.process.pid for daemon in started_daemons]
                before, started = dict(stats), now()
                cpu_before = sum(daemon.cpu_s() for daemon in started_daemons)
                sims_before, threads_before = sims_cpu_s(), threads_cpu_s(pids)
                time.sleep(seconds)
                cpu = sum(daemon.cpu_s() for daemon in started_daemons) - cpu_before
                ended = now()
                sims_cpu = sims_cpu_s() - sims_before
                threads = threads_cpu_s(pids)
                time.sleep(1.5)  # one more stats sample, covering the window
                after = dict(stats)
            finally:
                stop.set()
                streamer.join()
    finally:
        for daemon in started_daemons:
            daemon.stop()
    buses = list(after.values())
    elapsed = ended - started
    return {
        "window": (started, ended),
        "host_min_ms": 1000 * min(bus["follow_error_min_s"] for bus in buses),
        # The stats keep the shortest interval, not a count: none is under when it is not.
        "host_under": 0 if min(bus["follow_error_min_s"] for bus in buses) >= 0 else None,
        "host_p50_ms": 1000 * statistics.median(bus["follow_error_p50_s"] for bus in buses),
        "host_p99_ms": 1000 * max(bus["follow_error_p99_s"] for bus in buses),
        "host_gap_ms": 1000 * min(bus["smallest_gap_s"] for bus in buses),
        "timeouts": sum(bus["timeouts"] for bus in buses)
        - sum(bus["timeouts"] for bus in before.values()),
        "cpu_percent": 100 * cpu / elapsed,
        "threads_cpu_percent": {
            role: 100 * (used - threads_before.get(role, 0.0)) / elapsed
            for role, used in threads.items()
        },
        "simulators_cpu_percent": 100 * sims_cpu / elapsed,
    }


def threads_cpu_s(pids: list[int]) -> dict[str, float]:
    """CPU seconds of the daemons' threads by role: their bus threads (named ``bus-<bus>``),
    their other Python threads (the event loop's: publishing), and zenoh's own (Rust)."""
    used: dict[str, float] = {}
    for task in (task for pid in pids for task in Path(f"/proc/{pid}/task").iterdir()):
        name = (task / "comm").read_text().strip()
        role = "bus" if name.startswith("bus-") else "python" if name == "python" else "zenoh"
        used[role] = used.get(role, 0.0) + cpu_s(str(task / "stat"))
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
        [sys.executable, __file__, "--bare", ",".join(ports), "--seconds", str(seconds)],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).parent,
    )
    return json.loads(child.stdout)


def bare_loops(ports: list[str], seconds: float) -> dict:
    tune_interpreter()  # as the daemon does
    drivers = [drivers_of(n) for n in range(len(ports))]
    latest = {
        (n, index): driver.follow_target(target(0.0, n, index))
        for n, bus in enumerate(drivers)
        for index, driver in enumerate(bus)
    }
    started = now() + 0.2
    end = started + seconds
    stop = threading.Event()
    figures: list[dict] = []

    def feed() -> None:
        while not stop.wait(1 / TARGET_HZ):
            t = now() - started
            for n, bus in enumerate(drivers):
                for index, driver in enumerate(bus):
                    latest[n, index] = driver.follow_target(target(t, n, index))

    def loop(n: int) -> None:
        bus = drivers[n]

        def request_of() -> Request:
            return InspireLaDriver.follow_request(
                [(driver, latest[n, index]) for index, driver in enumerate(bus)]
            )

        time.sleep(max(0.0, started - now()))
        starts = bare_follow_loop(ports[n], BAUD, request_of, PERIOD_S, end)
        figures.append(interval_figures(starts, PERIOD_S))

    threads = [threading.Thread(target=loop, args=(n,)) for n in range(len(ports))]
    feeder = threading.Thread(target=feed)
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


def step(buses: int, seconds: float, daemons: int) -> dict:
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
            gateway = gateway_step(scratch, ports, seconds, sims, min(daemons, buses))
            bare = bare_step(ports, seconds)
        return {
            "gateway": gateway | wire_figures(records, gateway["window"]),
            "bare": bare | wire_figures(records, bare["window"]),
        }


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
    return text


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
    parser.add_argument("--bare", help=argparse.SUPPRESS)  # the child: its ports
    args = parser.parse_args()
    if args.bare:
        print(json.dumps(bare_loops(args.bare.split(","), args.seconds)))
        return
    for run in range(1, args.runs + 1):
        for buses in args.buses:
            figures = step(buses, args.seconds, args.daemons)
            daemons = min(args.daemons, buses)
            print(
                f"run {run}, {buses} bus(es) of {len(IDS)} LA, {daemons} daemon(s), "
                f"{args.seconds:g} s:"
            )
            print(line("gateway", figures["gateway"]))
            print(line("bare", figures["bare"]), flush=True)


if __name__ == "__main__":
    main()
