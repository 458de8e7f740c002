"""``busgate demo``: the real gateway on simulated devices of every kind, no hardware needed.

Rules of this file:

1. The gateway is the one ``busgate run`` runs. The demo only builds its config (a ``Config``,
   through ``parse_config``, so it is validated like any file) and hands it to ``serve``; what
   differs from a robot is where the ports lead: to the simulators' ptys and to a python-can
   ``virtual`` channel of its own.
2. The simulators run in this process, beside the gateway, with their wire timing (baud rate,
   bitrate, turnaround) and without busy polling (``serial_server`` rule 5: spinning would
   contend with the bus threads for the GIL).
3. Simulators start before the gateway and stop after it, so the frames the gateway sends on
   its way out (each device's safe state) still reach a device.
4. The hints are printed only once the gateway and its dashboard serve, and they are
   commands that work as printed: ``--connect`` appears when the endpoint is not the client
   tools' default.
5. The dashboard is the one ``busgate dashboard`` serves, on the same loop as the gateway,
   reaching it through zenoh like any client; it stops when the gateway does.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import errno
import logging
import math
import os
import shlex
import shutil
import socket
import sys
import threading
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from busgate.client import aio
from busgate.client.errors import ConnectError
from busgate.client.keys import check_name
from busgate.codecs.ros2.rmw_zenoh import resolve
from busgate.dashboard.server import DEFAULT_LISTEN, Listen, serve_dashboard
from busgate.errors import CommandError
from busgate.gateway.cli.arguments import named_path
from busgate.gateway.cli.client_session import DEFAULT_ENDPOINT
from busgate.gateway.service import logs
from busgate.gateway.service.daemon import IN_USE_HINT, serve, stop_on_signals
from busgate.gateway.sim.models import make_devices
from busgate.gateway.sim.recorder import Recorder
from busgate.schemas.config import Config, parse_config, workers_value
from busgate.schemas.endpoints import takes_tcp_port
from busgate.schemas.families import PROTOCOLS
from busgate.schemas.files import FileRefused, make_folder

GATEWAY_NAME = "demo"
HEARTBEAT_MS = 100
READY_POLL_S = 0.05
TRY_COMMAND = '{"op":"move","position":1500}'

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class DemoBus:
    """One simulated bus: its protocol, baud rate (CAN: bitrate) and devices (name, id)."""

    name: str
    protocol: str
    rate: int
    devices: tuple[tuple[str, int], ...]

    @property
    def heartbeat_ms(self) -> int:
        """ZLAC706 on CAN talks unasked; the others only answer."""
        return HEARTBEAT_MS if PROTOCOLS[self.protocol].can else 0


#: The demo's simulated buses and devices: one bus per protocol of every family (a test holds
#: it to the registry), each at the protocol's default rate.
_DEMO_DEVICES: dict[str, tuple[str, tuple[tuple[str, int], ...]]] = {
    "inspire_la": ("uart0", (("la1", 1), ("la2", 2), ("la3", 3))),
    "ds_servo": ("uart1", (("servo1", 1), ("servo2", 2))),
    "zlac706_can": ("can0", (("wheel", 1), ("wheel_l", 2), ("wheel_r", 3))),
    "zlac706_rs232": ("rs232", (("drive", 1),)),
}
DEMO_BUSES = tuple(
    DemoBus(bus, protocol, PROTOCOLS[protocol].timing.default_rate, devices)
    for protocol, (bus, devices) in _DEMO_DEVICES.items()
)

_TURN = 2 * math.pi
#: The hub motors' velocity joint: 10000 encoder pulses a turn (the manual's), at most 15 rad/s
#: (143 rpm: 1.3 m/s on a 6.5-inch wheel).
_HUB_MOTOR: dict[str, Any] = {
    "type": "velocity",
    "unit": "rad",
    "scale": _TURN / 10_000,
    "max_velocity": 15.0,
}
#: Each demo device's joint table (``[buses.devices.joint]``, docs/joints.md), as examples of
#: plausible SI calibrations. Position limits are left out, so each is its device's whole
#: range (the tests drive the demo's devices through all of it and stream big steps to them):
#:
#: - ``la1``–``la3``: a 10 mm stroke over raw 0–2000, 5 µm a count: 0–0.010 m.
#: - ``servo1``, ``servo2``: one turn in 4096 counts, centred (raw 2048 is 0 rad): −π to
#:   π − 2π/4096 rad, streamed or played at most one turn a second (2π rad/s).
#: - ``wheel``: a small robot's wheel, ``_HUB_MOTOR``; ``wheel_l`` and ``wheel_r`` the
#:   demo base's (``DEMO_BASES``), the right one mirrored.
#: - ``drive``: a cart's drive, ``_HUB_MOTOR`` that also speeds up and slows down at most at
#:   10 rad/s² (0 to 15 rad/s in 1.5 s): a step in speed, one-shot or streamed, becomes a ramp
#:   (the reply to a one-shot speed comes at once, with the speed the ramp starts from).
DEMO_JOINTS: dict[str, dict[str, Any]] = {
    **{la: {"unit": "m", "scale": 5e-6} for la in ("la1", "la2", "la3")},
    **{
        servo: {"unit": "rad", "scale": _TURN / 4096, "offset": -math.pi, "max_velocity": _TURN}
        for servo in ("servo1", "servo2")
    },
    "wheel": _HUB_MOTOR,
    "drive": {**_HUB_MOTOR, "max_acceleration": 10.0},
    "wheel_l": _HUB_MOTOR,
    "wheel_r": {**_HUB_MOTOR, "scale": -_HUB_MOTOR["scale"]},
}
#: The demo's base (``[[bases]]``, docs/bases.md): ``wheel_l`` and ``wheel_r`` on ``can0`` as
#: one differential drive, the right motor mirrored (its joint's negative scale), 6.5-inch
#: wheels 0.4 m apart.
DEMO_BASES: list[dict[str, Any]] = [
    {
        "name": "base",
        "left": "wheel_l",
        "right": "wheel_r",
        "wheel_radius_m": 0.0825,
        "track_m": 0.40,
        "max_linear_mps": 1.0,
        "max_angular_radps": 2.0,
        "max_linear_accel": 0.8,
        "max_angular_accel": 3.0,
        "cmd_timeout_s": 0.5,
    }
]


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    demo = subparsers.add_parser(
        "demo",
        description="Run the real gateway (named 'demo') on simulated devices: three Inspire LA "
        "actuators and two DS servos on UART buses, three ZLAC706 on CAN (two of them a "
        "differential-drive base) and one on RS232, with "
        "wire timing emulated. Prints how to connect; serves until SIGTERM or Ctrl-C.",
    )
    link = demo.add_mutually_exclusive_group()  # a client of a router listens on nothing
    link.add_argument(
        "--listen",
        default=DEFAULT_ENDPOINT,
        metavar="ENDPOINT",
        help=f"zenoh endpoint to listen on (default {DEFAULT_ENDPOINT})",
    )
    link.add_argument(
        "--connect",
        default=None,
        metavar="ENDPOINT",
        help="join a zenoh router here (as a client) instead of listening",
    )
    demo.add_argument(
        "--name",
        type=_gateway_name,
        default=GATEWAY_NAME,
        help=f"the gateway's name (default {GATEWAY_NAME})",
    )
    demo.add_argument(
        "--dashboard-listen",
        default=DEFAULT_LISTEN,
        metavar="HOST:PORT",
        help=f"serve the dashboard here (default {DEFAULT_LISTEN}; port 0: any free one)",
    )
    demo.add_argument(
        "--dashboard-allow-host",
        action="append",
        default=[],
        metavar="NAME",
        help="a host name the dashboard answers to besides its address's own (repeatable)",
    )
    demo.add_argument("--no-dashboard", action="store_true", help="serve no dashboard")
    demo.add_argument(
        "--record",
        default=None,
        type=named_path,
        metavar="DIR",
        help="write each simulator's wire record to DIR/<bus>.jsonl (JSON lines)",
    )
    demo.add_argument(
        "--incidents",
        default=None,
        type=named_path,
        metavar="DIR",
        help="turn the flight recorder on: an incident file (MCAP) in DIR on each e-stop, "
        "fault, bus down or SIGUSR1",
    )
    demo.add_argument(
        "--metrics-listen",
        default=None,
        metavar="HOST:PORT",
        help="serve Prometheus metrics here (default: off)",
    )
    demo.add_argument(
        "--workers",
        default=1,
        type=_workers,
        metavar="auto|N",
        help="bus workers: the processes the demo's serial buses are split across (default 1: "
        "every bus in the demo's own process; auto: one per core)",
    )
    demo.add_argument(
        "--ros2",
        action="store_true",
        help="be a ROS 2 node too (rmw_zenoh's wire format, domain 0): joint states on "
        "/robot_joint_states, commands on /robot_joint_commands (the [ros2] table's defaults)",
    )
    demo.set_defaults(handler=run_demo)


def run_demo(args: argparse.Namespace) -> int:
    if args.no_dashboard and (args.dashboard_listen != DEFAULT_LISTEN or args.dashboard_allow_host):
        raise CommandError(
            "--no-dashboard serves none: --dashboard-listen and --dashboard-allow-host would be "
            "ignored; give one or the other"
        )
    dashboard = (
        None
        if args.no_dashboard
        else Listen.parse(args.dashboard_listen, args.dashboard_allow_host)
    )
    logs.configure("INFO")
    if dashboard is not None and (exposed := dashboard.exposure()) is not None:
        print(f"busgate demo: warning: the dashboard at {exposed}", file=sys.stderr)
    with contextlib.ExitStack() as simulators:
        # Bound before anything starts: a port in use is refused at once, not after the
        # gateway came up (held until the dashboard serves it).
        listening = None if args.connect else args.listen  # a client of a router listens on none
        bound = None if dashboard is None else _bound(dashboard, listening)
        if bound is not None:
            simulators.callback(bound.close)
        records = None if args.record is None else _record_dir(args.record)
        links = {bus.name: _start_simulator(bus, simulators, records) for bus in DEMO_BUSES}
        config = demo_config(
            links,
            listen=args.listen,
            connect=args.connect,
            name=args.name,
            metrics_listen=args.metrics_listen,
            incidents=None if args.incidents is None else os.path.abspath(args.incidents),
            ros2=args.ros2,
            workers=args.workers,
        )
        try:
            asyncio.run(_serve_announcing(config, links, dashboard, bound))
        except ConnectError as exc:
            raise _beside(exc) from None
    return 0


def _beside(exc: ConnectError) -> ConnectError:
    """zenoh's endpoint in use, told with the option that runs a second demo beside the
    first, as the dashboard's address in use is (``_bound``)."""
    said = str(exc)
    if not said.endswith(f"({IN_USE_HINT})"):
        return exc
    return ConnectError(
        f"{said[:-1]} A second one runs beside it with --listen tcp/127.0.0.1:<another port>)"
    )


