"""A fleet on one machine, for ``tests/test_fleet.py`` and ``benchmarks/bench_fleet.py``: one
``busgate router``, gateways that join it (``busgate demo --connect``, each a process with its
own simulated devices of every kind, recording every frame its devices receive), and
``busgate dashboard`` connected to the router.

Each gateway is a host of its own where this machine allows it (root, and ``ip netns``): a
network namespace made here, joined to this one by a veth pair, the router listening on this
side's address of each pair (and on loopback, for the dashboard and the tests' clients), the
gateway connecting from the other side. Elsewhere every process is on a loopback port of its
own. No traffic leaves loopback or the pairs made here.

The wire records are the evidence of what reached a device: JSON lines with
``time.perf_counter()`` times, which on Linux is CLOCK_MONOTONIC, the same clock in every
process of the machine (``busgate.gateway.sim.recorder``).
"""

from __future__ import annotations

import contextlib
import math
import os
import secrets
import shutil
import signal
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from busgate.codecs.can_frame import CanFrame
from busgate.gateway.cli.demo import DEMO_BUSES, DemoBus
from busgate.gateway.drivers.families import make_driver
from busgate.gateway.sim.recorder import WireRecord
from busgate.schemas.config import DeviceConfig
from busgate.schemas.families import PROTOCOLS
from tests.conftest import unused_loopback_port
from tests.gateway_process import DemoProcess, ServingProcess

DEVICES_PER_GATEWAY = sum(len(bus.devices) for bus in DEMO_BUSES)
#: How far before the moment looked after a record is still read: records are in the order
#: their frames arrived, give or take a reader thread's turn.
LOOK_BACK_S = 1.0


class Tail:
    """The frames a bus's devices received, from the record its simulator is writing: each
    look reads only what was added since the last (a line not yet ended waits for the next)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.received: list[WireRecord] = []
        self.unreadable = 0  # lines that did not parse (none are expected)
        self._offset = 0

    def read(self) -> list[WireRecord]:
        with contextlib.suppress(FileNotFoundError), self.path.open("rb") as stream:
            stream.seek(self._offset)
            added = stream.read()
            ended = added.rfind(b"\n") + 1
            self._offset += ended
            for line in added[:ended].splitlines():
                try:
                    record = WireRecord.from_json(line.decode())
                except (ValueError, KeyError):
                    self.unreadable += 1
                    continue
                if record.direction == "rx":
                    self.received.append(record)
        return self.received


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


class Hosts:
    """Network namespaces joined to this one by veth pairs, one per gateway (``add``), made
    on a subnet 10.<random>.<n>.0/24 and removed by ``close``."""

    def __init__(self) -> None:
        self._token = secrets.token_hex(2)
        self._subnet = 100 + secrets.randbelow(150)
        self._made: list[str] = []

    @staticmethod
    def possible() -> bool:
        """Namespaces can be made here (root, ``ip``): tried with one."""
        if os.geteuid() != 0 or shutil.which("ip") is None:
            return False
        probe = f"bgprobe-{secrets.token_hex(3)}"
        made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, check=False)
        if made.returncode != 0:
            return False
        subprocess.run(["ip", "netns", "del", probe], capture_output=True, check=True)
        return True

    def add(self, n: int) -> tuple[str, list[str]]:
        """Host ``n``: (this side's address of its pair, the command prefix that runs in it)."""
        namespace = f"bgfleet-{self._token}-{n}"
        here, there = f"bg{self._token}{n}h", f"bg{self._token}{n}g"
        near, far = f"10.{self._subnet}.{n}.1", f"10.{self._subnet}.{n}.2"
        inside = ["ip", "netns", "exec", namespace]
        for command in (["ip", "netns", "add", namespace],
                        ["ip", "link", "add", here, "type", "veth", "peer", "name", there],
                        ["ip", "link", "set", there, "netns", namespace],
                        ["ip", "addr", "add", f"{near}/24", "dev", here],
                        ["ip", "link", "set", here, "up"],
                        [*inside, "ip", "addr", "add", f"{far}/24", "dev", there],
                        [*inside, "ip", "link", "set", there, "up"],
                        [*inside, "ip", "link", "set", "lo", "up"]):
            subprocess.run(command, capture_output=True, check=True)
            if command[1:3] == ["netns", "add"]:
                self._made.append(namespace)
        return near, inside

    def close(self) -> None:
        """Remove the namespaces (and with each, its pair)."""
        for namespace in self._made:
            subprocess.run(["ip", "netns", "del", namespace], capture_output=True, check=False)
        self._made.clear()


@dataclass
class Gateway:
    name: str
    records: Path
    connect: str  # the router's endpoint as the gateway reaches it
    within: list[str] = field(default_factory=list)  # its host's command prefix (netns)
    process: DemoProcess | None = None

    tails: dict[str, Tail] = field(default_factory=dict)

    def received(self, bus: str) -> list[WireRecord]:
        """What ``bus``'s devices received so far (since the gateway last started)."""
        tail = self.tails.setdefault(bus, Tail(self.records / f"{bus}.jsonl"))
        return tail.read()


@dataclass
class Fleet:
    router: str  # its endpoint
    gateways: dict[str, Gateway]
    records: Path  # where each gateway's folder of wire records goes
    on_hosts: bool  # each gateway in a network namespace of its own
    dashboard: str = ""  # its URL
    dashboard_pid: int = 0
    _processes: list[ServingProcess] = field(default_factory=list)

    def start_gateway(self, name: str) -> None:
        gateway = self.gateways[name]
        gateway.tails.clear()  # its records are written anew
        gateway.process = DemoProcess(
            gateway.connect, "--connect", gateway.connect, "--name", name, "--no-dashboard",
            "--record", str(gateway.records), within=gateway.within)

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
                for record in reversed(gateway.received(bus.name)):
                    if record.start < moment - LOOK_BACK_S:  # in order, near enough
                        break
                    for ident, wire in wires.items():
                        key = (gateway.name, bus.name, ident)
                        if record.start > moment and record.wire == wire:
                            found[key] = min(record.start, found.get(key, math.inf))
        return found

    def expected_stops(self) -> set[tuple[str, str, int]]:
        return {(g, bus.name, ident) for g in self.gateways for bus in DEMO_BUSES
                for _, ident in bus.devices}


@contextlib.contextmanager
def running_fleet(tmp_path: Path, names: list[str], *, hosts: bool = True) -> Iterator[Fleet]:
    """A router, a gateway for each name (each on a host of its own when ``hosts`` and this
    machine allows it), and the dashboard; every process stopped by its PID after, and the
    hosts removed."""
    port = unused_loopback_port()
    router_endpoint = f"tcp/127.0.0.1:{port}"
    network = Hosts() if hosts and Hosts.possible() else None
    fleet = Fleet(router_endpoint, {}, tmp_path, on_hosts=network is not None)
    try:
        listen = [router_endpoint]
        for n, name in enumerate(names, start=1):
            connect, within = router_endpoint, []
            if network is not None:
                near, within = network.add(n)
                connect = f"tcp/{near}:{port}"
                listen.append(connect)
            fleet.gateways[name] = Gateway(name, tmp_path / name, connect, within)
        router = ServingProcess("router", *(f"--listen={e}" for e in listen),
                                ready="busgate router")
        fleet._processes.append(router)
        for name in names:
            fleet.start_gateway(name)
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
        if network is not None:
            network.close()
