"""A fleet on one machine, for ``tests/test_fleet.py`` and ``benchmarks/bench_fleet.py``: one
``busgate router``, gateways that join it (``busgate demo --connect``, each a process with its
own simulated devices of every kind, recording every frame its devices receive), and
``busgate dashboard`` connected to the router, each on its own loopback port.

The wire records are the evidence of what reached a device: JSON lines with
``time.perf_counter()`` times, which on Linux is CLOCK_MONOTONIC, the same clock in every
process of the machine (``busgate.gateway.sim.recorder``).
"""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from busgate.codecs.can_frame import CanFrame
from busgate.gateway.cli.demo import DEMO_BUSES, DemoBus
from busgate.gateway.drivers.families import make_driver
from busgate.gateway.sim.recorder import WireRecord
from busgate.gateway.sim.wire_analysis import load_records
from busgate.schemas.config import DeviceConfig
from busgate.schemas.families import PROTOCOLS
from tests.conftest import unused_loopback_port
from tests.gateway_process import DemoProcess, ServingProcess

DEVICES_PER_GATEWAY = sum(len(bus.devices) for bus in DEMO_BUSES)


def received(path: Path) -> list[WireRecord]:
    """The frames a bus's devices received so far, from its record."""
    return [r for r in load_records(path) if r.direction == "rx"] if path.exists() else []


def _wire(wire: bytes | CanFrame) -> str:
    return str(wire) if isinstance(wire, CanFrame) else wire.hex()


def safe_stop_wires(bus: DemoBus) -> dict[int, str]:
    """Each device's last e-stop frame (what leaves it in its safe state), as recorded: the
    frames the gateway's own drivers send."""
    protocol = PROTOCOLS[bus.protocol]
    wires = {}
    for name, ident in bus.devices:
        driver = make_driver(DeviceConfig(name=name, kind=protocol.kind, id=ident), protocol)
        wires[ident] = _wire(driver.safe_stop()[-1].wire)
    return wires


@dataclass
class Gateway:
    name: str
    records: Path
    process: DemoProcess | None = None

    def record(self, bus: str) -> Path:
        return self.records / f"{bus}.jsonl"


@dataclass
class Fleet:
    router: str  # its endpoint
    gateways: dict[str, Gateway]
    records: Path  # where each gateway's folder of wire records goes
    dashboard: str = ""  # its URL
    dashboard_pid: int = 0
    _processes: list[ServingProcess] = field(default_factory=list)

    def add_gateway(self, name: str) -> None:
        self.gateways[name] = Gateway(name, self.records / name)
        self.start_gateway(name)

    def start_gateway(self, name: str) -> None:
        gateway = self.gateways[name]
        gateway.process = DemoProcess(
            self.router, "--connect", self.router, "--name", name, "--no-dashboard",
            "--record", str(gateway.records))

    def kill_gateway(self, name: str) -> None:
        """As a crash or a power cut: SIGKILL, nothing said on the way out."""
        process = self.gateways[name].process
        assert process is not None
        process.terminate(signal.SIGKILL)
        self.gateways[name].process = None

    def estop_frames_after(self, moment: float) -> dict[tuple[str, str, int], float]:
        """When each device of each gateway first received its e-stop frame after
        ``moment`` (perf_counter seconds): ``(gateway, bus, device id) → start``."""
        found = {}
        for gateway in self.gateways.values():
            for bus in DEMO_BUSES:
                wires = safe_stop_wires(bus)
                for record in received(gateway.record(bus.name)):
                    for ident, wire in wires.items():
                        key = (gateway.name, bus.name, ident)
                        if record.start > moment and record.wire == wire and key not in found:
                            found[key] = record.start
        return found

    def expected_stops(self) -> set[tuple[str, str, int]]:
        return {(g, bus.name, ident) for g in self.gateways for bus in DEMO_BUSES
                for _, ident in bus.devices}


@contextlib.contextmanager
def running_fleet(tmp_path: Path, names: list[str]) -> Iterator[Fleet]:
    """A router, a gateway for each name, and the dashboard, stopped (each by its PID) after."""
    router_endpoint = f"tcp/127.0.0.1:{unused_loopback_port()}"
    router = ServingProcess("router", "--listen", router_endpoint, ready="busgate router")
    fleet = Fleet(router_endpoint, {}, tmp_path)
    fleet._processes.append(router)
    try:
        for name in names:
            fleet.add_gateway(name)
        dashboard = ServingProcess("dashboard", "--connect", router_endpoint, "--listen",
                                   "127.0.0.1:0", ready="busgate dashboard")
        fleet._processes.append(dashboard)
        fleet.dashboard = dashboard.printed.split()[-1]
        fleet.dashboard_pid = dashboard.process.pid
        yield fleet
    finally:
        for gateway in fleet.gateways.values():
            if gateway.process is not None:
                gateway.process.terminate()
        for process in reversed(fleet._processes):
            process.terminate()