def _bound(dashboard: Listen, endpoint: str | None) -> socket.socket:
    """The dashboard's socket (``Listen.bind``), its refusal saying what else to do; refused
    too on the port the gateway's zenoh ``endpoint`` listens on (the socket is bound, not
    listening, until the dashboard serves: zenoh took the port, and the dashboard failed
    after the gateway came up, with a traceback)."""
    if (
        endpoint is not None
        and dashboard.port
        and takes_tcp_port(endpoint, dashboard.host, dashboard.port)
    ):  # port 0 is any free one: never zenoh's
        raise CommandError(
            f"--dashboard-listen {dashboard.host}:{dashboard.port} is the port zenoh listens "
            f"on ({endpoint}): give the dashboard another"
        )
    try:
        return dashboard.bind()
    except CommandError as exc:  # where else it could go, for a new user
        cause = exc.__cause__
        if isinstance(cause, OSError) and cause.errno == errno.EADDRINUSE:  # a demo running?
            raise CommandError(
                f"{exc} (another busgate demo? A second one runs beside it with --listen "
                "tcp/127.0.0.1:<another port> --dashboard-listen 127.0.0.1:0, or "
                "--no-dashboard)"
            ) from None
        raise CommandError(
            f"{exc} (--dashboard-listen 127.0.0.1:0 takes any free port, --no-dashboard "
            "serves none)"
        ) from None


