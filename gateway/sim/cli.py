"""``busgate sim``: serve simulated devices on a new pty until SIGTERM or SIGINT.

The first line of output is ``PORT <path>``, the path a host opens (the ``--link`` symlink
when given). SIGUSR1 unplugs the adapter, or plugs it back in; SIGUSR2 reboots every device.

Rules of this file:

1. Every argument is checked before anything is made: each number by its parser type (one
   line naming the option and its range), ids and ``--fault`` by the device models. Only then
   is the pty made with its ``--link``, and then the ``--record`` file opened.
2. A ``--record`` file is written from the start each run (the benchmarks write theirs again
   on each step), but only once everything else has been taken: a refused command leaves an
   existing record as it was. ``-`` is standard output, after the ``PORT`` line; a pipe or a
   device is written as a file is, a directory refused.
3. ``--link`` replaces only a symlink, one an earlier simulator left (``PtyLink``); a file or
   directory there is refused. When the record cannot be opened, the link is taken away
   again: a refused command leaves nothing behind.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import signal
import sys
import threading
import uuid
from collections.abc import Callable
from typing import IO

from busgate.errors import CommandError
from busgate.gateway.bus.clock import now
from busgate.gateway.sim.faults import FaultConfig, FaultInjector
from busgate.gateway.sim.models import make_devices
from busgate.gateway.sim.pty_link import PtyLink
from busgate.gateway.sim.recorder import Recorder
from busgate.schemas.families import PROTOCOLS
from busgate.schemas.files import EMPTY_PATH

#: The longest time an option sets: a day, more than any simulated wait needs, and short
#: enough that a timer can be set for it (``time.sleep`` overflows long before infinity).
MAX_MS = 86_400_000
#: Classic CAN's fastest bitrate (SLCAN's S8).
MAX_CAN_BITRATE = 1_000_000


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    sim = subparsers.add_parser(
        "sim",
        description="Serve simulated devices on a new pty (CAN: behind a simulated SLCAN "
        "adapter) and print 'PORT <path>' first. SIGUSR1 unplugs/replugs, SIGUSR2 reboots.",
    )
    sim.add_argument("protocol", choices=sorted(PROTOCOLS))
    sim.add_argument("--ids", type=id_list, default=[1], help="device ids, e.g. 1,2,3 (default 1)")
    sim.add_argument("--baudrate", type=_baudrate, help="serial baud rate (default: per protocol)")
    sim.add_argument("--interface", choices=("slcan",), default="slcan", help="CAN adapter")
    sim.add_argument(
        "--bitrate", type=_bitrate, default=500_000, help="CAN bitrate (default 500000)"
    )
    sim.add_argument(
        "--heartbeat-ms", type=_heartbeat_ms, help="ZLAC706 CAN heartbeat interval, 0 = none"
    )
    sim.add_argument("--stroke-s", type=_stroke_s, help="Inspire LA: seconds for a full stroke")
    sim.add_argument("--link", help="keep a symlink here pointing at the current pty")
    sim.add_argument(
        "--record", metavar="FILE", help="write every frame to FILE (JSON lines; - for stdout)"
    )
    sim.add_argument("--seed", type=int, default=0, help="seed for turnaround times and faults")
    sim.add_argument(
        "--busy-poll-ms",
        type=_ms,
        default=5.0,
        help="poll the port without sleeping for this long after each frame, for exact "
        "arrival times (default 5; 0 sleeps in select)",
    )
    faults = sim.add_argument_group("fault injection")
    faults.add_argument("--drop-rate", type=_share, default=0.0, help="share of replies dropped")
    faults.add_argument("--late-rate", type=_share, default=0.0, help="share of replies sent late")
    faults.add_argument("--late-ms", type=_ms, default=100.0, help="how late (default 100 ms)")
    faults.add_argument("--bad-checksum-rate", type=_share, default=0.0, help="share corrupted")
    faults.add_argument("--garbage-rate", type=_share, default=0.0, help="share preceded by noise")
    faults.add_argument("--silent-ids", type=id_list, default=[], help="ids that never answer")
    faults.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="ID:NAME",
        help="raise a device fault at start, e.g. 2:over_current (repeatable)",
    )
    sim.set_defaults(handler=run_sim)


def id_list(text: str) -> list[int]:
    """``--ids`` of ``busgate sim`` and ``busgate bench``: ids joined by commas."""
    try:
        return [int(part) for part in text.split(",") if part.strip()]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not a list of ids: {text!r}") from exc


def _in_range(
    parse: Callable[[str], float], low: float, high: float, allowed: str
) -> Callable[[str], float]:
    """An argparse type: ``parse`` the text and refuse what is not within [low, high] (NaN is
    not), saying the ``allowed`` values; argparse names the option."""

    def check(text: str) -> float:
        try:
            value = parse(text)
        except ValueError:
            value = math.nan
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be {allowed}, not {text!r}")
        return value

    return check


_baudrate = _in_range(int, 1, math.inf, "a whole number of baud above 0")
_bitrate = _in_range(int, 1, MAX_CAN_BITRATE, f"a whole number of bit/s, 1 to {MAX_CAN_BITRATE}")
_heartbeat_ms = _in_range(int, 0, MAX_MS, f"a whole number of ms, 0 (none) to {MAX_MS}")
_stroke_s = _in_range(float, 0.001, MAX_MS / 1000, f"seconds, 0.001 to {MAX_MS // 1000}")
_ms = _in_range(float, 0, MAX_MS, f"ms, 0 to {MAX_MS}")
_share = _in_range(float, 0, 1, "a share, 0 to 1")


def run_sim(args: argparse.Namespace) -> int:
    try:
        devices = make_devices(args.protocol, args.ids, **_model_options(args))
    except TypeError as exc:  # an option this device model does not have
        raise CommandError(f"{args.protocol} simulator: {exc}") from exc
    for spec in args.fault:
        _raise_fault(devices, spec)
    faults = FaultInjector(_fault_config(args), seed=args.seed)
    with contextlib.ExitStack() as stack:
        try:
            link = PtyLink(args.link)
        except OSError as exc:  # rule 3: a file or directory there, or no such folder
            raise CommandError(f"--link {args.link}: {exc.strerror}") from None
        stack.callback(link.close)  # closed again by the server's stop: twice is once
        record_file = (
            None if args.record is None else stack.enter_context(_open_record(args.record))
        )
        server = _make_server(args, devices, faults, Recorder(record_file, keep=0), link)
        stop = threading.Event()
        _install_signals(server, devices, stop)  # before PORT: a stop may follow it at once
        print(f"PORT {server.port}", flush=True)
        stack.callback(server.stop)
        server.start()
        stop.wait()
    return 0


def _open_record(path: str) -> contextlib.AbstractContextManager[IO[str]]:
    """``path`` opened for writing from the start (rule 2), ``-`` standard output (left open);
    closed by the caller."""
    if path == "-":
        return contextlib.nullcontext(sys.stdout)
    if not path:
        raise CommandError(f"--record: {EMPTY_PATH}")
    try:
        return open(path, "w")
    except OSError as exc:
        raise CommandError(f"cannot write --record {path}: {exc.strerror}") from None


def _model_options(args: argparse.Namespace) -> dict[str, object]:
    options = {"heartbeat_ms": args.heartbeat_ms, "stroke_s": args.stroke_s}
    return {name: value for name, value in options.items() if value is not None}


def _fault_config(args: argparse.Namespace) -> FaultConfig:
    return FaultConfig(
        drop_rate=args.drop_rate,
        late_rate=args.late_rate,
        late_s=args.late_ms / 1000,
        bad_checksum_rate=args.bad_checksum_rate,
        garbage_rate=args.garbage_rate,
        silent_ids=frozenset(args.silent_ids),
    )


def _raise_fault(devices: list, spec: str) -> None:
    ident, _, name = spec.partition(":")
    matching = [d for d in devices if str(d.device_id) == ident]
    if not matching or not name:
        raise CommandError(f"--fault wants ID:NAME with one of the simulated ids, not {spec!r}")
    try:
        matching[0].inject_fault(name, now())
    except ValueError as exc:
        raise CommandError(f"--fault {spec}: {exc}") from exc


def _make_server(args, devices, faults, recorder, link):
    protocol = PROTOCOLS[args.protocol]
    if protocol.can:
        return _SlcanServer(protocol.codec, devices, args.bitrate, link, faults, recorder)
    from busgate.gateway.sim.serial_server import SerialSimulator

    baudrate = args.baudrate or protocol.timing.default_rate
    return SerialSimulator(
        protocol.codec,
        devices,
        baudrate=baudrate,
        link=link,
        faults=faults,
        recorder=recorder,
        seed=args.seed,
        busy_poll_s=args.busy_poll_ms / 1000,
    )


class _SlcanServer:
    """A simulated SLCAN adapter and the CAN devices behind it, started and stopped as one."""

    def __init__(self, codec, devices, bitrate, link, faults, recorder) -> None:
        import can

        from busgate.gateway.sim.can_server import CanSimulator
        from busgate.gateway.sim.slcan import SlcanAdapter

        channel = f"busgate-sim-{uuid.uuid4().hex}"
        self.adapter = SlcanAdapter(channel, link=link)
        self.devices = devices
        self.simulator = CanSimulator(
            codec,
            devices,
            bus=can.Bus(interface="virtual", channel=channel),
            bitrate=bitrate,
            faults=faults,
            recorder=recorder,
        )
        self.port = self.adapter.port

    def start(self) -> None:
        self.simulator.start()
        self.adapter.start()

    def stop(self) -> None:
        self.adapter.stop()
        self.simulator.stop()

    def unplug(self) -> None:
        self.adapter.unplug()

    def replug(self) -> None:
        self.adapter.replug()


def _install_signals(server, devices, stop: threading.Event) -> None:
    plugged = [True]

    def toggle_plug(*_: object) -> None:
        plugged[0] = not plugged[0]
        (server.replug if plugged[0] else server.unplug)()

    def reboot(*_: object) -> None:
        for device in devices:
            device.reboot(now())

    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGUSR1, toggle_plug)
    signal.signal(signal.SIGUSR2, reboot)
