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
4. The hints are printed only once the gateway serves, and they are commands that work as
   printed: ``--connect`` appears when the endpoint is not the client tools' default.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import shlex
import shutil
import sys
import threading
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from busgate.gateway.cli.client_session import DEFAULT_ENDPOINT
from busgate.gateway.service.daemon import serve
from busgate.gateway.sim.models import make_devices
from busgate.schemas.config import Config, parse_config
from busgate.schemas.families import PROTOCOLS

GATEWAY_NAME = "demo"
HEARTBEAT_MS = 100
READY_POLL_S = 0.05
TRY_COMMAND = '{"op":"move","position":1500}'


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


#: One bus per protocol of every family, at the protocol's default rate (the registry's demo).
DEMO_BUSES = tuple(
    DemoBus(p.demo.bus, p.name, p.timing.default_rate, p.demo.devices) for p in PROTOCOLS.values()
)


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    demo = subparsers.add_parser(
        "demo",
        description="Run the real gateway (named 'demo') on simulated devices: three Inspire LA "
        "actuators and two DS servos on UART buses, a ZLAC706 on CAN and one on RS232, with "
        "wire timing emulated. Prints how to connect; serves until SIGTERM or Ctrl-C.",
    )
    demo.add_argument(
        "--listen",
        default=DEFAULT_ENDPOINT,
        metavar="ENDPOINT",
        help=f"zenoh endpoint to listen on (default {DEFAULT_ENDPOINT})",
    )
    demo.add_argument(
        "--metrics-listen",
        default=None,
        metavar="HOST:PORT",
        help="serve Prometheus metrics here (default: off)",
    )
    demo.set_defaults(handler=run_demo)


def run_demo(args: argparse.Namespace) -> int:
    logging.basicConfig(level="INFO", format="%(levelname)s %(name)s: %(message)s")
    with contextlib.ExitStack() as simulators:
        links = {bus.name: _start_simulator(bus, simulators) for bus in DEMO_BUSES}
        config = demo_config(links, listen=args.listen, metrics_listen=args.metrics_listen)
        asyncio.run(_serve_announcing(config, _hints(config, links)))
    return 0


def _start_simulator(bus: DemoBus, stack: contextlib.ExitStack) -> dict[str, Any]:
    """Start ``bus``'s simulator (stopped when ``stack`` closes); return the config keys that
    lead the gateway to it."""
    protocol = PROTOCOLS[bus.protocol]
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
            )
        )
        return {"transport": "can", "interface": "virtual", "channel": channel, "bitrate": bus.rate}
    from busgate.gateway.sim.serial_server import SerialSimulator

    simulator = stack.enter_context(SerialSimulator(protocol.codec, devices, baudrate=bus.rate))
    return {"transport": "serial", "port": simulator.port, "baudrate": bus.rate}


def demo_config(
    links: dict[str, dict[str, Any]], *, listen: str, metrics_listen: str | None = None
) -> Config:
    """The demo gateway's config, validated; ``links`` holds each bus's port or channel keys.
    Raises ``ConfigError`` (naming the key) for a bad endpoint or metrics address."""
    document: dict[str, Any] = {
        "gateway": {"name": GATEWAY_NAME},
        "zenoh": {"mode": "peer", "listen": [listen]},
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
                    }
                    for name, ident in bus.devices
                ],
            }
            for bus in DEMO_BUSES
        ],
    }
    if metrics_listen is not None:
        document["metrics"] = {"listen": metrics_listen}
    return parse_config(document)


def _hints(config: Config, links: dict[str, dict[str, Any]]) -> str:
    """What the demo serves, and two commands to try from another terminal."""
    [listen] = config.zenoh.listen
    connect = "" if listen == DEFAULT_ENDPOINT else f" --connect {shlex.quote(listen)}"
    lines = [f"busgate demo: gateway {config.gateway.name!r} is serving on {listen}"]
    for bus in config.buses:
        link = links[bus.name]
        where = (
            f"{link['port']} at {link['baudrate']} baud"
            if "port" in link
            else f"virtual CAN {link['channel']} at {link['bitrate']} bit/s"
        )
        names = ", ".join(device.name for device in bus.devices)
        lines.append(f"  {bus.name:<6} {bus.protocol:<14} {names:<15} {where}")
    first, program = config.buses[0].devices[0].name, _program()
    lines += [
        "From another terminal, move an actuator and watch every device:",
        f"  {program} send {first} {shlex.quote(TRY_COMMAND)}{connect}",
        f"  {program} watch {config.gateway.name}{connect}",
        "Ctrl-C stops the demo.",
    ]
    return "\n".join(lines)


def _program() -> str:
    """``busgate`` as the user started it (``.venv/bin/busgate`` in the README), so the hints
    work from another terminal in the same directory; plain ``busgate`` when that is what
    PATH finds, or when started some other way (``python -m``)."""
    started = Path(sys.argv[0])
    on_path = shutil.which("busgate")
    if started.name != "busgate" or (on_path and Path(on_path).resolve() == started.resolve()):
        return "busgate"
    return shlex.quote(sys.argv[0])


async def _serve_announcing(config: Config, announcement: str) -> None:
    """``serve`` until SIGTERM/SIGINT, printing ``announcement`` once it serves."""
    ready = threading.Event()  # set by ``serve`` on this loop's thread
    serving = asyncio.create_task(serve(config, ready=ready))
    while not (ready.is_set() or serving.done()):
        await asyncio.wait({serving}, timeout=READY_POLL_S)
    if ready.is_set():
        print(announcement, flush=True)
    await serving