def _gateway_name(text: str) -> str:
    """``--name``: a gateway's name, refused as the SDK refuses one (argparse naming the flag,
    where the config's refusal named its key, ``gateway.name``)."""
    try:
        return check_name("gateway", text)
    except CommandError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _workers(text: str) -> object:
    """``--workers``: what ``[gateway] workers`` takes, a number as one; refused as the
    config refuses it, argparse naming the flag."""
    try:
        value: object = int(text)
    except ValueError:
        value = text
    try:
        return workers_value(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def _record_dir(path: str) -> Path:
    try:
        return make_folder(path)
    except FileRefused as exc:
        raise CommandError(f"cannot write wire records: {exc}") from exc


def _record_file(path: Path) -> IO[str]:
    """``path`` opened for writing, or refused in one line naming it (a folder that takes no
    files, as ``/proc``, or a directory of that name): the simulators started before it stop
    as the refusal leaves ``run_demo``'s stack."""
    try:
        return path.open("w")
    except OSError as exc:
        raise CommandError(f"cannot write the wire record {path}: {exc.strerror}") from exc


def _start_simulator(
    bus: DemoBus, stack: contextlib.ExitStack, records: Path | None
) -> dict[str, Any]:
    """Start ``bus``'s simulator (stopped when ``stack`` closes), recording its wire in
    ``records``/<bus>.jsonl when given; return the config keys that lead the gateway to it."""
    protocol = PROTOCOLS[bus.protocol]
    record = stack.enter_context(_record_file(records / f"{bus.name}.jsonl")) if records else None
    recorder = Recorder(record, keep=0)  # the demo reads none back: its file alone, if any
    options = {"heartbeat_ms": bus.heartbeat_ms} if protocol.can else {}
    devices = make_devices(bus.protocol, [ident for _, ident in bus.devices], **options)
    if protocol.can:
        import can

        from busgate.gateway.sim.can_server import CanSimulator

        channel = f"busgate-demo-{uuid.uuid4().hex[:8]}"  # virtual channels are per process
        stack.enter_context(
            CanSimulator(
                protocol.codec,
                devices,
                bitrate=bus.rate,
                bus=can.Bus(interface="virtual", channel=channel),
                recorder=recorder,
            )
        )
        return {"transport": "can", "interface": "virtual", "channel": channel, "bitrate": bus.rate}
    from busgate.gateway.sim.serial_server import SerialSimulator

    simulator = stack.enter_context(
        SerialSimulator(protocol.codec, devices, baudrate=bus.rate, recorder=recorder)
    )
    return {"transport": "serial", "port": simulator.port, "baudrate": bus.rate}


def demo_config(
    links: dict[str, dict[str, Any]],
    *,
    listen: str,
    connect: str | None = None,
    name: str = GATEWAY_NAME,
    metrics_listen: str | None = None,
    incidents: str | None = None,
    ros2: bool = False,
    workers: str | int = 1,
) -> Config:
    """The demo gateway's config, validated; ``links`` holds each bus's port or channel keys.
    With ``connect``, it joins a router there as a zenoh client instead of listening; with
    ``incidents`` (an absolute path), its flight recorder writes there; with ``ros2``, it is a
    ROS 2 node too (``[ros2]`` with its defaults); ``workers`` is ``[gateway] workers``. Raises
    ``ConfigError`` (naming the key) for a bad name, endpoint or metrics address."""
    zenoh = {"mode": "client", "connect": [connect]} if connect else {"listen": [listen]}
    document: dict[str, Any] = {
        "gateway": {"name": name, "workers": workers},
        "zenoh": {"mode": "peer", **zenoh},
        "buses": [
            {
                "name": bus.name,
                **links[bus.name],
                "devices": [
                    {
                        "name": name,
                        "kind": PROTOCOLS[bus.protocol].kind,
                        "id": ident,
                        "heartbeat_ms": bus.heartbeat_ms,
                        "joint": DEMO_JOINTS.get(name),
                    }
                    for name, ident in bus.devices
                ],
            }
            for bus in DEMO_BUSES
        ],
        "bases": DEMO_BASES,
    }
    if metrics_listen is not None:
        document["metrics"] = {"listen": metrics_listen}
    if incidents is not None:
        document["recorder"] = {"dir": incidents}
    if ros2:
        document["ros2"] = {}
    return parse_config(document)


def _hints(config: Config, links: dict[str, dict[str, Any]], dashboard: str | None) -> str:
    """What the demo serves, two commands to try from another terminal, and the dashboard."""
    endpoint = _endpoint(config)
    connect = "" if endpoint == DEFAULT_ENDPOINT else f" --connect {shlex.quote(endpoint)}"
    how = "joined the router at" if config.zenoh.connect else "is serving on"
    lines = [f"busgate demo: gateway {config.gateway.name!r} {how} {endpoint}"]
    width = max(len(", ".join(d.name for d in bus.devices)) for bus in config.buses)
    for bus in config.buses:
        link = links[bus.name]
        where = (
            f"{link['port']} at {link['baudrate']} baud"
            if "port" in link
            else f"virtual CAN {link['channel']} at {link['bitrate']} bit/s"
        )
        names = ", ".join(device.name for device in bus.devices)
        lines.append(f"  {bus.name:<6} {bus.protocol:<14} {names:<{width}} {where}")
    first, program = config.buses[0].devices[0].name, _program()
    if config.zenoh.connect:  # a fleet's gateways share device names: name the gateway
        first = f"{config.gateway.name}/{first}"
    lines += [
        "From another terminal, move an actuator and watch every device:",
        f"  {program} send {first} {shlex.quote(TRY_COMMAND)}{connect}",
        f"  {program} watch {config.gateway.name}{connect}",
    ]
    if dashboard is not None:
        lines.append(f"Or see them in a browser: {dashboard}")
    if config.ros2 is not None:
        ros2 = config.ros2
        node = ros2.node_of(config.gateway.name)
        states = resolve(ros2.joint_states, ros2.namespace, node)
        lines += [
            f"ROS 2 (rmw_zenoh, domain {ros2.domain_id}): node {resolve('~', ros2.namespace, node)}"
            f", joint states on {states}, commands on "
            f"{resolve(ros2.joint_commands, ros2.namespace, node)}; from a ROS shell:",
            "  export RMW_IMPLEMENTATION=rmw_zenoh_cpp "
            f'ZENOH_CONFIG_OVERRIDE=\'mode="client";connect/endpoints=["{endpoint}"]\'',
            f"  export ROS_DOMAIN_ID={ros2.domain_id} ZENOH_ROUTER_CHECK_ATTEMPTS=-1",
            "  ros2 daemon stop",
            f"  ros2 topic echo {states}",
        ]
    lines.append("Ctrl-C stops the demo.")
    return "\n".join(lines)


def _endpoint(config: Config) -> str:
    """Where clients reach the demo: the router it joined, or where it listens."""
    return (config.zenoh.connect or config.zenoh.listen)[0]


def _program() -> str:
    """``busgate`` as the user started it, by its absolute path (``.venv/bin/busgate`` in the
    README: a second terminal opens in another directory), so the hints work wherever they
    are pasted; plain ``busgate`` when that is what PATH finds, or when started some other
    way (``python -m``)."""
    started = Path(sys.argv[0])
    on_path = shutil.which("busgate")
    if started.name != "busgate" or (on_path and Path(on_path).resolve() == started.resolve()):
        return "busgate"
    return shlex.quote(str(started.absolute()))


async def _serve_announcing(
    config: Config,
    links: dict[str, dict[str, Any]],
    dashboard: Listen | None,
    bound: socket.socket | None,
) -> None:
    """``serve`` (and the dashboard) until SIGTERM/SIGINT, printing the hints once both serve.
    A dashboard that cannot listen stops the gateway too, and its error is raised."""
    stop = stop_on_signals(asyncio.get_running_loop())
    ready = threading.Event()  # set by ``serve`` on this loop's thread
    serving = asyncio.create_task(serve(config, ready=ready, stop=stop))
    while not (ready.is_set() or serving.done()):
        await asyncio.wait({serving}, timeout=READY_POLL_S)
    if not ready.is_set():
        await serving  # its error
        return
    url: str | None = None
    showing: asyncio.Task | None = None
    if dashboard is not None:
        shown: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        showing = asyncio.create_task(_dashboard(config, dashboard, stop, shown.set_result, bound))
        await asyncio.wait({shown, showing}, return_when=asyncio.FIRST_COMPLETED)
        if not shown.done():
            signalled = stop.is_set()  # a Ctrl-C while it started: the gateway stops anyway
            stop.set()
            await serving
            if signalled:  # what the dashboard said meanwhile (its session found no gateway)
                try:
                    await showing
                except Exception:  # a stop is what the user asked for: kept for a debug log
                    log.debug("the dashboard's start, stopped by a signal", exc_info=True)
                return
            await showing  # its error
        url = shown.result()
    print(_hints(config, links, url), flush=True)
    await serving
    if showing is not None:
        await showing


async def _dashboard(
    config: Config,
    listen: Listen,
    stop: asyncio.Event,
    on_ready: Callable[[str], None],
    bound: socket.socket | None,
) -> None:
    client = await aio.connect(_endpoint(config), client_id=f"busgate-demo-{os.getpid()}")
    try:
        await serve_dashboard(client, listen, stop, on_ready=on_ready, bound=bound)
    finally:
        await client.close()
