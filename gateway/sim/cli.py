"""``busgate sim``: serve simulated devices on a new pty until SIGTERM or SIGINT.

The first line of output is ``PORT <path>``, the path a host opens (the ``--link`` symlink
when given). SIGUSR1 unplugs the adapter, or plugs it back in; SIGUSR2 reboots every device.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import threading
import uuid

from busgate.errors import CommandError
from busgate.gateway.bus.clock import now
from busgate.gateway.sim.faults import FaultConfig, FaultInjector
from busgate.gateway.sim.models import make_devices
from busgate.gateway.sim.pty_link import PtyLink
from busgate.gateway.sim.recorder import Recorder
from busgate.schemas.families import PROTOCOLS


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    sim = subparsers.add_parser(
        "sim",
        description="Serve simulated devices on a new pty (CAN: behind a simulated SLCAN "
        "adapter) and print 'PORT <path>' first. SIGUSR1 unplugs/replugs, SIGUSR2 reboots.",
    )
    sim.add_argument("protocol", choices=sorted(PROTOCOLS))
    sim.add_argument("--ids", type=_id_list, default=[1], help="device ids, e.g. 1,2,3 (default 1)")
    sim.add_argument("--baudrate", type=int, help="serial baud rate (default: per protocol)")
    sim.add_argument("--interface", choices=("slcan",), default="slcan", help="CAN adapter")
    sim.add_argument("--bitrate", type=int, default=500_000, help="CAN bitrate (default 500000)")
    sim.add_argument("--heartbeat-ms", type=int, help="ZLAC706 CAN heartbeat interval, 0 = none")
    sim.add_argument("--stroke-s", type=float, help="Inspire LA: seconds for a full stroke")
    sim.add_argument("--link", help="keep a symlink here pointing at the current pty")
    sim.add_argument(
        "--record", type=argparse.FileType("w"), help="write every frame to FILE (JSON lines)"
    )
    sim.add_argument("--seed", type=int, default=0, help="seed for turnaround times and faults")
    sim.add_argument(
        "--busy-poll-ms",
        type=float,
        default=5.0,
        help="poll the port without sleeping for this long after each frame, for exact "
        "arrival times (default 5; 0 sleeps in select)",
    )
    faults = sim.add_argument_group("fault injection")
    faults.add_argument("--drop-rate", type=float, default=0.0, help="share of replies dropped")
    faults.add_argument("--late-rate", type=float, default=0.0, help="share of replies sent late")
    faults.add_argument("--late-ms", type=float, default=100.0, help="how late (default 100 ms)")
    faults.add_argument("--bad-checksum-rate", type=float, default=0.0, help="share corrupted")
    faults.add_argument("--garbage-rate", type=float, default=0.0, help="share preceded by noise")
    faults.add_argument("--silent-ids", type=_id_list, default=[], help="ids that never answer")
    faults.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="ID:NAME",
        help="raise a device fault at start, e.g. 2:over_current (repeatable)",
    )
    sim.set_defaults(handler=run_sim)


def _id_list(text: str) -> list[int]:
    try:
        return [int(part) for part in text.split(",") if part.strip()]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not a list of ids: {text!r}") from exc


def run_sim(args: argparse.Namespace) -> int:
    try:
        devices = make_devices(args.protocol, args.ids, **_model_options(args))
    except TypeError as exc:  # an option this device model does not have
        raise CommandError(f"{args.protocol} simulator: {exc}") from exc
    for spec in args.fault:
        _raise_fault(devices, spec)
    try:
        faults = FaultInjector(_fault_config(args), seed=args.seed)
    except ValueError as exc:
        raise CommandError(str(exc)) from exc
    recorder = Recorder(args.record)
    server = _make_server(args, devices, faults, recorder)
    print(f"PORT {server.port}", flush=True)
    stop = threading.Event()
    _install_signals(server, devices, stop)
    with contextlib.ExitStack() as stack:
        stack.callback(server.stop)
        server.start()
        stop.wait()
    return 0


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


def _make_server(args, devices, faults, recorder):
    protocol = PROTOCOLS[args.protocol]
    if protocol.can:
        return _SlcanServer(protocol.codec, devices, args.bitrate, args.link, faults, recorder)
    from busgate.gateway.sim.serial_server import SerialSimulator

    baudrate = args.baudrate or protocol.timing.default_rate
    return SerialSimulator(
        protocol.codec,
        devices,
        baudrate=baudrate,
        link=PtyLink(args.link),
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
        self.adapter = SlcanAdapter(channel, link=PtyLink(link))
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
