"""How many serial buses one host drives while every timing rule holds, and at what CPU.

Not a test (pytest does not collect it). Everything on this machine, on 127.0.0.1 with
multicast scouting off: the simulators, the daemon (``busgate run``) and the bare loops as
child processes, the streaming client here; every process ended by its PID.

    .venv/bin/python tests/benchmarks/bench_scale.py [--buses 1,2,4,8] [--seconds 10] [--runs 2]

For each N: N simulated UARTs of 3 Inspire LA actuators at 921600 baud (``busgate sim``,
each recording its wire). First the gateway: one daemon drives all N buses, every device
followed at 10 ms and polled at 20 Hz, a client here putting a new target to every device
at 50 Hz over zenoh. Then, on the same simulators for the same time, the yardstick: N bare
sleep-then-spin loops in one process (one thread each, ``busgate bench --baseline``'s loop)
writing each bus's follow frame every 10 ms with targets a thread there updates at 50 Hz.

Host side, as each writer timed its own writes: the shortest follow interval less the period
(negative: an interval under the period), the interval error p50 (median over buses) and p99
(worst bus); for the gateway also its smallest gap and timeouts, from its stats key (since
its start: the warm-up included). Device side, from the simulators' records: the follow
error p50/p99 and the gaps under the 1 ms minimum. The simulators wait in ``select`` rather
than busy-poll (N spinning simulators would take the two cores from what is measured), so
a device-side time is late by their wake-up, some 0.1 ms and more under load, the bare
loops' as much as the gateway's: a frame read late looks longer, and the gap after it
shorter, than on a wire. CPU: utime + stime from /proc, % of one core; the daemon's split
into its bus threads, its other Python threads and zenoh's, and the simulators' together.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh
from bench_zenoh import Daemon, free_endpoint, serial_bus, wait_ready

from busgate.client.zenoh_config import session_config
from busgate.gateway.bus.clock import now, tune_interpreter
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


def position(t_s: float, bus: int, index: int) -> int:
    """Every device a sine of its own phase, as ``follow_sample`` would give."""
    return round(1000 + 500 * math.sin(2 * math.pi * t_s + bus + index))


# -- the gateway ---------------------------------------------------------------------------


def gateway_step(scratch: Path, ports: list[str], seconds: float, sims: list[SimProcess]) -> dict:
    """The daemon on the N buses under a streaming client: its window, its CPU by thread, its
    stats (host side), and the simulators' CPU."""

    def sims_cpu_s() -> float:
        return sum(cpu_s(f"/proc/{sim.process.pid}/stat") for sim in sims)

    endpoint = free_endpoint()
    config = "".join(
        serial_bus(
            f"bus{n}",
            port,
            "inspire_la",
            list(IDS),
            BAUD,
            poll_hz=POLL_HZ,
            follow_period_ms=round(PERIOD_S * 1000),
        )
        for n, port in enumerate(ports)
    )
    daemon = Daemon(scratch, endpoint, config)
    stats: dict[str, dict] = {}
    try:
        with zenoh.open(session_config(connect=[endpoint])) as session:
            wait_ready(session)
            session.declare_subscriber(
                "busgate/bench/bus/*/stats",
                lambda sample: stats.__setitem__(
                    str(sample.key_expr), json.loads(sample.payload.to_bytes())
                ),
            )
            for name in (f"bus{n}-{i}" for n in range(len(ports)) for i in IDS):
                session.get(
                    f"busgate/bench/dev/{name}/cmd", payload='{"op":"enable"}', timeout=5
                ).recv()
            stop = threading.Event()
            streamer = threading.Thread(target=stream, args=(session, len(ports), stop))
            streamer.start()
            try:
                time.sleep(WARM_UP_S)
                before, cpu_before, started = dict(stats), daemon.cpu_s(), now()
                sims_before, threads_before = sims_cpu_s(), threads_cpu_s(daemon.process.pid)
                time.sleep(seconds)
                cpu, ended = daemon.cpu_s() - cpu_before, now()
                sims_cpu = sims_cpu_s() - sims_before
                threads = threads_cpu_s(daemon.process.pid)
                time.sleep(1.5)  # one more stats sample, covering the window
                after = dict(stats)
            finally:
                stop.set()
                streamer.join()
    finally:
        daemon.stop()
    buses = list(after.values())
    elapsed = ended - started
    return {
        "window": (started, ended),
        "host_min_ms": 1000 * min(bus["follow_error_min_s"] for bus in buses),
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


def threads_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds of the daemon's threads by role: its bus threads (named ``bus-<bus>``),
    its other Python threads (the event loop's: publishing), and zenoh's own (Rust)."""
    used: dict[str, float] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        name = (task / "comm").read_text().strip()
        role = "bus" if name.startswith("bus-") else "python" if name == "python" else "zenoh"
        used[role] = used.get(role, 0.0) + cpu_s(str(task / "stat"))
    return used


def stream(session: zenoh.Session, buses: int, stop: threading.Event) -> None:
    publishers = {
        (n, index): session.declare_publisher(f"busgate/bench/dev/bus{n}-{ident}/follow")
        for n in range(buses)
        for index, ident in enumerate(IDS)
    }
    start = now()
    deadline = start
    while not stop.is_set():
        t = now() - start
        for (n, index), publisher in publishers.items():
            publisher.put(json.dumps({"position": position(t, n, index)}))
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
        (n, index): driver.follow_target({"position": position(0.0, n, index)})
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
                    latest[n, index] = driver.follow_target({"position": position(t, n, index)})

    def loop(n: int) -> None:
        bus = drivers[n]
        request_of = lambda: InspireLaDriver.follow_request(  # noqa: E731
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
        "device_gaps_under_1ms": sum(
            f.gaps_after_reply_below_minimum + f.gaps_after_silent_frame_below_minimum
            for f in figures
        ),
        "device_p50_ms": 1000 * statistics.median(f.follow_error_p50_s or 0.0 for f in figures),
        "device_p99_ms": 1000 * max(f.follow_error_p99_s or 0.0 for f in figures),
    }


def step(buses: int, seconds: float) -> dict:
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
            gateway = gateway_step(scratch, ports, seconds, sims)
            bare = bare_step(ports, seconds)
        return {
            "gateway": gateway | wire_figures(records, gateway["window"]),
            "bare": bare | wire_figures(records, bare["window"]),
        }


def line(name: str, figures: dict) -> str:
    """One writer's figures in a line (see the module's docstring for what each is)."""
    text = (
        f"  {name:8} host: shortest interval {figures['host_min_ms']:+.3f} ms from the period, "
        f"error p50 {figures['host_p50_ms']:.3f} p99 {figures['host_p99_ms']:.3f} ms"
    )
    if "host_gap_ms" in figures:
        text += f", smallest gap {figures['host_gap_ms']:.3f} ms, {figures['timeouts']} timeouts"
    text += (
        f"\n  {'':8} device: {figures['follow_frames']} ticks, error p50 "
        f"{figures['device_p50_ms']:.3f} p99 {figures['device_p99_ms']:.3f} ms, "
        f"{figures['device_gaps_under_1ms']} gaps under 1 ms; CPU {figures['cpu_percent']:.1f} %"
    )
    threads = figures.get("threads_cpu_percent")
    if threads:
        split = ", ".join(f"{role} {value:.1f}" for role, value in sorted(threads.items()))
        text += f" ({split}; the simulators {figures['simulators_cpu_percent']:.0f} %)"
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--buses", default="1,2,4,8", help="the values of N, e.g. 1,2,4,8")
    parser.add_argument("--seconds", type=float, default=10.0, help="measured per step")
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--bare", help=argparse.SUPPRESS)  # the child: its ports
    args = parser.parse_args()
    if args.bare:
        print(json.dumps(bare_loops(args.bare.split(","), args.seconds)))
        return
    for run in range(1, args.runs + 1):
        for buses in (int(n) for n in args.buses.split(",")):
            figures = step(buses, args.seconds)
            print(f"run {run}, {buses} bus(es) of {len(IDS)} LA, {args.seconds:g} s:")
            print(line("gateway", figures["gateway"]))
            print(line("bare", figures["bare"]), flush=True)


if __name__ == "__main__":
    main()
