"""``busgate bench``: the real bus owner and scheduler against a port, measured.

It streams follow targets to the devices and polls them in the spare capacity for a while,
then prints what it achieved: exchanges and frames per second, the smallest gap, the follow
interval error (p50/p99, and how many intervals fell under the period), timeouts and CPU.
Without ``--port`` it starts the built-in simulator in a child process (so the CPU figure is
the gateway's alone) and also reports what the devices saw on the wire. ``--baseline`` then
runs a plain sleep-then-spin pyserial loop on the same port for the same time, under the same
client load (a thread streaming targets), the yardstick for follow jitter on this machine;
with ``--follow-period-ms 0``, a plain write-read-wait-the-gap polling loop instead, the
yardstick for exchanges per second.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import itertools
import json
import math
import os
import select
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import serial

from busgate.errors import BusUnavailableError, CommandError
from busgate.gateway.bus.clock import now, sleep_until, tighten_timer_slack, tune_interpreter
from busgate.gateway.bus.request import Request
from busgate.gateway.bus.stats import percentile
from busgate.gateway.cli.arguments import seconds
from busgate.gateway.drivers.base import Driver
from busgate.gateway.drivers.families import driver_class, make_driver
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.cli import id_list
from busgate.gateway.sim.process import SimProcess
from busgate.gateway.sim.wire_analysis import analyse, load_records
from busgate.schemas.config import CanBus, SerialBus, parse_config
from busgate.schemas.families import PROTOCOLS

ONLINE_TIMEOUT_S = 5.0
#: The polling baseline's wait for a reply before it counts a timeout and goes on.
REPLY_WAIT_S = 0.02


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    bench = subparsers.add_parser(
        "bench",
        description=__doc__.split("\n\n")[1],
    )
    bench.add_argument(
        "--protocol",
        "--kind",  # its name in earlier releases, still in users' scripts
        required=True,
        choices=sorted(PROTOCOLS),
        metavar="PROTOCOL",
        help=f"wire protocol: {', '.join(sorted(PROTOCOLS))}",
    )
    bench.add_argument("--port", help="serial port or slcan tty (default: built-in simulator)")
    bench.add_argument(
        "--ids", type=id_list, default="1", help="device ids, e.g. 1,2,3 (default 1)"
    )
    bench.add_argument("--baudrate", type=int, help="serial baud rate (default: per protocol)")
    bench.add_argument(
        "--follow-period-ms",
        type=float,
        default=10.0,
        help="follow period, 10–50 ms; 0 streams nothing (default 10)",
    )
    bench.add_argument("--poll-hz", type=float, default=20.0, help="polls per device per second")
    bench.add_argument("--seconds", type=seconds, default=6.0, help="how long to measure")
    bench.add_argument("--min-gap-ms", type=float, help="UART gap (default: per protocol)")
    bench.add_argument(
        "--reply-margin-ms",
        type=float,
        default=2.0,
        help="time allowed on top of a reply's wire and turnaround time (default "
        "2, as in a config; more for a loaded host or a slow adapter)",
    )
    bench.add_argument(
        "--baseline", action="store_true", help="also time a plain sleep-then-spin pyserial loop"
    )
    bench.add_argument("--json", action="store_true", help="print the figures as JSON")
    bench.set_defaults(handler=run_bench)


def run_bench(args: argparse.Namespace) -> int:
    ids = args.ids
    if not ids:
        raise CommandError("--ids names no device")
    protocol = PROTOCOLS[args.protocol]
    baudrate = protocol.timing.default_rate if args.baudrate is None else args.baudrate
    # Refused before anything opens; the simulator's port is not known yet, a stand-in is.
    bus_config(args, ids, args.port or "/dev/pts/simulator", baudrate)
    tune_interpreter()
    with tempfile.TemporaryDirectory() as scratch, contextlib.ExitStack() as simulator:
        port, record = args.port, None
        if port is None:
            record = Path(scratch) / "wire.jsonl"
            sim_args = ["--ids", ",".join(map(str, ids)), "--record", str(record)]
            if not protocol.can:
                sim_args += ["--baudrate", str(baudrate)]
            port = simulator.enter_context(SimProcess(args.protocol, sim_args)).port
        figures, window, drivers = measure(args, ids, port, baudrate)
        if args.baseline and not protocol.can:
            run_baseline = baseline if args.follow_period_ms else polling_baseline
            figures["baseline"] = run_baseline(args, drivers, port, baudrate)
        if record is not None:
            simulator.close()  # stop the simulator so that its record is complete
            figures["device_side"] = device_side(args, record, window)
    print(json.dumps(figures, indent=2) if args.json else format_figures(args, figures))
    return 0


def bus_config(
    args: argparse.Namespace, ids: list[int], port: str, baudrate: int
) -> SerialBus | CanBus:
    """The bus the benchmark runs: the only bus of a whole config, so that it passes every
    check a config file's bus does (the protocol's gap minimum, its ids, one device per port
    …) and is refused in the config's words (``buses[0].min_gap_ms: …``)."""
    protocol = PROTOCOLS[args.protocol]
    kind, period = protocol.kind, args.follow_period_ms or 20.0
    # Named by place, as a file's devices[n]: a repeated id is refused as such, not its name.
    devices: list[Any] = [
        {"name": f"dev{n}", "kind": kind, "id": i, "poll_hz": args.poll_hz,
         "follow_period_ms": period}
        for n, i in enumerate(ids)
    ]  # fmt: skip
    common = {"name": "bench", "devices": devices, "reply_margin_ms": args.reply_margin_ms}
    if protocol.can:
        bus = {"transport": "can", "interface": "slcan", "channel": port,
               "options": {"sleep_after_open": 0}, **common}  # fmt: skip
    else:
        bus = {"transport": "serial", "port": port, "baudrate": baudrate,
               "min_gap_ms": args.min_gap_ms, **common}  # fmt: skip
    return parse_config({"gateway": {"name": "bench"}, "buses": [bus]}).buses[0]


def measure(
    args: argparse.Namespace, ids: list[int], port: str, baudrate: int
) -> tuple[dict, tuple[float, float, set[str]], list]:
    """Run the bus for ``args.seconds``; the figures, the measured window (start, end, and the
    frame types of its follow ticks), and the drivers (which keep what the devices were set
    to, e.g. a ZLAC706's mode)."""
    runner = build_bus(bus_config(args, ids, port, baudrate)).start()
    try:
        wait_online(runner)
        for name in runner.drivers:
            driver = runner.drivers[name]
            for text in driver.follow_preparation:
                runner.submit(name, driver.parse(text)).result(timeout=2)
        gc.freeze()
        thread_before = thread_cpu_s(runner.native_id)
        before, cpu_before, started = runner.statistics(), time.process_time(), now()
        stream_targets(runner, args)
        after, cpu_after, ended = runner.statistics(), time.process_time(), now()
        thread_cpu = thread_cpu_s(runner.native_id) - thread_before
        follow_frames = follow_frame_names(list(runner.drivers.values()))  # before the safe stop
    finally:
        runner.stop()
    elapsed = ended - started
    exchanges = after.frames_out - before.frames_out
    return (
        {
            "protocol": args.protocol,
            "devices": len(ids),
            "rate": baudrate,
            "seconds": round(elapsed, 3),
            "follow_period_ms": args.follow_period_ms,
            "poll_hz": args.poll_hz,
            "frames_out_per_s": round(exchanges / elapsed, 1),
            "frames_in_per_s": round((after.frames_in - before.frames_in) / elapsed, 1),
            "smallest_gap_ms": _ms(after.smallest_gap_s),
            "follow_intervals": after.follow_intervals,
            "follow_error_p50_ms": _ms(after.follow_error_p50_s),
            "follow_error_p99_ms": _ms(after.follow_error_p99_s),
            "follow_error_min_ms": _ms(after.follow_error_min_s),
            "timeouts": after.timeouts - before.timeouts,
            "retries": after.retries - before.retries,
            "checksum_errors": after.checksum_errors - before.checksum_errors,
            "skipped_polls": runner.planner.skipped_polls,
            "utilisation": round(after.utilisation, 3),
            "cpu_percent_bus_thread": round(100 * thread_cpu / elapsed, 1),
            "cpu_percent_process": round(100 * (cpu_after - cpu_before) / elapsed, 1),
        },
        (started, ended, follow_frames),
        list(runner.drivers.values()),
    )


def cpu_s(stat: str) -> float:
    """CPU seconds (user + system) from a /proc ``stat`` file: a process's
    (``/proc/<pid>/stat``) or one thread's (``/proc/self/task/<tid>/stat``); NaN if gone."""
    try:
        fields = Path(stat).read_text().rsplit(")", 1)[1].split()
    except OSError:
        return math.nan
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def thread_cpu_s(native_id: int | None) -> float:
    """CPU seconds one thread of this process has used."""
    return cpu_s(f"/proc/self/task/{native_id}/stat")


def wait_online(runner: BusRunner) -> None:
    deadline = now() + ONLINE_TIMEOUT_S
    while not all(d.online for d in runner.drivers.values()):
        if now() > deadline:
            offline = [f"id {d.device_id}" for d in runner.drivers.values() if not d.online]
            raise BusUnavailableError(f"devices did not answer: {', '.join(offline)}")
        time.sleep(0.01)


def stream_targets(runner: BusRunner, args: argparse.Namespace) -> None:
    """Act as a client of the gateway for ``args.seconds``."""
    if not args.follow_period_ms:
        time.sleep(args.seconds)
        return
    feed_targets(list(runner.drivers.values()), args, runner.follow, now() + args.seconds)


def feed_targets(drivers: list, args: argparse.Namespace, deliver, end: float) -> None:
    """A client's stream: a new follow target for every device twice a period, validated
    the way the gateway validates a client's payload, delivered as ``BusRunner.follow``
    takes it (the device, the target, what it is)."""
    step = args.follow_period_ms / 2000
    while (moment := now()) < end:
        for index, driver in enumerate(drivers):
            payload = driver.follow_sample(moment, index)
            deliver(driver.name, driver.follow_target(payload), driver.follow_carries(payload))
        time.sleep(step)


def baseline(args: argparse.Namespace, used: list, port: str, baudrate: int) -> dict:
    """A plain loop under the same client load: sleep then spin to each deadline and write a
    follow frame with the latest targets; no polling, no scheduler."""
    protocol = PROTOCOLS[args.protocol]
    period = (args.follow_period_ms or 10.0) / 1000
    drivers = baseline_drivers(args, used, port, baudrate)
    latest = {d.name: d.follow_target(d.follow_sample(0.0, 0)) for d in drivers}
    end = now() + args.seconds
    client = threading.Thread(
        target=feed_targets,
        args=(drivers, args, lambda name, target, _follows: latest.__setitem__(name, target), end),
        daemon=True,
    )
    client.start()
    follow_request = driver_class(protocol).follow_request
    starts = bare_follow_loop(
        port, baudrate, lambda: follow_request([(d, latest[d.name]) for d in drivers]), period, end
    )
    client.join()
    return interval_figures(starts, period)


def bare_follow_loop(
    port: str, baudrate: int, request_of: Callable[[], Request], period_s: float, end: float
) -> list[float]:
    """The yardstick: sleep then spin to each deadline and write the frame ``request_of``
    makes, until ``end``; when the kernel had each frame (timed like the bus owner)."""
    starts: list[float] = []
    tighten_timer_slack()
    deadline = now()
    with serial.Serial(port, baudrate, timeout=0, write_timeout=0.5) as handle:
        while deadline < end:
            request = request_of()
            sleep_until(deadline)
            assert isinstance(request.wire, bytes)  # a UART protocol's frames
            os.write(handle.fileno(), request.wire)
            starts.append(now())
            deadline += period_s
    return starts


def line_gap_s(args: argparse.Namespace) -> float:
    """The UART gap the bench's bus keeps: ``--min-gap-ms``, else the protocol's."""
    if args.min_gap_ms is not None:
        return args.min_gap_ms / 1000
    return PROTOCOLS[args.protocol].timing.default_gap_s


def polling_baseline(args: argparse.Namespace, used: list, port: str, baudrate: int) -> dict:
    """A plain polling loop: each device's poll in turn, written, its reply read, then the
    gap waited from the reply's last byte (sleep then spin); no scheduler."""
    protocol = PROTOCOLS[args.protocol]
    gap_s = line_gap_s(args)
    polls = [request for driver in used for request in driver.poll()]
    decoder = protocol.codec.ReplyDecoder()
    exchanges = timeouts = 0
    tighten_timer_slack()
    started = now()
    end = started + args.seconds
    with serial.Serial(port, baudrate, timeout=0, write_timeout=0.5) as handle:
        fd = handle.fileno()
        for request in itertools.cycle(polls):
            if now() >= end:
                break
            assert isinstance(request.wire, bytes)  # a UART protocol's frames
            os.write(fd, request.wire)
            deadline = now() + REPLY_WAIT_S
            replied = None
            while replied is None and select.select([fd], [], [], max(0.0, deadline - now()))[0]:
                decoder.feed(os.read(fd, 4096))
                if any(True for _ in decoder.events()):
                    replied = now()
            if replied is None:
                timeouts += 1
                replied = now()
            exchanges += 1
            sleep_until(replied + gap_s)
    elapsed = now() - started
    return {"frames_out_per_s": round(exchanges / elapsed, 1), "timeouts": timeouts}


def interval_figures(starts: list[float], period_s: float) -> dict:
    """Follow interval error figures of frames written at ``starts``."""
    errors = sorted(b - a - period_s for a, b in itertools.pairwise(starts))
    return {
        "follow_intervals": len(errors),
        "follow_intervals_under_period": sum(1 for error in errors if error < 0),
        "follow_error_p50_ms": _ms(percentile(errors, 0.5)),
        "follow_error_p99_ms": _ms(percentile(errors, 0.99)),
        "follow_error_min_ms": _ms(errors[0] if errors else None),
    }


def baseline_drivers(args: argparse.Namespace, used: list, port: str, baudrate: int) -> list:
    """Drivers to validate the baseline client's targets: fresh ones, as a client meets them;
    those the gateway ran when a fresh one refuses a stream (a ZLAC706 needs its mode set)."""
    protocol = PROTOCOLS[args.protocol]
    config = bus_config(args, [d.device_id for d in used], port, baudrate)
    fresh = [make_driver(device, protocol) for device in config.devices]
    try:
        fresh[0].follow_target(fresh[0].follow_sample(0.0, 0))
    except CommandError:
        return used
    return fresh


def follow_frame_names(drivers: list[Driver]) -> set[str]:
    """The frame types that carry these drivers' follow targets: alone, and together."""
    follow_request = type(drivers[0]).follow_request
    targets = [(d, d.follow_target(d.follow_sample(0.0, 0))) for d in drivers]
    limit = type(drivers[0]).follow_group_limit
    groups = [targets[:1], targets[:limit]]
    return {type(follow_request(group).frame).__name__ for group in groups}


def device_side(args: argparse.Namespace, record: Path, window: tuple[float, float, set]) -> dict:
    start, end, follow_frames = window
    records = [r for r in load_records(record) if start <= r.start <= end]
    figures = analyse(
        records,
        min_gap_s=line_gap_s(args),
        follow_frames=follow_frames,
        follow_period_s=(args.follow_period_ms or 0) / 1000 or None,
    )
    return {
        (name.removesuffix("_s") + "_ms" if name.endswith("_s") else name): (
            _ms(value) if name.endswith("_s") else value
        )
        for name, value in asdict(figures).items()
    }


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else round(seconds * 1000, 3)


def format_figures(args: argparse.Namespace, figures: dict) -> str:
    lines = [
        f"busgate bench: {figures['protocol']}, {figures['devices']} device(s), "
        f"{figures['seconds']} s, follow {figures['follow_period_ms']} ms, "
        f"poll {figures['poll_hz']} Hz"
    ]
    for section in ("", "device_side", "baseline"):
        values = figures if not section else figures.get(section)
        if not values:
            continue
        if section:
            lines.append(f"{section.replace('_', ' ')}:")
        for name, value in values.items():
            if not isinstance(value, dict) and name not in ("protocol", "devices", "seconds"):
                lines.append(f"  {name.replace('_', ' '):32} {value}")
    return "\n".join(lines)
